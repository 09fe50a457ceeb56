"""The size of a friction effect named in a part that moves as one body with another.

Through a stiff mesh the motor and the rack turn as one body: the stage pins the body's
friction, not how the fit splits its Coulomb level between the two parts. An effect whose
size is a ratio of its element's level (an asymmetry F+/F−, a Stribeck rise F_s/F_c) then
takes the split with it: a realistic rig's rack asymmetry of 0.77 (rack 229 N, motor
0.020 N·m) was fitted as 0.39 on a rack level of 67 N beside a motor level of 0.099 N·m,
and the same 60 N between the directions. Where a finding names such a part "or" another
of its body, it states the size of the body's friction — every part's level referred to
the named part's coordinate by its speed (equal power) — and the named part's own ratio in
the fitted split beside it; the extended model keeps its terms as fitted.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from mbst.core.model import ModelDefinition
from mbst.discovery.data import TestResidual
from mbst.discovery.state import Finding

# per effect: (headline, what a part adds at its referred level L, size of the body from
# the sum D of what the parts add and their summed level)
Rule = tuple[str, Callable[[float, float], float], Callable[[float, float], float]]
_RULES: dict[str, Rule] = {
    # mean kept: F± = 2L·r/(1+r), 2L/(1+r); a part adds F+ − F− to the body's difference
    "asymmetric_friction": ("ratio", lambda r, lvl: 2 * lvl * (r - 1) / (r + 1),
                            lambda d, lvl: (2 * lvl + d) / (2 * lvl - d)),
    # a part adds its rise F_s − F_c to the body's
    "stribeck_friction": ("static_to_coulomb_ratio", lambda r, lvl: lvl * (r - 1),
                          lambda d, lvl: 1 + d / lvl),
}
# a body's level must carry the difference a size describes (a ratio stays finite)
_MAX_SHARE = 0.999


def state_body_sizes(findings: list[Finding], residuals: list[TestResidual],
                     model: ModelDefinition, p: np.ndarray) -> None:
    """Give each finding that names a part "or" another of its body the size of the body's
    friction (``parameters``), with the part's own size in its evidence."""
    for f in findings:
        rule = _RULES.get(f.effect)
        spec = model.effects.get(f"{f.effect}:{f.component}")
        if rule is None or spec is None or not spec.level or not f.indistinguishable_from:
            continue
        tests = [r for r in residuals if r.scenario == f.stage and r.role == "identification"]
        parts = [f.component] + [c for c in f.indistinguishable_from
                                 if f"{f.effect}:{c}" in model.effects]
        headline, adds, size_of = rule
        own = f.parameters.get(headline)
        referred = _referred_levels(parts, tests, model, p, f.effect)
        if len(referred) < 2 or own is None:
            continue
        # the named part's size is the finding's (a stick-slip name need not be in ``p``)
        referred[f.component] = (referred[f.component][0], own)
        level = sum(lvl for lvl, _ in referred.values())
        diff = sum(adds(r, lvl) for lvl, r in referred.values())
        if level <= 0 or abs(diff) >= 2 * _MAX_SHARE * level:
            continue
        f.parameters[headline] = float(size_of(diff, level))
        unit = model.spec(spec.level).unit
        split = ", ".join(f"{c} {lvl:.3g} {unit}" for c, (lvl, _) in referred.items())
        f.evidence += (
            f"; ONE-BODY SIZE: {' and '.join(referred)} move as one body and these tests do "
            f"not part their Coulomb levels (fitted, referred to the {f.component}: {split}); "
            f"the size given, {headline} {f.parameters[headline]:.3g}, is that of the body's "
            f"friction; the {f.component}'s own {headline} in the fitted split is {own:.3g}")


def _referred_levels(parts: list[str], tests: list[TestResidual], model: ModelDefinition,
                     p: np.ndarray, effect: str) -> dict[str, tuple[float, float]]:
    """Each part's Coulomb level at the first part's coordinate (its speed over the first
    part's, least squares over the stage's tests), with the part's size of ``effect``
    (neutral where the model does not carry it there)."""
    speeds = model.element_speeds
    if not tests or any(c not in speeds for c in parts):
        return {}
    ref = np.concatenate([r.states[speeds[parts[0]]] for r in tests])
    if float(ref @ ref) <= 0:
        return {}
    headline = _RULES[effect][0]
    out = {}
    for c in parts:
        spec = model.effects[f"{effect}:{c}"]
        v = np.concatenate([r.states[speeds[c]] for r in tests])
        ratio = abs(float(v @ ref) / float(ref @ ref))
        out[c] = (float(p[model.param_index[spec.level]]) * ratio,
                  float(p[model.param_index[spec.headline[headline]]]))
    return out
