"""The held-out control tests measure the gain of every model family; they decide nothing."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from mbst.core.metrics import fit_percent
from mbst.core.model import ModelDefinition
from mbst.discovery.data import TestResidual, residual_data
from mbst.discovery.state import DiscoverSettings
from mbst.identify.cascade import IdentifyResult, correlate
from mbst.io.campaign import Campaign


@dataclass
class Comparison:
    """Control FIT % per test, channel and model family, and the twins behind it."""

    table: pd.DataFrame
    twins: dict[str, dict]
    base_correlation: pd.DataFrame  # the base model on the controls (identify's table)


def compare(campaign: Campaign, base: IdentifyResult, p_ext: np.ndarray,
            id_res: list[TestResidual], settings: DiscoverSettings, neural_model
            ) -> Comparison:
    """Control FIT % of every model family, one row per test, channel and model."""
    controls = [base.prepared[s.id] for s in campaign.control_tests()]
    rows: list[dict] = []
    twins: dict[str, dict] = {}

    def add(model: str, tw: dict[str, dict[str, np.ndarray]]) -> None:
        twins[model] = tw
        for pt in controls:
            for ch, y in pt.measured.items():
                yh = tw.get(pt.id, {}).get(ch)
                fp = fit_percent(y, yh) if yh is not None else float("nan")
                rows.append({"test": pt.id, "channel": ch, "model": model, "fit_percent": fp})

    base_correlation, base_tw = correlate(controls, base.params)
    add("base", base_tw)
    base_twins = {**base.twins, **base_tw}
    _, ext_tw = correlate(controls, p_ext)
    add("extended", ext_tw)
    ctrl_res = [residual_data(pt, base.params, base_twins[pt.id]) for pt in controls]
    if settings.wants(base.model, "sparse"):
        from mbst.discovery.evidence.sindy import SindyControlModel

        sm = SindyControlModel().fit(id_res)
        add("sindy", {r.id: sm.predict(r) for r in ctrl_res})
    if neural_model is not None:
        add("neural", {r.id: neural_model.predict(r) for r in ctrl_res})
    truth = _truth_params(campaign, base.model)
    if truth is not None:
        _, true_tw = correlate(controls, truth)
        add("true", true_tw)
    df = pd.DataFrame(rows, columns=["test", "channel", "model", "fit_percent"])
    return Comparison(df, twins, base_correlation)


def mean_gain(df: pd.DataFrame) -> float:
    if df.empty:
        return 0.0
    wide = df.pivot_table(index=["test", "channel"], columns="model", values="fit_percent")
    return float((wide["extended"] - wide["base"]).mean())



def _truth_params(campaign: Campaign, model: ModelDefinition) -> np.ndarray | None:
    """The bench's ground truth, when the campaign came from ``mbst bench``."""
    path = Path(campaign.path).parent / "truth.json"
    if not path.is_file():
        return None
    try:
        return model.vector_from(json.loads(path.read_text())["params"])
    except (KeyError, ValueError, json.JSONDecodeError):
        return None
