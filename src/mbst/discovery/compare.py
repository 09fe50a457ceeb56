"""The held-out control tests measure the gain of every model family; they decide nothing."""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from mbst.core.metrics import fit_percent
from mbst.core.model import ModelDefinition
from mbst.discovery.data import TestResidual, residual_data
from mbst.discovery.state import DiscoverSettings
from mbst.identify.cascade import IdentifyResult, correlate
from mbst.io.campaign import Campaign

log = logging.getLogger(__name__)


@dataclass
class Learned:
    """The unexplained round's fitted signatures: the "physics + learned" correction."""

    signatures: list  # ChannelSignature, structured only
    places: dict[str, float]  # each test's place in the campaign
    input_name: str
    # the physics under the learned terms: the extended model with a reality outside the
    # catalogue refitted (``DiscoveryState.rival_physics``); None: the extended model
    physics: np.ndarray | None = None

    @property
    def any(self) -> bool:
        return bool(self.signatures) or self.physics is not None

    def twins(self, ctrl_res: list[TestResidual]) -> dict[str, dict[str, np.ndarray]]:
        from mbst.discovery.signature import learned_term

        out = {}
        for r in ctrl_res:
            tw = dict(r.simulated)
            for sig in self.signatures:
                if sig.channel in tw:
                    tw[sig.channel] = tw[sig.channel] + learned_term(
                        r, sig, self.places.get(r.id, 0.0), self.input_name)
            out[r.id] = tw
        return out


@dataclass
class Comparison:
    """Control FIT % per test, channel and model family, and the twins behind it."""

    table: pd.DataFrame
    twins: dict[str, dict]
    base_correlation: pd.DataFrame  # the base model on the controls (identify's table)
    failures: list[str] = field(default_factory=list)  # model families that could not run


def compare(campaign: Campaign, base: IdentifyResult, p_ext: np.ndarray,
            id_res: list[TestResidual], settings: DiscoverSettings, neural_model,
            learned: Learned | None = None) -> Comparison:
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
    failures: list[str] = []
    if learned is not None and learned.any:
        _optional("physics+learned", lambda: learned.twins(
            _physics_twins(controls, p_ext, ext_tw, learned.physics)), add, failures)
    if settings.wants(base.model, "sparse"):
        _optional("sindy", lambda: _sindy_twins(id_res, ctrl_res, failures), add, failures)
    if neural_model is not None:
        _optional("neural", lambda: {r.id: neural_model.predict(r) for r in ctrl_res}, add,
                  failures)
    truth = _truth_params(campaign, base.model)
    if truth is not None:
        _, true_tw = correlate(controls, truth)
        add("true", true_tw)
    df = pd.DataFrame(rows, columns=["test", "channel", "model", "fit_percent"])
    return Comparison(df, twins, base_correlation, failures)


def _physics_twins(controls: list, p_ext: np.ndarray, ext_tw: dict,
                   physics: np.ndarray | None) -> list[TestResidual]:
    """The controls under the learned terms' physics: the extended model, or it with a
    reality outside the catalogue refitted."""
    if physics is None:
        return [residual_data(pt, p_ext, ext_tw[pt.id]) for pt in controls]
    _, tw = correlate(controls, physics)
    return [residual_data(pt, physics, tw[pt.id]) for pt in controls]


def _sindy_twins(id_res: list[TestResidual], ctrl_res: list[TestResidual],
                 failures: list[str]) -> dict:
    """The black-box SINDy model open loop on each control test; a test it cannot simulate
    (it blew up, or no model for its cut-out) has its FIT left blank, and the reason said."""
    from mbst.discovery.evidence.sindy import SindyControlModel

    sm = SindyControlModel().fit(id_res)
    twins = {r.id: sm.predict(r) for r in ctrl_res}
    failures += [f"control twin of the sindy model on {tid}: {why} (its FIT is left blank)"
                 for tid, why in sm.failures.items()]
    return twins


def _optional(model: str, twins_of, add, failures: list[str]) -> None:
    """A data-driven model family on the controls; its failure costs its row, not the answer."""
    try:
        tw = twins_of()
    except Exception as exc:  # one model family must never sink the discovery
        msg = f"control twins of the {model} model: {type(exc).__name__}: {exc}"
        log.warning("%s (its row is left out of the comparison)", msg)
        failures.append(msg)
        return
    add(model, tw)


def mean_gain(df: pd.DataFrame) -> float:
    if df.empty:
        return 0.0
    wide = df.pivot_table(index=["test", "channel"], columns="model", values="fit_percent", dropna=False)
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
