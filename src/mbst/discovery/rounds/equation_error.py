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

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from mbst.core.model import ModelDefinition
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
