"""The size of a friction effect named in a part that moves as one body with another.

Through a stiff mesh the motor and the rack turn as one body: the stage pins the body's
friction, not how the fit splits its Coulomb level between the two parts. An effect whose
size is a ratio of its element's levels (an asymmetry F+/F−, a Stribeck rise F_s/F_c) then
takes the split with it: a realistic rig's rack asymmetry of 0.77 (rack 229 N, motor
0.020 N·m) was fitted as 0.39 on a rack level of 67 N beside a motor level of 0.099 N·m,
and the same 60 N between the directions. Where a finding names such a part "or" another
of its body, it states the size of the body's friction — the same ratio of the parts'
levels summed, each referred to the named part's coordinate by its speed (equal power),
each level from the family's own law (``ModelDefinition.coulomb_level``) — and the named
part's own ratio in the fitted split beside it; the extended model keeps its terms as
fitted.
"""

from __future__ import annotations

import math

import numpy as np

from mbst.core.model import ModelDefinition
from mbst.discovery.data import TestResidual
from mbst.discovery.state import Finding

# per effect: its ratio headline, and the speeds (numerator, denominator) whose levels it
# sets in ratio — forwards over backwards sliding, breakaway over sliding
_RATIOS: dict[str, tuple[str, float, float]] = {
    "asymmetric_friction": ("ratio", math.inf, -math.inf),
    "stribeck_friction": ("static_to_coulomb_ratio", 0.0, math.inf),
}


def state_body_sizes(findings: list[Finding], residuals: list[TestResidual],
                     model: ModelDefinition, p: np.ndarray) -> None:
    """Give each finding that names a part "or" another of its body the size of the body's
    friction (``parameters``), with the part's own size in its evidence."""
    if model.coulomb_level is None:
        return
    for f in findings:
        rule = _RATIOS.get(f.effect)
        spec = model.effects.get(f"{f.effect}:{f.component}")
        if rule is None or spec is None or not spec.level or not f.indistinguishable_from:
            continue
        headline, fast, slow = rule
        own = f.parameters.get(headline)
        tests = [r for r in residuals if r.scenario == f.stage and r.role == "identification"]
        parts = [f.component] + [c for c in f.indistinguishable_from
                                 if f"{f.effect}:{c}" in model.effects]
        referral = _referral(parts, tests, model)
        if len(referral) < 2 or own is None:
            continue
        # the named part's size is the finding's (a stick-slip name need not be in ``p``)
        q = np.array(p, np.float64)
        q[model.param_index[spec.headline[headline]]] = own
        num = sum(s * model.coulomb_level(q, c, fast) for c, s in referral.items())
        den = sum(s * model.coulomb_level(q, c, slow) for c, s in referral.items())
        if not den > 0:
            continue
        f.parameters[headline] = float(num / den)
        unit = model.spec(spec.level).unit
        split = ", ".join(
            f"{c} {s * q[model.param_index[model.effects[f'{f.effect}:{c}'].level]]:.3g} {unit}"
            for c, s in referral.items())
        f.evidence += (
            f"; ONE-BODY SIZE: {' and '.join(referral)} move as one body and these tests do "
            f"not part their Coulomb levels (fitted, referred to the {f.component}: {split}); "
            f"the size given, {headline} {f.parameters[headline]:.3g}, is that of the body's "
            f"friction; the {f.component}'s own {headline} in the fitted split is {own:.3g}")


def body_shares(parts: list[str], tests: list[TestResidual], model: ModelDefinition,
                p: np.ndarray) -> dict[str, float]:
    """Each part's share of the body's sliding friction: its Coulomb level referred to the
    first part's coordinate at equal power, over the sum (empty where the family states no
    levels or the parts have no speeds)."""
    if model.coulomb_level is None:
        return {}
    referral = _referral(parts, tests, model)
    if len(referral) < len(parts):
        return {}
    level = {c: s * abs(model.coulomb_level(p, c, math.inf)) for c, s in referral.items()}
    total = sum(level.values())
    return {c: v / total for c, v in level.items()} if total > 0 else {}


def _referral(parts: list[str], tests: list[TestResidual], model: ModelDefinition
              ) -> dict[str, float]:
    """Each part's speed over the first part's (least squares over the stage's tests): the
    factor that refers its friction to the first part's coordinate at equal power."""
    speeds = model.element_speeds
    if not tests or any(c not in speeds for c in parts):
        return {}
    ref = np.concatenate([r.states[speeds[parts[0]]] for r in tests])
    if float(ref @ ref) <= 0:
        return {}
    return {c: abs(float(np.concatenate([r.states[speeds[c]] for r in tests]) @ ref)
                   / float(ref @ ref)) for c in parts}
