"""Where a refit starts from, in one place: the restarts a fit without an effect needs.

A base model fitted without an effect inflates the parameters that stand in for it
(a stiff gear for a backlash, a high Coulomb level for a Stribeck rise). The
structure test and the extension therefore also start from a *reset* variant,
those parameters at their typical values (``compensating_parameters``); a
candidate with evidence refines from its handbook start
(``structure.StageScorer.handbook_start``).
"""

from __future__ import annotations

import numpy as np

from mbst.core.model import ModelDefinition


def compensating_parameters(p: np.ndarray, names: list[str], model: ModelDefinition,
                            factor: float = 3.0) -> dict[str, float]:
    """Base parameters far from their typical value, with that typical value.

    A base model that lacks an effect hides it by driving parameters to
    unphysical values (gear stiffness 14× too soft, a damping at zero); the
    structure test restarts those at the typical value so the inserted effect
    can take over what they were compensating.
    """
    out = {}
    for n in names:
        spec = model.spec(n)
        if spec.kind != "base" or spec.default <= 0:
            continue
        v = p[model.param_index[n]]
        if not (spec.default / factor <= v <= spec.default * factor):
            out[n] = spec.default
    return out
