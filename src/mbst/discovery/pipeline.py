"""Discovery: show what the simulation gets wrong, name the cause, extend, measure the gain.

``discover`` runs, on the identification tests only:

1. the base cascade (``identify``) and the residual analysis;
2. the family's rounds (``ModelDefinition.discovery_rounds``), each a function of
   the ``DiscoveryState`` that proposes findings into it (``ROUNDS`` below):
   the structure test (``rounds/catalogue.py``: the best catalogue candidate
   must clear the margins of ``acceptance.py``, win leave-one-test-out
   cross-validation and still lower the identification cost once the whole
   cascade is refitted with it), the stick-slip envelope, the equation error,
   and what the tests can resolve (``rounds/resolution.py``);
3. the family's evidence methods (sparse regression, neural residual) beside them.

The held-out control tests are touched only afterwards, to measure the
gain of every model family side by side.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from functools import partial
from pathlib import Path

import numpy as np
import pandas as pd

from mbst.discovery.acceptance import EVEN_ODDS, fold_one_body
from mbst.discovery.compare import Learned, compare, mean_gain
from mbst.discovery.data import TestResidual, residual_data
from mbst.discovery.evidence.collect import NeuralJob, sparse_evidence
from mbst.discovery.evidence.hybrid import neural_correction
from mbst.discovery.lumped import state_body_sizes
from mbst.discovery.precision import state_size_precision
from mbst.discovery.residuals import dominant_regions, residual_locations
from mbst.discovery.rounds.catalogue import proposal_finding, structure_rounds
from mbst.discovery.rounds.equation_error import equation_error_round
from mbst.discovery.rounds.limits import checked_resolution_round
from mbst.discovery.rounds.resolution import Resolution
from mbst.discovery.rounds.stickslip import (
    held_out_envelopes,
    sawtooth_in_another_part,
    stick_slip_round,
)
from mbst.discovery.rounds.unexplained import (
    campaign_places,
    driving_input,
    judge_catalogue_names,
    unexplained_round,
)
from mbst.discovery.state import DiscoverSettings, DiscoveryState, Finding, total_cost
from mbst.identify.cascade import IdentifyResult, identify
from mbst.identify.record import base_from_record
from mbst.io.campaign import Campaign

log = logging.getLogger(__name__)

FORMAT = "mbst-discovery/2"

# Every round has this signature; a family lists the ones it runs, in order.
Round = Callable[[DiscoveryState], None]
ROUNDS: dict[str, Round] = {
    "structure": structure_rounds,
    "stick_slip": stick_slip_round,
    "equation_error": equation_error_round,
    "unexplained": unexplained_round,
    # what these tests resolve, with the limits the refits left untested checked
    "resolution": checked_resolution_round,
}

__all__ = ["FORMAT", "ROUNDS", "DiscoverSettings", "DiscoveryResult", "Finding", "discover",
           "total_cost"]


@dataclass
class DiscoveryResult:
    campaign: str
    base: IdentifyResult
    extended_params: np.ndarray
    findings: list[Finding]
    rounds: list[dict]
    locations: list[dict]
    sparse: dict | None
    neural: dict | None
    comparison: pd.DataFrame
    gain: dict
    wall_s: float
    timings: dict
    twins: dict[str, dict[str, dict[str, np.ndarray]]] = field(repr=False, default_factory=dict)
    neural_model: object = field(repr=False, default=None)
    residual_tests: list[TestResidual] = field(repr=False, default_factory=list)
    settings: DiscoverSettings = field(repr=False, default_factory=DiscoverSettings)
    benchmark: dict | None = None
    # what the tests could show of each pair not in the extended model (resolution.py)
    resolution: list[Resolution] = field(default_factory=list)
    # what failed on the way (an evidence method, a model family, a figure): never the answer
    failures: list[str] = field(default_factory=list)
    # what the extended model's residual correlates with, per channel (rounds/unexplained.py)
    signatures: list = field(default_factory=list)
    places: dict[str, float] = field(default_factory=dict)  # each test's place in the campaign
    # the extended model's residuals on the identification tests (the unexplained round's)
    extended_residuals: list[TestResidual] = field(repr=False, default_factory=list)
    # what the resolution step judged with (``mbst plan --resolve`` designs with the same):
    # the campaign's folder, each stage's free parameters, the compensating parameters
    stages: dict = field(default_factory=dict)

    def summary(self) -> str:
        lines = [f"discovery on '{self.campaign}' in {self.wall_s:.1f} s"]
        declined = [g["key"] for r in self.rounds for g in r.get("rival_declined", [])]
        if not self.findings and declined:
            lines.append(f"  no finding: {', '.join(declined)} matched as well by a reality "
                         "outside the catalogue (a sensor, a drift, the stated values): "
                         "see discovery.md")
        elif not self.findings:
            lines.append("  no finding: the base model explains the identification tests down "
                         "to the noise floor")
        for f in self.findings:
            if f.effect == "unexplained":
                what = (f.signature["reading"] if f.signature.get("refitted") == "physics"
                        else f"{f.signature['kind']} in {f.signature['quantity']}")
                lines.append(f"  outside the catalogue ({what}), confidence "
                             f"{f.confidence:.2f}: see discovery.md")
                continue
            pars = ", ".join(f"{k}={v:.4g}" for k, v in f.parameters.items())
            where = " or ".join([f.component, *f.indistinguishable_from])
            lines.append(f"  found {f.effect} in {where} ({pars}), confidence "
                         f"{f.confidence:.2f}")
            if f.size_not_measured:
                lines.append("    size not measured by these tests: " + ", ".join(
                    f"{h} ± {f.size_std_error[h]:.2g}" for h in f.size_not_measured))
            if f.alternatives:
                lines.append("    not ruled out: " + ", ".join(
                    f"{a['effect']} in {a['component']}" for a in f.alternatives))
        below = controls_below_base(self.findings, self.comparison)
        if below is not None:
            lines.append(f"  held out: the extended model scores below the base on the controls "
                         f"({below[1]:.1f} against {below[0]:.1f} %): read the names with care "
                         "(discovery.md)")
        blind = [r.key for r in self.resolution if r.sizes and not r.resolved_at_realistic_size]
        if blind:
            lines.append("  these tests would not show at their realistic size: "
                         f"{', '.join(blind)} (discovery.md, resolution.csv)")
        untested = [r.key for r in self.resolution if r.stage is None]
        if untested:
            lines.append(f"  no test where they act: {', '.join(untested)}")
        means = self.comparison.groupby("model", sort=False)["fit_percent"].mean()
        for m, v in means.items():
            value = (f"{v:6.1f} %" if np.isfinite(v)
                     else "     – (no control it could simulate; discovery.md)")
            lines.append(f"  control FIT mean {m:<9} {value}")
        for key, pub in (self.benchmark or {}).get("published", {}).items():
            lines.append(f"  {key:<40} ours {self.benchmark.get(key, float('nan')):9.4g}  "
                         f"published {pub['value']:.4g} ({pub['model']})")
        return "\n".join(lines)


def controls_below_base(findings: list[Finding], comparison: pd.DataFrame
                        ) -> tuple[float, float] | None:
    """(base, extended) mean control FIT where a named extension scores below the base on
    the held-out controls (by at least the 0.1 % the reports print), else ``None``. Said,
    never acted on: the controls choose nothing."""
    if not any(f.effect != "unexplained" for f in findings) or comparison.empty:
        return None
    wide = comparison.pivot_table(index=["test", "channel"], columns="model",
                                  values="fit_percent")
    if not {"base", "extended"} <= set(wide.columns):
        return None
    both = wide[["base", "extended"]].dropna()
    if both.empty:
        return None
    base, ext = (float(both[m].mean()) for m in ("base", "extended"))
    return (base, ext) if ext <= base - 0.1 else None


def discover(campaign: Campaign, settings: DiscoverSettings | None = None,
             base_fit: dict | None = None) -> DiscoveryResult:
    """Find, name and insert the effects the base model lacks; compare model families.

    ``base_fit``: the base cascade as ``mbst identify`` recorded it (``base_fit.json``),
    used where it was made from this campaign's data with these settings by this code;
    otherwise (or ``None``) discovery fits the cascade itself.
    """
    settings = settings or DiscoverSettings()
    t_start = time.perf_counter()
    timings: dict[str, float] = {}
    base = _base_model(campaign, settings, base_fit)
    timings["identify_s"] = time.perf_counter() - t_start
    id_res = [residual_data(base.prepared[s.id], base.params, base.twins.get(s.id))
              for s in campaign.identification_tests()]
    locations = residual_locations(id_res)
    state = DiscoveryState.start(campaign, settings, base, id_res,
                                 dominant_regions(locations), timings)
    # the floor each acceptance's "explained above the noise" counts: the input's noise
    # through the base model as well as the sensors' (a production 0.35° worm-gear backlash
    # was named at 0.55, "partly explained", with the angle's noise counted as structure)
    state.measure_floors("catalogue rounds")
    # two parts the base fit moved apart only by what it compensated with still move as one
    # body at the typical values (``acceptance.parts_speed_correlation``)
    state.measure_typical_speeds("catalogue rounds")
    # the network needs only the base residuals: it trains on one torch thread beside
    # the structure test, in a process of its own (``NeuralJob``)
    neural_job = NeuralJob(id_res, settings, base.model.candidate_library) \
        if settings.wants(base.model, "neural") else None
    try:
        for name in base.model.discovery_rounds:
            if settings.wants(base.model, name):
                _run_round(name, state)
        return _conclude(state, locations, neural_job, t_start)
    finally:
        if neural_job is not None:
            neural_job.close()


def _run_round(name: str, state: DiscoveryState) -> None:
    """One of the family's rounds; where it raises, the state goes back to what the rounds
    before it left and the failure is reported: a round that fails on a campaign nobody
    foresaw costs its own answer only, never the ones already found (#30)."""
    saved = state.checkpoint()
    try:
        ROUNDS[name](state)
    except Exception as exc:
        state.restore(saved)
        state.failed(f"{name.replace('_', ' ')} round", exc)


def _base_model(campaign: Campaign, settings: DiscoverSettings, base_fit: dict | None
                ) -> IdentifyResult:
    """The identify step's cascade where its record fits, else the same cascade fitted."""
    if base_fit is not None:
        rebuilt = base_from_record(campaign, settings.identify, base_fit)
        if rebuilt.result is not None:
            log.info("base model: the identify step's cascade (base_fit record)")
            return rebuilt.result
        log.warning("base-fit record not used (%s): fitting the cascade", rebuilt.reason)
    # the fixed known values are checked by `mbst identify`; discovery keeps its minutes
    return identify(campaign, settings.identify, controls=False, check_known=False)


def _named(state: DiscoveryState, sparse_ev: dict | None, neural_ev: dict | None
           ) -> list[Finding]:
    """The structure rounds' proposals named, beside the other rounds' findings, parts of
    one body folded into one finding and its size stated as the body's."""
    findings = [proposal_finding(p, state, sparse_ev, neural_ev) for p in state.proposals]
    # the phase-free round ran after these were proposed, and can question their part
    sawtooth_in_another_part(findings, state)
    findings = fold_one_body(findings + state.findings, state.residuals, state.model)
    state_body_sizes(findings, state.residuals, state.model, state.p)
    state_size_precision(findings, state)
    if any(f.startswith("structure round") for f in state.failures):
        _catalogue_not_searched(findings)
    return findings


def _catalogue_not_searched(findings: list[Finding]) -> None:
    """Where a structure round failed, the catalogue was not searched through: what the
    later rounds read as outside it may be a catalogue effect that round would have named
    (the damper's play, read as unexplained at 0.93 once its round had failed)."""
    for f in findings:
        if f.effect == "unexplained":
            f.evidence = ("CATALOGUE NOT SEARCHED THROUGH: a structure round failed (\"What "
                          "failed\"), so this may be a catalogue effect that round would have "
                          f"named; at most even odds. {f.evidence}")
            f.confidence = min(f.confidence, EVEN_ODDS)


def _conclude(state: DiscoveryState, locations: list[dict], neural_job: NeuralJob | None,
              t_start: float) -> DiscoveryResult:
    """Evidence in, findings named, model families compared on the held-out controls."""
    settings, model, timings = state.settings, state.model, state.timings
    sparse_ev, neural_ev, neural_model = _evidence(state, neural_job)
    findings = _named(state, sparse_ev, neural_ev)
    _judge_names(findings, state)
    # the held-out control tests measure the gain; they decided nothing above
    t0 = time.perf_counter()
    places = campaign_places(state)
    learned = Learned([s for s in state.signatures if s.structured], places,
                      driving_input(model), state.rival_physics)
    cmp = compare(state.campaign, state.base, state.p, state.residuals, settings, neural_model,
                  learned)
    timings["compare_s"] = time.perf_counter() - t0
    _learned_gain(findings, cmp.table)
    base = replace(state.base, correlation=cmp.base_correlation,
                   twins={**state.base.twins, **cmp.twins["base"]})
    gain = _gain(state, cmp.table)
    _stick_slip_held_out(gain, findings, state, cmp.twins)
    failures = [f"{name} evidence: {ev['error']}" for name, ev in
                (("sparse-regression", sparse_ev), ("neural-residual", neural_ev))
                if ev and ev.get("error")] + state.failures + cmp.failures
    return DiscoveryResult(
        campaign=state.campaign.name, base=base, extended_params=state.p, findings=findings,
        rounds=state.rounds, locations=locations, sparse=sparse_ev, neural=neural_ev,
        comparison=cmp.table, gain=gain, wall_s=time.perf_counter() - t_start,
        timings=timings, twins=cmp.twins, neural_model=neural_model,
        residual_tests=state.residuals, settings=settings,
        benchmark=_benchmark(model, base, state.p, failures,
                             partial(neural_correction, seed=settings.identify.seed)
                             if settings.neural else None),
        resolution=state.resolution, failures=failures, signatures=state.signatures,
        places=places, extended_residuals=state.extended_residuals,
        stages={"campaign_path": str(Path(state.campaign.path).resolve()),
                "stage_free": state.model_free_by_stage, "compensating": state.compensating(),
                "tau_s": settings.identify.tau_s, "decimate": settings.identify.decimate},
    )


def _evidence(state: DiscoveryState, neural_job: NeuralJob | None
              ) -> tuple[dict | None, dict | None, object]:
    """The sparse regression's and the neural residual's evidence, and the trained network
    (``None`` where a method was not run); their times go to ``state.timings``."""
    settings, model, timings = state.settings, state.model, state.timings
    sparse_ev = neural_ev = neural_model = None
    if settings.wants(model, "sparse"):
        t0 = time.perf_counter()
        sparse_ev = sparse_evidence(state.residuals, model.candidate_library)
        timings["sparse_s"] = time.perf_counter() - t0
    if neural_job is not None:
        t0 = time.perf_counter()
        neural_model, neural_ev = neural_job.result()
        timings["neural_s"] = neural_ev.get("train_seconds") or 0.0
        timings["neural_wait_s"] = time.perf_counter() - t0
    return sparse_ev, neural_ev, neural_model


def _judge_names(findings: list[Finding], state: DiscoveryState) -> None:
    """The unexplained round's check of the catalogue names; a failure is recorded."""
    try:
        judge_catalogue_names(findings, state)
    except Exception as exc:  # a check on the names must never sink them
        log.warning("the unexplained round's check of the names failed: %s", exc)
        state.failures.append(f"unexplained round (names check): {type(exc).__name__}: {exc}")


def _gain(state: DiscoveryState, table: pd.DataFrame) -> dict:
    """The extension's gain: control FIT, and ΔAIC on the identification tests."""
    cost_base, n_eff = state.base_cost, state.base_n_eff
    k_added = sum(len(state.model.effects[k].free) for k in state.accepted)
    return {
        "control_fit_percent_mean": mean_gain(table),
        "aic_delta": float(n_eff * math.log(state.cost / cost_base) + 2 * k_added)
        if state.accepted and cost_base > 0 else 0.0,
        "identification_cost_base": cost_base,
        "identification_cost_extended": state.cost,
        "effective_samples": n_eff,
    }


def _stick_slip_held_out(gain: dict, findings: list[Finding], state: DiscoveryState,
                         twins: dict) -> None:
    """A stick-slip finding's gain on the controls in its own measure, the fast envelope
    (``stickslip.held_out_envelopes``); a failure costs that entry only."""
    controls = [state.base.prepared[s.id] for s in state.campaign.control_tests()]
    try:
        envelopes = held_out_envelopes(findings, controls, twins, state.model)
    except Exception as exc:  # a report's measure must never sink the answer
        log.warning("stick-slip envelope on the controls failed: %s", exc)
        state.failures.append(f"stick-slip envelope on the controls: "
                              f"{type(exc).__name__}: {exc}")
        return
    if envelopes:
        gain["stick_slip_envelope_held_out"] = envelopes


def _learned_gain(findings: list[Finding], table: pd.DataFrame) -> None:
    """An unexplained finding's signature carries its correction's gain on the controls."""
    means = table.groupby("model")["fit_percent"].mean()
    if "physics+learned" not in means:
        return
    for f in findings:
        if f.effect == "unexplained" and f.signature is not None:
            f.signature["control_fit_percent_mean"] = {
                m: round(float(means[m]), 3) for m in ("base", "extended", "physics+learned")
                if m in means}
            f.signature["control_fit_gain_percent"] = round(
                float(means["physics+learned"] - means["extended"]), 3)


def _benchmark(model, base: IdentifyResult, p: np.ndarray, failures: list[str],
               learner: Callable | None) -> dict | None:
    """The family's published figures of merit; a failure there costs the table only."""
    if model.benchmark is None:
        return None
    try:
        # the neural residual is discovery's; the family's benchmark gets it handed over
        return model.benchmark(base, p, learner=learner)
    except Exception as exc:  # a benchmark table must never sink the discovery
        failures.append(f"benchmark table: {type(exc).__name__}: {exc}")
        log.warning("benchmark table failed: %s: %s", type(exc).__name__, exc)
        return None
