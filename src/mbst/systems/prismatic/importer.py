"""Converters from other data formats to an mbst campaign.

``import_emps``: the EMPS benchmark (Janot, Gautier & Brunot 2019) →
a ``prismatic-axis`` campaign: ``DATA_EMPS`` is the identification test,
``DATA_EMPS_PULSES`` the held-out control. The pulses are already inside the
recorded drive command ``vir`` (shared/data/real/emps/README.md, note 2): the
motor force is ``gtau·vir`` and the pulses are written only as the separate
``injected_force_n`` channel that the closed-loop simulation adds after the
controller's saturation, never a second time to the force.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from mbst.io.campaign import CampaignError, TestSpec, write_campaign
from mbst.systems.prismatic.channels import SYSTEM_NAME

EMPS_FILES = {
    "emps_identification": ("DATA_EMPS.mat", "identification"),
    "emps_pulses_ctrl": ("DATA_EMPS_PULSES.mat", "control"),
}
EMPS_COMMAND_LIMIT_V = 10.0  # the authors' reference simulation saturates vir at ±10


def _load_mat(path: Path, campaign: str) -> dict[str, np.ndarray]:
    from scipy.io import loadmat

    if not path.is_file():
        raise CampaignError("benchmark file not found", campaign=campaign, path=path)
    try:
        raw = loadmat(path)
    except Exception as exc:  # scipy raises several types for a damaged file
        raise CampaignError(f"cannot read as a MATLAB file ({exc})", campaign=campaign,
                            path=path) from None
    need = ("t", "qg", "qm", "vir", "gtau", "kp", "kv")
    missing = [k for k in need if k not in raw]
    if missing:
        raise CampaignError(f"variable(s) {', '.join(missing)} missing", campaign=campaign,
                            path=path)
    return {k: np.asarray(v, dtype=float).ravel() for k, v in raw.items()
            if not k.startswith("__")}


def import_emps(data_dir: str | Path, out_dir: str | Path, overwrite: bool = False) -> Path:
    """Write the EMPS benchmark as a ``prismatic-axis`` campaign in ``out_dir``.

    Parameters
    ----------
    data_dir
        Folder with ``DATA_EMPS.mat`` and ``DATA_EMPS_PULSES.mat``.
    out_dir
        The campaign directory to create (atomically).
    overwrite
        Replace an existing campaign.

    Returns
    -------
    Path
        The campaign directory.
    """
    name = "emps"
    data_dir = Path(data_dir)
    tests, known = [], None
    for test_id, (fname, role) in EMPS_FILES.items():
        path = data_dir / fname
        d = _load_mat(path, name)
        _check_signals(d, path, name)
        consts = _drive_constants(d)
        if known is None:
            known = consts
        else:
            _check_same_drive(known, consts, path, name)
        frame = _emps_frame(d, consts["drive_gain_n_per_v"])
        spec = TestSpec(id=test_id, file=f"tests/{test_id}.csv", scenario="closed_loop",
                        input={"kind": "recorded", "source": fname}, motor="drive", role=role)
        tests.append((spec, frame))
    return write_campaign(
        out_dir, name=name, system=SYSTEM_NAME, known=known, tests=tests,
        extra={"source": "EMPS benchmark, Janot, Gautier & Brunot (2019), nonlinearbenchmark.org",
               "notes": "pulses are inside motor_force_n; injected_force_n repeats them only "
                        "for the closed-loop simulation"},
        overwrite=overwrite,
    )


def _check_signals(d: dict[str, np.ndarray], path: Path, campaign: str) -> None:
    """The recorded reference, position and drive command are as long as ``t`` and
    finite (the first bad sample named by its 1-based row)."""
    n = len(d["t"])
    for k in ("qg", "qm", "vir"):
        if len(d[k]) != n:
            raise CampaignError(f"variable '{k}' has {len(d[k])} samples, 't' has {n}",
                                campaign=campaign, path=path)
        bad = np.nonzero(~np.isfinite(d[k]))[0]
        if bad.size:
            raise CampaignError(f"variable '{k}' is not finite", campaign=campaign,
                                path=path, row=int(bad[0]) + 1)


def _drive_constants(d: dict[str, np.ndarray]) -> dict[str, float]:
    """The drive gain and loop gains a file records, with the command limit: the
    campaign's ``known`` values."""
    return {"drive_gain_n_per_v": float(d["gtau"][0]),
            "position_loop_gain_per_s": float(d["kp"][0]),
            "velocity_loop_gain_v_s_per_m": float(d["kv"][0]),
            "drive_command_limit_v": EMPS_COMMAND_LIMIT_V}


def _check_same_drive(known: dict[str, float], consts: dict[str, float], path: Path,
                      campaign: str) -> None:
    """A later file's drive and controller constants agree with those of DATA_EMPS.mat."""
    if any(abs(known[k] - v) > 1e-9 * abs(v) for k, v in consts.items()):
        raise CampaignError("drive or controller constants differ from DATA_EMPS.mat",
                            campaign=campaign, path=path)


def _emps_frame(d: dict[str, np.ndarray], gtau: float) -> pd.DataFrame:
    """One test's channels: the motor force is ``gtau·vir`` (the pulses already inside),
    the pulses alone (zero where the file has none) as ``injected_force_n``."""
    pulses = d.get("pulses_N", np.zeros(len(d["t"])))
    return pd.DataFrame({
        "time_s": d["t"],
        "position_m": d["qm"],
        "motor_force_n": gtau * d["vir"],
        "position_reference_m": d["qg"],
        "injected_force_n": gtau * pulses,
        "drive_command_v": d["vir"],
    })
