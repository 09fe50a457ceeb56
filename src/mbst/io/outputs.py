"""Writing results so that a killed run leaves nothing half-written."""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TextIO


def _plain(obj):
    import numpy as np

    if isinstance(obj, dict):
        return {str(k): _plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_plain(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _plain(obj.tolist())
    if isinstance(obj, (np.floating, float)):
        f = float(obj)
        return f if np.isfinite(f) else None
    if isinstance(obj, (np.integer,)):
        return int(obj)
    if isinstance(obj, np.bool_):
        return bool(obj)
    return obj


@contextmanager
def atomic_text(path: str | Path, newline: str | None = None) -> Iterator[TextIO]:
    """A text handle on a temporary name in the same folder, renamed to ``path`` on success.

    A reader (or a killed run) never sees half a file; on error nothing is left.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "w", newline=newline) as fh:
            yield fh
        os.chmod(tmp, 0o644)  # mkstemp makes it private; results are for the team
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def write_json(path: str | Path, obj: dict) -> Path:
    """JSON (NaN/inf as null), written atomically."""
    with atomic_text(path) as fh:
        json.dump(_plain(obj), fh, indent=2)
        fh.write("\n")
    return Path(path)


_HTML_PAGE = """<!DOCTYPE html>
<html><head><meta charset="utf-8"><title>{title}</title>
<style>
body {{ font-family: system-ui, sans-serif; font-size: 14px; margin: 1.5em; color: #222; }}
table {{ border-collapse: collapse; margin: 0.8em 0; }}
th, td {{ border: 1px solid #ccc; padding: 3px 8px; text-align: left; }}
th {{ background: #eef3f7; }}
tr:nth-child(even) td {{ background: #fafafa; }}
code {{ background: #f3f3f3; padding: 0 3px; }}
</style></head><body>
{body}
</body></html>
"""


def write_markdown(path: str | Path, text: str) -> Path:
    """A Markdown summary and its HTML rendering beside it (``.html``), both atomically.

    The Snakemake report shows HTML results inline but offers Markdown only as a
    download, so the tables an engineer reads first go into the report as HTML.
    """
    import markdown

    path = Path(path)
    with atomic_text(path) as fh:
        fh.write(text)
    first = next((ln.lstrip("# ").strip() for ln in text.splitlines() if ln.strip()), path.stem)
    body = markdown.markdown(text, extensions=["tables", "fenced_code"])
    with atomic_text(path.with_suffix(".html")) as fh:
        fh.write(_HTML_PAGE.format(title=first.replace("`", ""), body=body))
    return path


def output_dir_problem(out_dir: str | Path, keep: str | Path | None = None) -> str | None:
    """Why ``out_dir`` cannot take a command's results, before any work is done, or None.

    The results replace ``out_dir`` whole, so it must not be (or hold) ``keep``, the
    input the command reads (e.g. the campaign), nor an existing file; and its nearest
    existing parent must be a folder this user can write in.
    """
    out = Path(out_dir).absolute()
    if out.exists() and not out.is_dir():
        return f"--out {out_dir}: is a file, not a folder; results would replace it"
    if keep is not None:
        kept = Path(keep).absolute()
        if out.resolve() == kept.resolve() or out.resolve() in kept.resolve().parents:
            return (f"--out {out_dir}: the results replace this folder whole, and it holds "
                    f"the input {keep}; choose another folder")
    parent = out.parent
    while not parent.exists() and parent != parent.parent:
        parent = parent.parent
    try:  # a real probe: permissions alone do not say it (root, read-only or virtual file systems)
        probe = tempfile.mkdtemp(prefix=".mbst-probe-", dir=parent)
        os.rmdir(probe)
    except OSError as exc:
        return f"--out {out_dir}: cannot create it under {parent} ({exc.strerror or exc})"
    return None


@contextmanager
def atomic_output_dir(out_dir: str | Path) -> Iterator[Path]:
    """Yield a temporary sibling folder; on success it replaces ``out_dir`` whole."""
    out = Path(out_dir)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.tmp-", dir=out.parent))
    os.chmod(tmp, 0o755)  # mkdtemp makes it private; results are for the team
    try:
        yield tmp
        if out.exists():
            old = Path(tempfile.mkdtemp(prefix=f".{out.name}.old-", dir=out.parent))
            os.replace(out, old / out.name)
            os.replace(tmp, out)
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.replace(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
