"""The base fit as a record: what ``mbst identify`` writes and ``mbst discover`` starts from.

The workflow fits a campaign's base model once. The identify step writes its cascade
(``base_fit`` in ``params.json``), and the discover step rebuilds the same
``IdentifyResult`` from it instead of running the same deterministic cascade a second
time (demo: 16 s of its 3 minutes). A record is used only for the very campaign data,
settings and code that made it; for anything else discovery fits the cascade itself and
says why (``base_from_record`` returns the reason).
"""

from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass

import numpy as np

from mbst.identify.cascade import IdentifyResult, IdentifySettings, StageResult, correlate
from mbst.identify.cascade import prepare_campaign as _prepare_campaign
from mbst.io.campaign import Campaign
from mbst.io.provenance import source_hash

FORMAT = "mbst-base-fit/1"
# the settings that change what the cascade finds (``progress`` only prints)
FIT_SETTINGS = ("tau_s", "seed", "multistart", "max_nfev", "decimate", "joint_refinement",
                "extra_starts")


def campaign_digest(campaign: Campaign) -> str:
    """sha256 over ``campaign.yaml`` and every test file it lists, in its order."""
    h = hashlib.sha256()
    files = [campaign.path / "campaign.yaml"] + [campaign.path / s.file for s in campaign.tests]
    for path in files:
        data = path.read_bytes()
        h.update(len(data).to_bytes(8, "little") + data)
    return h.hexdigest()


def _settings_record(settings: IdentifySettings) -> dict:
    return {k: getattr(settings, k) for k in FIT_SETTINGS} | {"prior": settings.prior}


def fit_record(result: IdentifyResult, settings: IdentifySettings, campaign: Campaign
               ) -> dict:
    """What ``base_from_record`` needs to rebuild ``result`` as discovery's base model
    (discovery reads no warning and no known-value check of it: those stay identify's)."""
    return {
        "format": FORMAT,
        "campaign_digest": campaign_digest(campaign),
        "code": source_hash(),
        "settings": _settings_record(settings),
        # the parameter vector in the model's order (JSON floats round-trip exactly)
        "params": [float(v) for v in result.params],
        "stages": [{"scenario": st.scenario, "tests": st.tests, "free": st.free,
                    "cost": st.cost, "n_residuals": st.n_residuals, "starts": st.starts,
                    "wall_s": st.wall_s, "std_error": st.std_error,
                    "correlation": st.correlation, "at_bound": st.at_bound,
                    "identifiable": st.identifiable} for st in result.stages],
        "preidentification": result.preid,
        "warnings": result.warnings,
        "wall_s": result.wall_s,
    }


@dataclass
class Rebuilt:
    """``base_from_record``'s answer: the base fit, or why the record was not used."""

    result: IdentifyResult | None
    reason: str = ""


def base_from_record(campaign: Campaign, settings: IdentifySettings, record: dict | None
                     ) -> Rebuilt:
    """The identification-only base fit (``identify(..., controls=False,
    check_known=False)``) rebuilt from ``record``, if it was made from this campaign's
    data with these settings by this code."""
    if not isinstance(record, dict) or record.get("format") != FORMAT:
        return Rebuilt(None, f"not a base-fit record ({FORMAT})")
    model = campaign.model()
    mismatch = [what for what, ok in (
        ("campaign data", record.get("campaign_digest") == campaign_digest(campaign)),
        ("settings", record.get("settings") == _plain_settings(settings)),
        ("code", record.get("code") == source_hash()),
        ("parameter vector", len(record.get("params", ())) == len(model.param_specs)),
    ) if not ok]
    if mismatch:
        return Rebuilt(None, "made from other " + ", ".join(mismatch))
    prepared, _ = _prepare_campaign(campaign, settings.tau_s)
    p = np.array(record["params"], float)
    stages = [_stage(st) for st in record["stages"]]
    id_fit, id_twins = correlate([prepared[s.id] for s in campaign.identification_tests()], p)
    result = IdentifyResult(campaign.name, p, stages, record["preidentification"],
                            list(record["warnings"]), id_fit.iloc[0:0], id_fit,
                            float(record["wall_s"]), prepared, id_twins, model, [])
    return Rebuilt(result)


def _plain_settings(settings: IdentifySettings) -> dict:
    """The settings as they read back from JSON (tuples as lists)."""
    out = _settings_record(settings)
    if out["prior"] is not None:
        out["prior"] = {k: list(v) for k, v in out["prior"].items()}
    return out


def _stage(st: dict) -> StageResult:
    nan = math.nan
    return StageResult(
        scenario=st["scenario"], tests=list(st["tests"]), free=list(st["free"]),
        cost=float(st["cost"]), n_residuals=int(st["n_residuals"]), starts=list(st["starts"]),
        wall_s=float(st["wall_s"]),
        std_error={k: nan if v is None else float(v) for k, v in st["std_error"].items()},
        correlation=[[nan if v is None else v for v in row] for row in st["correlation"]],
        at_bound=dict(st["at_bound"]), identifiable=dict(st["identifiable"]))
