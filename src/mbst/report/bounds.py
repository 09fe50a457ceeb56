"""Fitted parameters that ended on a bound of their search range, base and extended.

The identify step says it of the base model (``identify.md``: "ended on a bound … the base
model may lack an effect and be compensating with this parameter"). Discovery's answer
says what the named effects did to it: on realistic bench rigs the worm-gear stiffness
sat on its lower bound in 42 of 79 stored discoveries, and on one (seed 2301) the
extension with the worm-gear backlash that was named left it there (1000 N·m/rad for a
true 5298), where on the demo the backlash released it (1000 → 7879). A value on a bound
is not a measurement of it: an engineer must not read it as the rig's.
"""

from __future__ import annotations

import numpy as np

from mbst.core.model import ModelDefinition
from mbst.identify.fitting import bound_side


def parameters_on_bounds(model: ModelDefinition, free: list[str], base: np.ndarray,
                         extended: np.ndarray, upper: dict[str, float] | None = None
                         ) -> list[dict]:
    """One row per fitted parameter of the base model (``free``; an effect's own size
    starts at its neutral end) on a bound in the base or the extended fit; ``upper``: the
    tighter upper bounds pre-identification set (``IdentifyResult.preid``)."""
    rows = []
    for name in dict.fromkeys(free):
        spec = model.spec(name)
        if spec.kind != "base":
            continue
        hi = min(spec.upper, (upper or {}).get(name, np.inf))
        i = model.param_index[name]
        was, now = (bound_side(v[i], spec.lower, hi, spec.log_scale) for v in (base, extended))
        if was or now:
            rows.append({"parameter": name, "unit": spec.unit, "base": float(base[i]),
                         "extended": float(extended[i]), "bounds": [spec.lower, hi],
                         "base_on": was, "extended_on": now})
    return rows


def _reading(row: dict, extended: bool) -> str:
    was, now = row["base_on"], row["extended_on"]
    if not extended:
        return ("on its bound: the base model may lack an effect and compensate with it, "
                "or these tests do not pin it")
    if was and now == was:
        return ("still on it with the named effects in: the model still compensates with "
                "it, or these tests do not pin it; its value is not the rig's")
    if was and now:
        return "moved by the extension to its other bound: a named effect trades against it"
    if was:
        return "released by the extension: the named effects took what it stood in for"
    return "driven to it by the extension: a named effect trades against it"


def bound_lines(rows: list[dict], extended: bool) -> list[str]:
    """The report's section; ``extended``: the answer named an effect the fit added."""
    if not rows:
        return []
    lines = ["", "## Fitted parameters on a bound of their range", "",
             "| parameter | base | extended | range | reading |", "|---|---|---|---|---|"]
    for r in rows:
        def value(v: float, on: str | None) -> str:
            return f"{v:.4g}" + (f" (on its {on} bound)" if on else "")

        lo, hi = r["bounds"]
        lines.append(f"| {r['parameter']} | {value(r['base'], r['base_on'])} | "
                     f"{value(r['extended'], r['extended_on'])} | [{lo:.3g}, {hi:.3g}] "
                     f"{r['unit']} | {_reading(r, extended)} |")
    return lines
