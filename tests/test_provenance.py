"""Tests for mbst.io.provenance: the code-version hash the workflow uses as a rule param."""

from __future__ import annotations

import re
from pathlib import Path

from mbst.io.provenance import package_dir, source_files, source_hash


def make_pkg(root: Path) -> Path:
    (root / "sub").mkdir(parents=True)
    (root / "__init__.py").write_text("x = 1\n")
    (root / "sub" / "mod.py").write_text("def f():\n    return 2\n")
    return root


def test_installed_package_hash_is_16_hex_and_stable():
    h = source_hash()
    assert re.fullmatch(r"[0-9a-f]{16}", h)
    assert source_hash() == h
    assert (package_dir() / "io" / "provenance.py") in source_files()


def test_edit_changes_hash(tmp_path):
    root = make_pkg(tmp_path / "pkg")
    before = source_hash(root)
    (root / "sub" / "mod.py").write_text("def f():\n    return 3\n")
    assert source_hash(root) != before


def test_rename_and_new_file_change_hash(tmp_path):
    root = make_pkg(tmp_path / "pkg")
    before = source_hash(root)
    (root / "sub" / "mod.py").rename(root / "sub" / "other.py")
    renamed = source_hash(root)
    assert renamed != before
    (root / "new.py").write_text("")
    assert source_hash(root) != renamed


def test_ignores_non_python_and_bytecode_and_mtime(tmp_path):
    root = make_pkg(tmp_path / "pkg")
    before = source_hash(root)
    (root / "__pycache__").mkdir()
    (root / "__pycache__" / "x.py").write_text("cached")
    (root / "notes.txt").write_text("not code")
    (root / "kernel.nbi").write_bytes(b"\x00numba cache")
    (root / "__init__.py").touch()
    assert source_hash(root) == before


def test_same_content_elsewhere_same_hash(tmp_path):
    assert source_hash(make_pkg(tmp_path / "a")) == source_hash(make_pkg(tmp_path / "b"))
