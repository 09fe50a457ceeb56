"""One table of FIT % over campaigns: ``results/summary.csv``.

Reads, for each per-campaign result folder ``results/<campaign>``:

- ``identify/correlation.csv`` (required): the base model's correlation,
  one row per (test, channel) → ``model = "base"``;
- ``discover/discovery.json`` (optional, skipped silently when absent): the
  extended model's ``control_fit_percent`` → ``model = "extended"``.

and writes one CSV with the columns :data:`COLUMNS`, atomically (temporary
name in the same folder, then rename), so a reader never sees half a table.
"""

from __future__ import annotations

import csv
import json
import math
from collections.abc import Iterable
from pathlib import Path

from mbst.io.outputs import atomic_text

COLUMNS = ("campaign", "test", "channel", "model", "fit_percent")
CORRELATION = Path("identify") / "correlation.csv"
DISCOVERY_CANDIDATES = (Path("discover") / "discovery.json", Path("discovery.json"))
REQUIRED_CORRELATION_COLUMNS = ("test", "channel", "fit_percent")


def write_summary(result_dirs: list[Path], out_csv: Path) -> Path:
    """Collect the per-campaign results in ``result_dirs`` into ``out_csv``; return its path.

    The campaign name is the result folder's name. Raises ``FileNotFoundError``
    naming the folder when its ``identify/correlation.csv`` is missing and
    ``ValueError`` for a malformed correlation table or discovery file; in
    both cases nothing is written.
    """
    dirs = [Path(d) for d in result_dirs]
    if not dirs:
        raise ValueError("no result folders given (expected results/<campaign> ...)")
    rows: list[dict[str, object]] = []
    for d in dirs:
        campaign = d.resolve().name if d.name in ("", ".", "..") else d.name
        rows.extend(_base_rows(d, campaign))
        rows.extend(_extended_rows(d, campaign))
    return _write_csv_atomic(Path(out_csv), rows)


def _base_rows(result_dir: Path, campaign: str) -> Iterable[dict[str, object]]:
    path = result_dir / CORRELATION
    if not path.is_file():
        raise FileNotFoundError(
            f"result folder '{result_dir}' has no {CORRELATION.as_posix()} "
            f"(has 'mbst identify' been run for campaign '{campaign}'?)"
        )
    with path.open(newline="") as fh:
        reader = csv.DictReader(fh)
        header = [c.strip() for c in (reader.fieldnames or [])]
        missing = [c for c in REQUIRED_CORRELATION_COLUMNS if c not in header]
        if missing:
            raise ValueError(f"{path}: missing column(s) {', '.join(missing)}")
        reader.fieldnames = header
        rows = []
        for line, rec in enumerate(reader, start=2):
            rows.append({
                "campaign": campaign,
                "test": rec["test"].strip(),
                "channel": rec["channel"].strip(),
                "model": "base",
                "fit_percent": _number(rec["fit_percent"], f"{path}, line {line}"),
            })
    return rows


def _extended_rows(result_dir: Path, campaign: str) -> Iterable[dict[str, object]]:
    path = next((result_dir / c for c in DISCOVERY_CANDIDATES if (result_dir / c).is_file()),
                None)
    if path is None:
        return []
    try:
        doc = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path}: not valid JSON ({exc})") from None
    fits = (doc.get("extended") or {}).get("control_fit_percent") if isinstance(doc, dict) else None
    if fits is None:
        return []
    if not isinstance(fits, dict):
        raise _malformed(path, "'extended.control_fit_percent' is not a mapping")
    rows = []
    for test, per_channel in fits.items():
        if not isinstance(per_channel, dict):
            raise _malformed(path, f"'extended.control_fit_percent.{test}' is not a mapping")
        for channel, fit in per_channel.items():
            rows.append({
                "campaign": campaign,
                "test": str(test),
                "channel": str(channel),
                "model": "extended",
                "fit_percent": _number(fit, f"{path}, test {test}, channel {channel}"),
            })
    return rows


def _malformed(path: Path, what: str) -> ValueError:
    """A discovery file of the wrong shape is bad input (ValueError), not a programming error."""
    return ValueError(f"{path}: {what}")


def _number(value: object, where: str) -> float:
    try:
        x = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise ValueError(f"{where}: fit_percent '{value}' is not a number") from None
    return x


def _format(value: object) -> object:
    if isinstance(value, float):
        return "nan" if math.isnan(value) else repr(value)
    return value


def _write_csv_atomic(out_csv: Path, rows: list[dict[str, object]]) -> Path:
    with atomic_text(out_csv, newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=COLUMNS, lineterminator="\n")
        writer.writeheader()
        for row in rows:
            writer.writerow({k: _format(v) for k, v in row.items()})
    return out_csv
