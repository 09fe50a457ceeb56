"""Converter from the published friction-damper data set to an mbst campaign.

``import_friction_damper``: the banded rotary friction device of Coble et al.
(ARTS Lab, CC BY-SA 4.0; shared/data/real/friction-damper/README.md) → a
``friction-damper`` campaign, one test per JSON file. Units are converted to
SI after the unit names the file declares are checked. Characterization
(sine) tests identify, earthquake tests are held-out controls unless
``control`` (a glob over file names) picks others. The makers' LuGre
predictions (``published/lugre_<test>.csv``), where present, are scored
against the measured force over their window and written with the test, so
that ``benchmark.json`` can set the extended model beside them.
"""

from __future__ import annotations

import fnmatch
import hashlib
import json
import logging
import re
from pathlib import Path

import numpy as np
import pandas as pd

from mbst.core.metrics import error_scores
from mbst.io.campaign import CampaignError, TestSpec, write_campaign
from mbst.systems.friction_damper.channels import SYSTEM_NAME

log = logging.getLogger(__name__)

INCH_M = 0.0254
KIP_N = 4448.2216152605
LB_N = 4.4482216152605
# the file's columns, and the unit each must declare (key in the file: unit name); the
# data set's six-column layout (datasets 1-3) and its eight-column one (dataset 4, two
# actuator positions before the forces, their unit the displacement's: none declared)
COLUMNS = (("time_s", "time units", "s", 1.0),
           ("displacement_m", "displacement units", "in", INCH_M),
           ("friction_force_n", "friction force units", "kip", KIP_N),
           ("velocity_m_per_s", None, None, INCH_M),  # in/s, follows the displacement
           ("actuator_force_1_n", "actuator force units", "lb", LB_N),
           ("actuator_force_2_n", "actuator force units", "lb", LB_N))
COLUMNS_8 = COLUMNS[:4] + (("actuator_position_1_m", None, None, INCH_M),
                           ("actuator_position_2_m", None, None, INCH_M)) + COLUMNS[4:]
SINE_NAME = re.compile(r"(?P<f>[\d.]+)Hz(?P<t>[\d.]+)lbtension((?P<a>[\d.]+)amplitude)?$")
# a folder's tests are identification when its name starts so ("characterization",
# "characterization datasets", "characterization tests"), else held-out controls
# (earthquake and wind profiles: recorded histories); files beside them identify
IDENTIFICATION_FOLDERS = "characterization"
NOT_TESTS = ("published",)


def test_id_of(stem: str) -> str:
    """A file-safe test id: the file's stem with its decimal points written ``p``."""
    return stem.replace(".", "p")


def _read(path: Path, campaign: str) -> pd.DataFrame:
    try:
        doc = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise CampaignError(f"cannot read as JSON ({exc})", campaign=campaign, path=path) from None
    if not isinstance(doc, dict) or "data" not in doc:
        raise CampaignError("no 'data' matrix", campaign=campaign, path=path)
    for _col, key, unit, _scale in COLUMNS:
        if key is not None and doc.get(key) != unit:
            raise CampaignError(f"'{key}' is {doc.get(key)!r}, expected '{unit}'",
                                campaign=campaign, path=path)
    try:
        data = np.asarray(doc["data"], dtype=float)
    except (TypeError, ValueError):
        raise CampaignError("'data' is not a numeric matrix", campaign=campaign,
                            path=path) from None
    if data.ndim != 2 or data.shape[1] < 3 or len(data) < 10:
        raise CampaignError(f"'data' has shape {data.shape}, expected rows × (time, "
                            "displacement, force, ...)", campaign=campaign, path=path)
    layout = COLUMNS_8 if data.shape[1] == len(COLUMNS_8) else COLUMNS
    cols = {}
    for j, (col, _key, _unit, scale) in enumerate(layout[:data.shape[1]]):
        bad = np.flatnonzero(~np.isfinite(data[:, j]))
        if bad.size:
            raise CampaignError(f"column {j + 1} ({col}) is not finite", campaign=campaign,
                                path=path, row=int(bad[0]) + 1)
        cols[col] = data[:, j] * scale
    return pd.DataFrame(cols)


def _input_of(stem: str, source: str, displacement_m: np.ndarray) -> dict:
    """A sine test's frequency, amplitude and band tension from its file name (dataset 1
    names no amplitude: half the measured stroke), else a recorded history."""
    m = SINE_NAME.match(stem)
    if m:
        amplitude = (float(m["a"]) * INCH_M if m["a"] is not None
                     else 0.5 * float(np.ptp(displacement_m)))
        return {"kind": "sine", "frequency_hz": float(m["f"]),
                "amplitude_m": round(amplitude, 6),
                "band_tension_n": round(float(m["t"]) * LB_N, 3)}
    return {"kind": "recorded", "source": source}


def _published(data_dir: Path, stem: str, force_n: np.ndarray, campaign: str) -> dict | None:
    """The makers' LuGre prediction scored on its window (None when not published)."""
    path = data_dir / "published" / f"lugre_{stem}.csv"
    if not path.is_file():
        return None
    lug = pd.read_csv(path)
    if not {"sample_index", "lugre_force_n"} <= set(lug.columns):
        raise CampaignError("expected columns sample_index, lugre_force_n", campaign=campaign,
                            path=path)
    idx = lug["sample_index"].to_numpy(int)
    if idx.min() < 0 or idx.max() >= len(force_n) or np.any(np.diff(idx) != 1):
        raise CampaignError("sample_index is not a contiguous window of the test",
                            campaign=campaign, path=path)
    e = error_scores(force_n[idx], lug["lugre_force_n"].to_numpy(float))
    return {"model": "LuGre (the data set's makers)", "source": f"published/{path.name}",
            "window_samples": [int(idx[0]), int(idx[-1])],
            "fit_percent": round(e["fit_percent"], 3), "rmse_n": round(e["rmse"], 3),
            "nrmse": round(e["nrmse"], 5)}


def _mixed_tensions(specs: list[TestSpec]) -> str:
    """What to say when the sine tests were run at several band tensions (the data set's
    dataset 2 mixes 0, 30 and 36 lb): the family's model has one friction level."""
    lbs = sorted({round(s.input["band_tension_n"] / LB_N, 3) for s in specs
                  if "band_tension_n" in s.input})
    if len(lbs) < 2:
        return ""
    listed = ", ".join(f"{v:g}" for v in lbs)
    return (f"the sine tests were run at band tensions of {listed} lb; the model has one "
            "friction level per campaign, so import one tension at a time (a folder each)")


def _files(data_dir: Path, campaign: str) -> list[tuple[Path, str]]:
    """Every test file with its default role: the data set's folders as published
    ("characterization datasets", "earthquake profiles", ...) or as shared here
    ("characterization", "earthquake"), and files directly in ``data_dir``."""
    files = [(p, "identification") for p in sorted(data_dir.glob("*.json"))]
    for folder in sorted(d for d in data_dir.iterdir() if d.is_dir()) \
            if data_dir.is_dir() else ():
        if folder.name in NOT_TESTS:
            continue
        role = ("identification" if folder.name.lower().startswith(IDENTIFICATION_FOLDERS)
                else "control")
        files += [(p, role) for p in sorted(folder.glob("*.json"))]
    if not files:
        raise CampaignError("no test files (*.json in the folder or in its characterization"
                            " and earthquake folders)", campaign=campaign, path=data_dir)
    return files


def import_friction_damper(data_dir: str | Path, out_dir: str | Path,
                           control: str | None = None, overwrite: bool = False) -> Path:
    """Write the friction-damper data set as a ``friction-damper`` campaign in ``out_dir``.

    Parameters
    ----------
    data_dir
        Folder with ``characterization*/*.json`` (identification), other folders of
        recorded histories such as ``earthquake/*.json`` (controls), test files of
        its own (identification) and optionally ``published/lugre_*.csv``.
    out_dir
        The campaign directory to create (atomically).
    control
        A glob over file stems (e.g. ``'1Hz*'``): those tests are the controls and
        every other test identifies. Default: the recorded histories (earthquake,
        wind) are the controls.
    overwrite
        Replace an existing campaign.
    """
    name = "friction-damper"
    data_dir = Path(data_dir)
    tests, seen, ids = [], {}, {}
    for path, default_role in _files(data_dir, name):
        frame = _read(path, name)
        _check_distinct(frame, path, seen, ids, name)
        stem = path.stem
        role = default_role if control is None else (
            "control" if fnmatch.fnmatch(stem, control) else "identification")
        spec = TestSpec(id=test_id_of(stem), file="", scenario="imposed_displacement",
                        input=_input_of(stem, path.relative_to(data_dir).as_posix(),
                                        frame["displacement_m"].to_numpy()),
                        motor="actuator", role=role)
        pub = _published(data_dir, stem, frame["friction_force_n"].to_numpy(), name)
        if pub is not None:
            spec.extra["published"] = pub
        tests.append((spec, frame))
    specs = [s for s, _ in tests]
    _check_roles(specs, control, data_dir, name)
    return write_campaign(
        out_dir, name=name, system=SYSTEM_NAME, known={}, tests=tests,
        extra={"source": "Dataset-Friction-Damper-with-Backlash, Coble, Huggins, Cao, Ricles "
                         "& Downey (ARTS Lab, University of South Carolina), CC BY-SA 4.0",
               "notes": _campaign_notes(specs, data_dir, name)},
        overwrite=overwrite,
    )


def _check_distinct(frame: pd.DataFrame, path: Path, seen: dict[str, Path],
                    ids: dict[str, Path], campaign: str) -> None:
    """A test file holds data and a test name no earlier file had (``seen``: data digest
    -> file, ``ids``: test id -> file); records both for the files after it."""
    digest = hashlib.sha256(frame[["displacement_m", "friction_force_n"]]
                            .to_numpy().tobytes()).hexdigest()
    if digest in seen:
        raise CampaignError(f"holds the same data as {seen[digest]}: one label is wrong; "
                            "remove one of the two files", campaign=campaign, path=path)
    seen[digest] = path
    test_id = test_id_of(path.stem)
    if test_id in ids:
        raise CampaignError(f"has the test name of {ids[test_id]}: rename one "
                            "of the two files", campaign=campaign, path=path)
    ids[test_id] = path


def _check_roles(specs: list[TestSpec], control: str | None, data_dir: Path,
                 campaign: str) -> None:
    """At least one test is held out as a control and at least one is left to identify."""
    if not any(s.role == "control" for s in specs):
        why = (f"no test matches --control {control!r}" if control is not None else
               "no earthquake test to hold out and no --control given (e.g. --control "
               "'1Hz*' holds out the 1 Hz sine tests)")
        raise CampaignError(f"{why}: nothing held out", campaign=campaign, path=data_dir)
    if not any(s.role == "identification" for s in specs):
        raise CampaignError("every test is a control: nothing left to identify",
                            campaign=campaign, path=data_dir)


def _campaign_notes(specs: list[TestSpec], data_dir: Path, campaign: str) -> str:
    """The campaign's ``notes``: the unit conversion, and (also logged as a warning) the
    band tensions when the sine tests mix several."""
    notes = ["SI units converted from in, kip and lb as the files declare them"]
    mixed = _mixed_tensions(specs)
    if mixed:
        log.warning("campaign %r from %s: %s", campaign, data_dir, mixed)
        notes.append(mixed)
    return "; ".join(notes)
