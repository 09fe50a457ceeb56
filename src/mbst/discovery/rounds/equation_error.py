"""Equation-error structure test: what the inverse model sees and a closed loop hides.

A rig under position control (EMPS) is fitted by output error of the closed
loop. On real data that cost has a high floor (EMPS: force FIT 93 %), and a
drive lag of about a millisecond removes 3 % of it, inside what noise gives
on the bench. The inverse model — the force the motion needs, the benchmark
authors' IDIM — has a far lower floor on the samples where the axis moves.
A family that defines ``ModelDefinition.equation_error`` gets this round
after the output-error rounds: every catalogue candidate not yet accepted is inserted and fitted,
with the base parameters, by least squares of that residual on the
identification tests, and scored by the share of the base's equation-error
cost it removes.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from mbst.core.model import ModelDefinition
from mbst.discovery.state import DiscoveryState, Finding
from mbst.identify.cascade import run_cascade
from mbst.identify.fitting import PreparedTest

# Share of the base's equation-error cost an effect must remove. Clean prismatic bench
# campaigns: at most 3.2 % (Stribeck); EMPS's drive lag 41 %.
MIN_GAIN = 0.10


@dataclass
class EquationErrorScore:
    key: str
    effect: str
    component: str
    relative_gain: float
    cost: float
    headline: dict[str, float]
    params: np.ndarray

    def record(self) -> dict:
        return {"key": self.key, "effect": self.effect, "component": self.component,
                "relative_gain": round(self.relative_gain, 5), "cost": self.cost,
                "headline": self.headline}


Residual = Callable[[np.ndarray], np.ndarray]


def _fit(model: ModelDefinition, parts: list[Residual], p: np.ndarray, free: list[str]
         ) -> tuple[np.ndarray, float]:
    idx = np.array([model.param_index[n] for n in free])
    lo = np.array([model.spec(n).lower for n in free])
    hi = np.array([model.spec(n).upper for n in free])

    def residual(x: np.ndarray) -> np.ndarray:
        q = p.copy()
        q[idx] = x
        return np.concatenate([part(q) for part in parts])

    span = hi - lo
    x0 = np.clip(p[idx], lo + 1e-6 * span, hi - 1e-6 * span)
    res = least_squares(residual, x0, bounds=(lo, hi), x_scale="jac")
    out = p.copy()
    out[idx] = res.x
    return out, float(2.0 * res.cost)


def equation_error_test(model: ModelDefinition, tests: list[PreparedTest], p: np.ndarray,
                        base_free: list[str], exclude: set[str]
                        ) -> tuple[float, np.ndarray, list[EquationErrorScore]]:
    """Base cost, refitted base and the candidates' scores, best first.

    ``base_free`` are the parameters refitted with every candidate (the
    cascade's and those of the effects already accepted); each candidate
    starts from its catalogue size.
    """
    parts = [r for r in (model.equation_error(pt) for pt in tests) if r is not None]
    if not parts:
        return 0.0, p, []
    p_base, cost_base = _fit(model, parts, p, base_free)
    scores = []
    for spec in model.catalogue:
        if spec.key in exclude:
            continue
        q = model.vector_from(spec.default_size, base=p_base)
        q, cost = _fit(model, parts, q, base_free + list(spec.free))
        gain = 1.0 - cost / cost_base if cost_base > 0 else 0.0
        scores.append(EquationErrorScore(
            key=spec.key, effect=spec.effect, component=spec.component,
            relative_gain=max(gain, 0.0), cost=cost,
            headline={h: float(q[model.param_index[n]]) for h, n in spec.headline.items()},
            params=q))
    scores.sort(key=lambda s: -s.relative_gain)
    return cost_base, p_base, scores


def equation_error_round(state: DiscoveryState) -> None:
    """The inverse-model structure test, after the output-error rounds found nothing more.

    The inverse model names and sizes the effect; the cascade then refits the base
    around it.
    """
    if not state.room_for_more():
        return
    t0 = time.perf_counter()
    model = state.model
    base_free = list(dict.fromkeys(
        [n for _, names in model.cascade for n in names]
        + [n for k in state.accepted for n in model.effects[k].free]))
    rec, finding, p_eq = _equation_error_record(model, state.ids, state.p, base_free,
                                                set(state.accepted), state.rounds)
    state.rounds.append(rec)
    if finding is not None:
        state.accepted.append(rec["accepted"])
        state.findings.append(finding)
        state.p = run_cascade(state.campaign, state.settings.identify, base=p_eq,
                              extra_free=state.extra_free).params
        state.refit_cost()
    state.timings["equation_error_s"] = time.perf_counter() - t0


def _equation_error_record(model: ModelDefinition, ids: list[PreparedTest], p: np.ndarray,
                           base_free: list[str], accepted: set[str], rounds: list[dict]
                           ) -> tuple[dict, Finding | None, np.ndarray]:
    """The round's record, the finding (or None) and the parameter vector with the named
    effect at its equation-error size (the rest as ``p``)."""
    cost_base, _, scores = equation_error_test(model, ids, p, base_free, accepted)
    rec = {"round": len(rounds) + 1, "method": "equation_error", "base_cost": cost_base,
           "candidates": [{**s.record(), "stage": "inverse model"} for s in scores],
           "accepted": None, "reason": ""}
    if not scores or scores[0].relative_gain < MIN_GAIN:
        top = scores[0] if scores else None
        rec["reason"] = ("equation error (inverse model): " + (
            f"best candidate {top.key} removes {100 * top.relative_gain:.1f} % of the base's "
            f"cost" if top else "no candidate") + f"; the margin is {100 * MIN_GAIN:.0f} %")
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
             f"{100 * MIN_GAIN:.0f} %; clean bench campaigns ≤ 3.2 %)"]
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
