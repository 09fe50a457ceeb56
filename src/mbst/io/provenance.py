"""Which code produced a result.

Snakemake re-runs a rule when its shell command, its params or its inputs
change, but it does not see Python code imported by the command. The workflow
therefore passes :func:`source_hash` as a rule parameter: any edit to a ``.py``
file of the installed ``mbst`` package changes the hash, and with it the
parameter, so every result made by the old code is rebuilt.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

import mbst

HASH_CHARS = 16


def package_dir() -> Path:
    """Folder of the installed ``mbst`` package (``src/mbst`` for an editable install)."""
    return Path(mbst.__file__).resolve().parent


def source_files(root: Path | None = None) -> list[Path]:
    """The package's ``.py`` files, sorted by their path relative to ``root``."""
    root = package_dir() if root is None else Path(root)
    files = [p for p in root.rglob("*.py") if "__pycache__" not in p.relative_to(root).parts]
    return sorted(files, key=lambda p: p.relative_to(root).as_posix())


def source_hash(root: Path | None = None) -> str:
    """sha256 over the sorted ``.py`` files of the package: first 16 hex characters.

    Each file contributes its relative path and its bytes, so adding, removing,
    renaming or editing a module changes the hash; timestamps and byte-code
    caches do not.
    """
    root = package_dir() if root is None else Path(root)
    h = hashlib.sha256()
    for path in source_files(root):
        rel = path.relative_to(root).as_posix().encode()
        data = path.read_bytes()
        h.update(len(rel).to_bytes(8, "little") + rel)
        h.update(len(data).to_bytes(8, "little") + data)
    return h.hexdigest()[:HASH_CHARS]
