"""Discovery: show what the simulation gets wrong, name the cause, extend, measure the gain.

``discover`` runs, on the identification tests only:

1. the base cascade (``identify``) and the residual analysis;
2. rounds of the structure test (``structure.structure_test``): the best
   catalogue candidate is accepted only if it removes at least
   ``min_relative_gain`` of its stage's residual cost, lowers the Akaike
   criterion (effective sample count) by ``min_aic_drop``, wins
   leave-one-test-out cross-validation in most folds, and still lowers the
   identification cost after the whole cascade is refitted with it;
3. the sparse regression and the neural residual as independent evidence;
4. what the tests can resolve (``resolution.campaign_resolution``): from which
   size each catalogue pair not found would have cleared the same margins.

The held-out control tests are touched only afterwards, to measure the
gain of every model family side by side.
"""

from __future__ import annotations

import json
import math
import time
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import pandas as pd

from mbst.core.metrics import fit_percent
from mbst.core.model import ModelDefinition
from mbst.discovery.data import TestResidual, residual_data
from mbst.discovery.residuals import dominant_regions, residual_locations
from mbst.discovery.rounds.resolution import Resolution, campaign_resolution
from mbst.discovery.rounds.structure import (
    CandidateScore,
    StageScorer,
    aic_delta,
    compensating_parameters,
    effective_samples,
    structure_test,
)
from mbst.identify.cascade import IdentifyResult, IdentifySettings, correlate, run_cascade
from mbst.identify.fitting import PreparedTest, channel_scales, solve, twins_of_tests
from mbst.io.campaign import Campaign

FORMAT = "mbst-discovery/1"

# Two friction elements move as one body in a stage when their base-model speeds
# correlate at least this well over its tests (motor and rack behind a stiff mesh)...
TIE_SPEED_CORRELATION = 0.999
# ...and the runner-up leaves at most this share of the stage's base cost more than the
# best: then the data cannot say which of the two carries the effect. (A share of
# the base cost, not a ratio of what is left: hidden asymmetric rack friction left
# 0.70 % in the rack and 0.78 % in the motor, a ratio of 1.12, from one body.)
TIE_GAIN = 0.01


@dataclass
class DiscoverSettings:
    """Settings of discovery (config: ``discover.*``).

    ``min_relative_gain`` and ``min_aic_drop`` are the margin that noise
    alone does not give: on clean bench campaigns the best candidate removes
    at most ~4 % of its stage's cost (``benchmarks/discover.py`` prints it).
    """

    identify: IdentifySettings = field(default_factory=IdentifySettings)
    max_effects: int = 2
    min_relative_gain: float = 0.10
    min_aic_drop: float = 100.0
    refine: int = 5
    cv_nfev: int = 8
    sparse: bool = True
    neural: bool = True
    stick_slip: bool = True
    # families with an inverse model (ModelDefinition.equation_error): one more round
    equation_error: bool = True
    neural_iterations: int | None = None
    progress: bool = False
    # predict the smallest size of every catalogue pair the tests resolve (resolution.py)
    resolution: bool = True


@dataclass
class Finding:
    """One named effect (discovery.json ``findings`` entry)."""

    effect: str
    component: str
    parameters: dict[str, float]
    confidence: float
    evidence: str
    stage: str
    relative_gain: float
    aic_delta: float | None  # None where the criterion is not the output error (stick-slip)
    cv: dict
    # components the same effect could sit in as well: they move as one body with
    # ``component`` in the stage's tests and explain the data alike
    indistinguishable_from: list[str] = field(default_factory=list)

    def record(self) -> dict:
        return {"effect": self.effect, "component": self.component,
                "parameters": self.parameters, "confidence": round(self.confidence, 4),
                "evidence": self.evidence, "stage": self.stage,
                "relative_gain": self.relative_gain, "aic_delta": self.aic_delta,
                "cross_validation": self.cv,
                "indistinguishable_from": list(self.indistinguishable_from)}


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

    def summary(self) -> str:
        lines = [f"discovery on '{self.campaign}' in {self.wall_s:.1f} s"]
        if not self.findings:
            lines.append("  no finding: the base model explains the identification tests down "
                         "to the noise floor")
        for f in self.findings:
            pars = ", ".join(f"{k}={v:.4g}" for k, v in f.parameters.items())
            where = " or ".join([f.component, *f.indistinguishable_from])
            lines.append(f"  found {f.effect} in {where} ({pars}), confidence "
                         f"{f.confidence:.2f}")
        blind = [r.key for r in self.resolution if r.sizes and r.resolved_from != 1.0]
        if blind:
            lines.append("  these tests would not show at their realistic size: "
                         f"{', '.join(blind)} (discovery.md, resolution.csv)")
        untested = [r.key for r in self.resolution if r.stage is None]
        if untested:
            lines.append(f"  no test where they act: {', '.join(untested)}")
        means = self.comparison.groupby("model", sort=False)["fit_percent"].mean()
        for m, v in means.items():
            lines.append(f"  control FIT mean {m:<9} {v:6.1f} %")
        for key, pub in (self.benchmark or {}).get("published", {}).items():
            lines.append(f"  {key:<40} ours {self.benchmark.get(key, float('nan')):9.4g}  "
                         f"published {pub['value']:.4g} ({pub['model']})")
        return "\n".join(lines)


# --------------------------------------------------------------------------------------
# helpers
# --------------------------------------------------------------------------------------
def total_cost(tests: list[PreparedTest], p: np.ndarray, scales: dict[str, float],
               decimate: int = 2) -> tuple[float, list[np.ndarray]]:
    """Weighted data cost of ``p`` on ``tests`` (as the cascade weighs it) and the residuals."""
    cost, res = 0.0, []
    for pt, (tw,) in zip(tests, twins_of_tests(tests, [p[None]] * len(tests)), strict=True):
        n = len(pt.time_s[::decimate])
        for ch in pt.measured:
            r = (tw[ch] - pt.measured[ch])[::decimate]
            res.append(r)
            w = 1.0 / (scales[ch] * math.sqrt(n))
            cost += 0.5 * float(np.sum((r * w) ** 2))
    return cost, res


def akaike_weight(best: CandidateScore, scores: list[CandidateScore]) -> float:
    """Akaike weight of ``best`` among the candidates scored on the same stage.

    (Differences are comparable only on the same data, and with one sample count:
    each candidate's ΔAIC counts the effective samples of its own residual, so a
    candidate that whitens the residual less could out-score the one that removes
    more of it — a worm-gear backlash removing 91 % of the cost got weight 0 beside
    a motor hysteresis removing 64 %. Here every candidate is scored with the best
    one's count, the F-test convention the rounds use.)
    """
    same = [s for s in scores if s.stage == best.stage]
    a = np.array([aic_delta(s.cost, s.cost_base, best.n_eff, s.k_effect) for s in same],
                 float)
    w = np.exp(-0.5 * (a - a.min()))
    return float(w[same.index(best)] / w.sum())


def tied_components(best: CandidateScore, scores: list[CandidateScore],
                    residuals: dict[str, TestResidual], model: ModelDefinition
                    ) -> list[tuple[CandidateScore, float]]:
    """Candidates of ``best``'s effect that the stage cannot tell from it.

    A runner-up counts when its component's speed follows ``best``'s in every
    test of the stage (``model.element_speeds``, base model) and it leaves almost
    the same cost: motor and rack friction seen through a rigid mesh are one
    term at the pinion, and which of the two wins is then down to noise.
    Returns ``(candidate, speed correlation)`` pairs.
    """
    speeds = model.element_speeds
    tests = [residuals[t] for t in best.tests if t in residuals]
    if best.component not in speeds or not tests:
        return []
    mine = np.concatenate([r.states[speeds[best.component]] for r in tests])
    out = []
    for s in scores:
        if s is best or s.stage != best.stage or s.effect != best.effect or \
                s.component not in speeds or s.cost - best.cost > TIE_GAIN * best.cost_base:
            continue
        theirs = np.concatenate([r.states[speeds[s.component]] for r in tests])
        corr = float(np.corrcoef(mine, theirs)[0, 1]) if np.std(mine) * np.std(theirs) > 0 \
            else 0.0
        if abs(corr) >= TIE_SPEED_CORRELATION:
            out.append((s, corr))
    return out


def _extended_cascade(campaign: Campaign, settings: IdentifySettings,
                      ids: list[PreparedTest], scales: dict[str, float],
                      starts: list[np.ndarray | None], extra_free: dict[str, tuple[str, ...]]
                      ) -> tuple[np.ndarray, float]:
    """The cascade refitted with an effect free from each start; the lowest identification cost.

    The starts compete too: a start is the base fit with one stage refitted around the
    effect, already a complete extended model, and a stage-by-stage cascade from it can
    land in a worse basin (powered backlash: start 0.00163, cascade 0.00762, base 0.00413).
    """
    best: tuple[np.ndarray, float] | None = None
    for start in starts:
        if start is None:
            continue
        p, _, _, _, _ = run_cascade(campaign, settings, base=start, extra_free=extra_free)
        for q in (p, start):
            cost, _ = total_cost(ids, q, scales, settings.decimate)
            if best is None or cost < best[1]:
                best = (q, cost)
    return best


def _extend(campaign: Campaign, settings: IdentifySettings, ids: list[PreparedTest],
            scales: dict[str, float], starts: list[np.ndarray | None],
            extra_free: dict[str, tuple[str, ...]], cost_to_beat: float
            ) -> tuple[np.ndarray, float]:
    """The extended cascade: quick from the deliberate starts, with restarts if that fails.

    First from the two deliberate starts only (the winner's fit, its reset
    variant): around a warm start the cascade's random restart just doubles the
    time (demo: 26 → 10 s, same result). Where that does not lower the
    identification cost below ``cost_to_beat``, the cascade runs again with its
    own restarts (a powered campaign without the current needed them).
    """
    p, cost = _extended_cascade(campaign, replace(settings, multistart=1), ids, scales,
                                starts, extra_free)
    if cost < cost_to_beat or settings.multistart <= 1:
        return p, cost
    return _extended_cascade(campaign, settings, ids, scales, starts, extra_free)


def _reset_extension_start(scorer: StageScorer, best: CandidateScore, spec
                           ) -> np.ndarray | None:
    """A second start for the extended cascade: the winner refitted from its reset variant.

    The winner's short refit may keep the base model's compensation (demo-assist:
    a gear 12× too soft beside the backlash it stood in for, stage cost 4.96e-5
    against 3.04e-5 from the reset start and the true model's 3.11e-5). ``None``
    when that start does not fit the stage better. The cascade runs from both and
    keeps the lower identification cost: from the reset start alone, a powered
    campaign's later stages went 5× worse.
    """
    if not scorer.reset:
        return None
    q = scorer.reset_start(best.params)
    fr = solve(scorer.problem(list(spec.free) + scorer.stage_free, q), [q],
               max_nfev=scorer.max_nfev)
    return fr.p if float(scorer.costs(fr.p[None])[0].sum()) < best.cost else None


def cross_validate(scorer: StageScorer, cand: CandidateScore, p_base: np.ndarray,
                   nfev: int) -> dict:
    """Leave one test of the stage out: refit base and extension on the rest, score it."""
    tests = scorer.tests
    if len(tests) < 2:
        return {"folds": 0, "wins": 0, "held_out_gain": None,
                "note": f"the {scorer.stage} stage has one identification test: no fold"}
    spec = scorer.model.effects[cand.key]
    wins, cb_sum, ce_sum, folds = 0, 0.0, 0.0, []
    for j, held in enumerate(tests):
        train = [pt for k, pt in enumerate(tests) if k != j]
        pb = solve(scorer.problem(scorer.stage_free, p_base, train), [p_base], nfev).p
        pe = solve(scorer.problem(list(spec.free) + scorer.stage_free, cand.params, train),
                   [cand.params], nfev).p
        cb, ce = scorer.costs(np.stack([pb, pe]), [held])[:, 0]
        wins += int(ce < cb)
        cb_sum += cb
        ce_sum += ce
        folds.append({"held_out": held.id, "cost_base": float(cb), "cost_extended": float(ce)})
    return {"folds": len(tests), "wins": wins, "held_out_gain": 1.0 - ce_sum / cb_sum,
            "per_fold": folds}


def _score_record(s: CandidateScore) -> dict:
    return {"key": s.key, "effect": s.effect, "component": s.component, "stage": s.stage,
            "relative_gain": round(s.relative_gain, 5), "aic_delta": round(s.aic_delta, 2),
            "n_eff": round(s.n_eff, 1), "headline": s.headline, "wall_s": round(s.wall_s, 2),
            "fell_back": s.fell_back}


def _truth_params(campaign: Campaign, model: ModelDefinition) -> np.ndarray | None:
    """The bench's ground truth, when the campaign came from ``mbst bench``."""
    path = Path(campaign.path).parent / "truth.json"
    if not path.is_file():
        return None
    try:
        return model.vector_from(json.loads(path.read_text())["params"])
    except (KeyError, ValueError, json.JSONDecodeError):
        return None


def _evidence(best: CandidateScore, runner: CandidateScore | None, cv: dict,
              regions: list[tuple[str, float]], sparse: dict | None,
              neural: dict | None, ties: list[tuple[CandidateScore, float]] = ()) -> str:
    parts = [
        f"structure test: inserting {best.effect} in {best.component} and refitting the "
        f"{best.stage} stage removed {100 * best.relative_gain:.1f} % of its residual cost "
        f"(ΔAIC {best.aic_delta:.0f} with {best.n_eff:.0f} effective samples)",
    ]
    for s, corr in ties:
        parts.append(
            f"NOT DECIDED between {best.component} and {s.component}: they move as one body in "
            f"the {best.stage} tests (speed correlation {corr:.5f}) and the same effect in "
            f"{s.component} removed {100 * s.relative_gain:.1f} %; a test that moves one "
            "without the other, or a sensor between them, would tell them apart")
    if runner is not None:
        parts.append(f"runner-up {runner.key} removed {100 * runner.relative_gain:.1f} % "
                     f"(ΔAIC {runner.aic_delta:.0f})")
    if cv.get("folds"):
        parts.append(f"leave-one-test-out: better on {cv['wins']}/{cv['folds']} held-out tests, "
                     f"held-out cost −{100 * cv['held_out_gain']:.1f} %")
    else:
        parts.append(cv.get("note", "no cross-validation"))
    if regions:
        parts.append("residual concentrated in " + ", ".join(
            f"{k} ({v:.1f}× its share of time)" for k, v in regions[:2]))
    for name, ev in (("sparse regression", sparse), ("neural residual", neural)):
        if not ev or not ev.get("ranking"):
            continue
        keys = [k for k, _ in ev["ranking"]]
        rank = keys.index(best.key) + 1 if best.key in keys else None
        top = ev["ranking"][0]
        txt = f"{name} ranks {top[0]} first ({100 * top[1]:.0f} % of residual variance)"
        txt += f", this effect #{rank}" if rank and rank > 1 else (
            "" if rank == 1 else ", this effect not among its terms")
        parts.append(txt)
    return "; ".join(parts)


# --------------------------------------------------------------------------------------
# the loop
# --------------------------------------------------------------------------------------
def discover(campaign: Campaign, settings: DiscoverSettings | None = None) -> DiscoveryResult:
    """Find, name and insert the effects the base model lacks; compare model families."""
    settings = settings or DiscoverSettings()
    t_start = time.perf_counter()
    timings: dict[str, float] = {}
    ids_settings = settings.identify
    t0 = time.perf_counter()
    base = _identify_base(campaign, ids_settings)
    timings["identify_s"] = time.perf_counter() - t0
    model = base.model
    id_res = [residual_data(base.prepared[s.id], base.params, base.twins.get(s.id))
              for s in campaign.identification_tests()]
    locations = residual_locations(id_res)
    regions = dominant_regions(locations)
    # the network needs only the base residuals: it trains on one torch thread beside
    # the structure test, which leaves the second core idle between its refits
    neural_pool = neural_job = None
    if settings.neural and "neural" in model.evidence_methods:
        neural_pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="mbst-neural")
        neural_job = neural_pool.submit(_neural_evidence, id_res, settings)
    try:
        return _discover_from_base(campaign, settings, base, id_res, locations, regions,
                                   neural_job, timings, t_start)
    finally:
        if neural_pool is not None:
            neural_pool.shutdown(wait=False, cancel_futures=True)


def _discover_from_base(campaign: Campaign, settings: DiscoverSettings, base: IdentifyResult,
                        id_res: list[TestResidual], locations: list[dict], regions: list,
                        neural_job: Future | None, timings: dict[str, float],
                        t_start: float) -> DiscoveryResult:
    ids_settings = settings.identify
    prepared = base.prepared
    model = base.model
    ids = [prepared[s.id] for s in campaign.identification_tests()]
    scales = channel_scales(ids)

    stage_params = [n for _, names in model.cascade for n in names]
    cascade_free = {st.scenario: list(st.free) for st in base.stages}
    held = set(base.preid.get("held", {}))  # measured directly: never "reset"
    p = base.params.copy()
    cost_cur, res_base = total_cost(ids, p, scales, ids_settings.decimate)
    n_eff_all = effective_samples(res_base)
    cost_base_all = cost_cur
    accepted: list[str] = []
    extra_free: dict[str, tuple[str, ...]] = {}
    rounds: list[dict] = []
    pending: list[tuple[CandidateScore, CandidateScore | None, dict, float, list]] = []
    t0 = time.perf_counter()
    bar = _progress_bar(settings.progress)
    shortlist: set[str] | None = None
    for rnd in range(settings.max_effects):
        reset = compensating_parameters(p, [n for n in stage_params if n not in held], model)

        def tick(phase: str, sc: CandidateScore, _bar=bar, _rnd=rnd) -> None:
            if _bar is not None:
                _bar.set_description(f"round {_rnd + 1} {phase} {sc.key}")
                _bar.update(1 if phase == "screen" else 0)

        if bar is not None:
            bar.reset(total=len(shortlist) if shortlist is not None else len(model.effects))
        scores = structure_test(ids, p, scales, base.preid["upper"], exclude=set(accepted),
                                decimate=ids_settings.decimate, refine=settings.refine,
                                reset=reset, only=shortlist, progress=tick,
                                stage_free=cascade_free,
                                evidence_gain=0.5 * settings.min_relative_gain)
        rec = {"round": rnd + 1, "candidates": [_score_record(s) for s in scores],
               "accepted": None, "reason": ""}
        rounds.append(rec)
        if not scores:
            rec["reason"] = ("no candidate left with evidence from the first round"
                             if shortlist is not None else
                             "no candidate can act in the scenarios tested")
            break
        best = scores[0]
        runner = scores[1] if len(scores) > 1 else None
        if best.relative_gain < settings.min_relative_gain or \
                best.aic_delta > -settings.min_aic_drop:
            rec["reason"] = (
                f"best candidate {best.key} removes {100 * best.relative_gain:.1f} % of the "
                f"{best.stage} cost (ΔAIC {best.aic_delta:.0f}); the margin is "
                f"{100 * settings.min_relative_gain:.0f} % and ΔAIC ≤ −{settings.min_aic_drop:.0f}"
                ": the residual is at the noise floor of the catalogue")
            break
        scorer = StageScorer(model.stage_tests(best.stage, ids), best.stage, p,
                             scales, base.preid["upper"], ids_settings.decimate, reset=reset,
                             free=cascade_free.get(best.stage))
        cv = cross_validate(scorer, best, p, settings.cv_nfev)
        if cv["folds"] and cv["wins"] * 2 < cv["folds"]:
            rec["reason"] = (f"{best.key} lost leave-one-test-out cross-validation "
                             f"({cv['wins']}/{cv['folds']})")
            break
        # extension: the whole cascade refitted with the effect free in its stage
        spec = model.effects[best.key]
        trial_free = dict(extra_free)
        trial_free[best.stage] = tuple(trial_free.get(best.stage, ())) + spec.free
        start = _reset_extension_start(scorer, best, spec)
        p_ext, cost_ext = _extend(campaign, ids_settings, ids, scales,
                                  [best.params, start], trial_free, cost_cur)
        if cost_ext >= cost_cur:
            rec["reason"] = (f"{best.key} won its stage but the refitted cascade did not lower "
                             f"the identification cost ({cost_ext:.4g} ≥ {cost_cur:.4g})")
            break
        rec["accepted"] = best.key
        rec["cross_validation"] = cv
        # later rounds rescore only what showed evidence here: an effect that did not
        # help the base model does not start to once a different one is added
        shortlist = {s.key for s in scores[1:]
                     if s.relative_gain >= 0.5 * settings.min_relative_gain
                     or s.aic_delta <= -settings.min_aic_drop}
        rec["identification_cost"] = {"before": cost_cur, "after": cost_ext}
        accepted.append(best.key)
        extra_free = trial_free
        p, cost_cur = p_ext, cost_ext
        ties = tied_components(best, scores, {r.id: r for r in id_res}, model)
        pending.append((best, runner, cv, akaike_weight(best, scores), ties))
    if bar is not None:
        bar.close()
    timings["structure_s"] = time.perf_counter() - t0
    stick_finding = None
    if settings.stick_slip and "stick_slip" in model.evidence_methods and \
            len(accepted) < settings.max_effects:
        t0 = time.perf_counter()
        rec, stick_finding, p_stick = _stick_slip_round(ids, p, set(accepted), rounds)
        rounds.append(rec)
        if stick_finding is not None:
            accepted.append(rec["accepted"])
            p = p_stick
            cost_cur, _ = total_cost(ids, p, scales, ids_settings.decimate)
        timings["stick_slip_s"] = time.perf_counter() - t0
    eq_finding = None
    if settings.equation_error and model.equation_error is not None and \
            len(accepted) < settings.max_effects:
        t0 = time.perf_counter()
        base_free = list(dict.fromkeys(
            [n for _, names in model.cascade for n in names]
            + [n for k in accepted for n in model.effects[k].free]))
        rec, eq_finding, p_eq = _equation_error_round(model, ids, p, base_free, set(accepted),
                                                      rounds)
        rounds.append(rec)
        if eq_finding is not None:
            # the inverse model named and sized it; the cascade refits the base around it
            accepted.append(rec["accepted"])
            p, _, _, _, _ = run_cascade(campaign, ids_settings, base=p_eq,
                                        extra_free=extra_free)
            cost_cur, _ = total_cost(ids, p, scales, ids_settings.decimate)
        timings["equation_error_s"] = time.perf_counter() - t0

    resolution = []
    if settings.resolution:
        # against the model as it stands: what else these tests could have shown
        t0 = time.perf_counter()
        reset = compensating_parameters(p, [n for n in stage_params if n not in held], model)
        resolution = campaign_resolution(ids, p, scales, cascade_free,
                                         settings.min_relative_gain, settings.min_aic_drop,
                                         exclude=set(accepted), decimate=ids_settings.decimate,
                                         reset=reset)
        timings["resolution_s"] = time.perf_counter() - t0

    # independent evidence from the regressions (identification tests only)
    sparse_ev = neural_ev = None
    neural_model = None
    if settings.sparse and "sparse" in model.evidence_methods:
        t0 = time.perf_counter()
        sparse_ev = _sparse_evidence(id_res)
        timings["sparse_s"] = time.perf_counter() - t0
    if neural_job is not None:
        t0 = time.perf_counter()
        neural_model, neural_ev = neural_job.result()
        timings["neural_s"] = neural_ev.get("train_seconds") or 0.0
        timings["neural_wait_s"] = time.perf_counter() - t0

    findings = []
    for best, runner, cv, weight, ties in pending:
        spec = model.effects[best.key]
        params = {h: float(p[model.param_index[n]]) for h, n in spec.headline.items()}
        cv_frac = cv["wins"] / cv["folds"] if cv.get("folds") else 1.0
        findings.append(Finding(
            effect=spec.effect, component=spec.component, parameters=params,
            confidence=weight * cv_frac,
            evidence=_evidence(best, runner, cv, regions, sparse_ev, neural_ev, ties),
            stage=best.stage, relative_gain=best.relative_gain, aic_delta=best.aic_delta, cv=cv,
            indistinguishable_from=[s.component for s, _ in ties],
        ))
    if stick_finding is not None:
        findings.append(stick_finding)
    if eq_finding is not None:
        findings.append(eq_finding)

    # the held-out control tests measure the gain; they decided nothing above
    t0 = time.perf_counter()
    comparison, twins = _compare(campaign, base, p, id_res, settings, neural_model)
    timings["compare_s"] = time.perf_counter() - t0
    benchmark = model.benchmark(base, p) if model.benchmark is not None else None
    k_added = sum(len(model.effects[k].free) for k in accepted)
    gain = {
        "control_fit_percent_mean": _mean_gain(comparison),
        "aic_delta": float(n_eff_all * math.log(cost_cur / cost_base_all) + 2 * k_added)
        if accepted and cost_base_all > 0 else 0.0,
        "identification_cost_base": cost_base_all,
        "identification_cost_extended": cost_cur,
        "effective_samples": n_eff_all,
    }
    return DiscoveryResult(
        campaign=campaign.name, base=base, extended_params=p, findings=findings, rounds=rounds,
        locations=locations, sparse=sparse_ev, neural=neural_ev, comparison=comparison,
        gain=gain, wall_s=time.perf_counter() - t_start, timings=timings, twins=twins,
        neural_model=neural_model, residual_tests=id_res, settings=settings,
        benchmark=benchmark, resolution=resolution,
    )


def _equation_error_round(model, ids: list[PreparedTest], p: np.ndarray, base_free: list[str],
                          accepted: set[str], rounds: list[dict]
                          ) -> tuple[dict, Finding | None, np.ndarray]:
    """The inverse-model structure test, after the output-error rounds found nothing more.

    Returns the round's record, the finding (or None) and the parameter vector
    with the named effect at its equation-error size (the rest as ``p``).
    """
    from mbst.discovery.rounds import equation_error as eq

    cost_base, _, scores = eq.equation_error_test(model, ids, p, base_free, accepted)
    rec = {"round": len(rounds) + 1, "method": "equation_error", "base_cost": cost_base,
           "candidates": [{**s.record(), "stage": "inverse model"} for s in scores],
           "accepted": None, "reason": ""}
    if not scores or scores[0].relative_gain < eq.MIN_GAIN:
        top = scores[0] if scores else None
        rec["reason"] = ("equation error (inverse model): " + (
            f"best candidate {top.key} removes {100 * top.relative_gain:.1f} % of the base's "
            f"cost" if top else "no candidate") + f"; the margin is {100 * eq.MIN_GAIN:.0f} %")
        return rec, None, p
    best = scores[0]
    rec["accepted"] = best.key
    spec = model.effects[best.key]
    p_new = model.vector_from({n: best.params[model.param_index[n]] for n in spec.free}, base=p)
    total = sum(s.relative_gain for s in scores)
    pars = ", ".join(f"{k} {v:.3g}" for k, v in best.headline.items())
    parts = [f"equation error (the inverse model's force residual on the moving samples of "
             f"the identification tests): inserting {best.effect} in {best.component} "
             f"({pars}) removed {100 * best.relative_gain:.1f} % of the base's cost (margin "
             f"{100 * eq.MIN_GAIN:.0f} %; clean bench campaigns ≤ 3.2 %)"]
    if len(scores) > 1:
        parts.append(f"runner-up {scores[1].key} removed {100 * scores[1].relative_gain:.1f} %")
    seen = next((c for r in reversed(rounds) if r.get("method") is None
                 for c in r.get("candidates", []) if c["key"] == best.key), None)
    if seen is not None:
        parts.append(f"the output-error structure test saw {100 * seen['relative_gain']:.1f} "
                     f"% of its {seen['stage']} cost (below its margin)")
    finding = Finding(
        effect=best.effect, component=best.component,
        parameters={h: float(p_new[model.param_index[n]]) for h, n in spec.headline.items()},
        confidence=best.relative_gain / total if total > 0 else 0.0,
        evidence="; ".join(parts), stage="inverse model", relative_gain=best.relative_gain,
        aic_delta=None, cv={"folds": 0, "criterion": "equation error"},
    )
    return rec, finding, p_new


def _stick_slip_round(ids: list[PreparedTest], p: np.ndarray, accepted: set[str],
                      rounds: list[dict]) -> tuple[dict, Finding | None, np.ndarray]:
    """The phase-free Stribeck test, after the output-error rounds found nothing more."""
    from mbst.discovery.rounds import stickslip

    base_misfit, scores = stickslip.stick_slip_test(ids, p, exclude=accepted)
    rec = {"round": len(rounds) + 1, "method": "stick_slip",
           "base_misfit": {k: round(v, 4) for k, v in base_misfit.items()},
           "candidates": [s.record() for s in scores], "accepted": None, "reason": ""}
    worst = max(base_misfit.items(), key=lambda kv: kv[1], default=("", 0.0))
    if not scores:
        rec["reason"] = (f"no stick-slip: the fast (> {stickslip.HIGHPASS_HZ:g} Hz) envelope "
                         f"of the base model fits to {worst[1]:.2f} noise-power units at worst "
                         f"({worst[0]}); the threshold is {stickslip.MIN_BASE_MISFIT:g}")
        return rec, None, p
    best = scores[0]
    if best.relative_gain < stickslip.MIN_GAIN or best.wins * 2 <= len(best.per_test):
        rec["reason"] = (f"best Stribeck candidate {best.key} removes "
                         f"{100 * best.relative_gain:.0f} % of the envelope misfit and lowers it "
                         f"on {best.wins}/{len(best.per_test)} tests; the margin is "
                         f"{100 * stickslip.MIN_GAIN:.0f} % on most tests")
        return rec, None, p
    rec["accepted"] = best.key
    runner = next((s for s in scores[1:] if s.stage == best.stage), None)
    confidence = best.relative_gain * best.wins / len(best.per_test)
    if best.decided_by != "misfit":
        confidence *= 0.5
    pars = ", ".join(f"{k} {v:.3g}" for k, v in best.headline.items())
    parts = [
        f"stick-slip: the base model leaves {best.misfit_base:.1f} noise-power units of "
        f"misfit in the fast (> {stickslip.HIGHPASS_HZ:g} Hz) envelope of the {best.stage} "
        f"tests (clean campaigns < {stickslip.MIN_BASE_MISFIT:g})",
        f"Stribeck friction in {best.component} ({pars}) removes "
        f"{100 * best.relative_gain:.0f} % of it, lower on {best.wins}/{len(best.per_test)} tests",
    ]
    if runner is not None:
        parts.append(f"runner-up {runner.key} removes {100 * runner.relative_gain:.0f} %"
                     + (f" with {', '.join(runner.at_bound)} on its bound"
                        if runner.at_bound else ""))
    if best.decided_by == "typical size":
        parts.append("a near tie, named by the more typical size (the elements move as one "
                     "body in this stage: a motor angle sensor or a blocked-rack test separates "
                     "them)")
    elif best.decided_by == "range":
        parts.append("the better-fitting look-alike needs a size on the edge of its range")
    prev = next((r for r in reversed(rounds) if r.get("candidates")), None)
    if prev is not None and prev["candidates"]:
        top = prev["candidates"][0]
        parts.append(f"the output-error structure test cannot see it (the sawtooth's phase is "
                     f"not repeatable): its best candidate {top['key']} removed "
                     f"{100 * top['relative_gain']:.1f} %")
    finding = Finding(
        effect=best.effect, component=best.component, parameters=best.headline,
        confidence=confidence, evidence="; ".join(parts), stage=best.stage,
        relative_gain=best.relative_gain, aic_delta=None,
        cv={"folds": len(best.per_test), "wins": best.wins, "criterion": "envelope misfit",
            "per_test": {k: {"misfit_base": b, "misfit": c}
                         for k, (b, c) in best.per_test.items()}},
    )
    return rec, finding, best.params.copy()


def _identify_base(campaign: Campaign, settings: IdentifySettings) -> IdentifyResult:
    """The base cascade on the identification tests; controls are not simulated here."""
    t0 = time.perf_counter()
    p, stages, preid, warnings, prepared = run_cascade(campaign, settings)
    id_fit, twins = correlate([prepared[s.id] for s in campaign.identification_tests()], p)
    return IdentifyResult(campaign.name, p, stages, preid, warnings, id_fit.iloc[0:0], id_fit,
                          time.perf_counter() - t0, prepared, twins, campaign.model())


def _progress_bar(enabled: bool):
    if not enabled:
        return None
    from tqdm import tqdm

    return tqdm(unit="candidate", leave=False)


def _sparse_evidence(id_res: list[TestResidual]) -> dict | None:
    from mbst.discovery.evidence.sindy import residual_regression

    try:
        ev = residual_regression(id_res)
    except Exception as exc:  # evidence only: a failure must not sink the discovery
        return {"error": f"{type(exc).__name__}: {exc}", "ranking": []}
    d = ev.to_dict()
    d["ranking"] = [list(x) for x in ev.ranking]
    return d


def _neural_evidence(id_res: list[TestResidual], settings: DiscoverSettings):
    from mbst.discovery.evidence import neural

    kw = {"seed": settings.identify.seed}
    if settings.neural_iterations is not None:
        kw["iterations"] = settings.neural_iterations
    model = neural.NeuralResidual(**kw).fit(id_res)
    ev = neural.explain(model, id_res)
    ev["train_seconds"] = getattr(model, "train_seconds", None)
    return model, ev


def _compare(campaign: Campaign, base: IdentifyResult, p_ext: np.ndarray,
             id_res: list[TestResidual], settings: DiscoverSettings, neural_model
             ) -> tuple[pd.DataFrame, dict]:
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

    base.correlation, base_tw = correlate(controls, base.params)
    base.twins.update(base_tw)
    add("base", base_tw)
    _, ext_tw = correlate(controls, p_ext)
    add("extended", ext_tw)
    ctrl_res = [residual_data(pt, base.params, base.twins[pt.id]) for pt in controls]
    if settings.sparse and "sparse" in base.model.evidence_methods:
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
    return df, twins


def _mean_gain(df: pd.DataFrame) -> float:
    if df.empty:
        return 0.0
    wide = df.pivot_table(index=["test", "channel"], columns="model", values="fit_percent")
    return float((wide["extended"] - wide["base"]).mean())
