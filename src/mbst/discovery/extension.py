"""The extended model: the whole cascade refitted with an accepted effect free in its stage.

Restart strategies of the extension, each with the campaign that needed it:
the winner's own refit and its reset variant are the deliberate starts; each
start competes with the cascade run from it; the cascade's random restarts run
only where the quick cascade does not lower the identification cost.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from mbst.discovery import rivals
from mbst.discovery.state import DiscoveryState, total_cost
from mbst.discovery.structure import CandidateScore, StageScorer
from mbst.identify.cascade import IdentifySettings, run_cascade
from mbst.identify.fitting import PreparedTest, solve
from mbst.io.campaign import Campaign


def extended_cascade(campaign: Campaign, settings: IdentifySettings,
                      ids: list[PreparedTest], scales: dict[str, float],
                      starts: list[np.ndarray | None], extra_free: dict[str, tuple[str, ...]],
                      work_reference: np.ndarray | None = None) -> tuple[np.ndarray, float]:
    """The cascade refitted with an effect free from each start; the lowest identification cost.

    The starts compete too: a start is the base fit with one stage refitted around the
    effect, already a complete extended model, and a stage-by-stage cascade from it can
    land in a worse basin (powered backlash: start 0.00163, cascade 0.00762, base 0.00413).
    ``work_reference``: the model the stages' work budgets are counted at (``run_cascade``).
    """
    best: tuple[np.ndarray, float] | None = None
    for start in starts:
        if start is None:
            continue
        p = run_cascade(campaign, settings, base=start, extra_free=extra_free,
                        work_reference=work_reference).params
        for q in (p, start):
            cost, _ = total_cost(ids, q, scales, settings.decimate)
            if best is None or cost < best[1]:
                best = (q, cost)
    return best


def extend(campaign: Campaign, settings: IdentifySettings, ids: list[PreparedTest],
            scales: dict[str, float], starts: list[np.ndarray | None],
            extra_free: dict[str, tuple[str, ...]], cost_to_beat: float,
            work_reference: np.ndarray | None = None) -> tuple[np.ndarray, float]:
    """The extended cascade: quick from the deliberate starts, with restarts if that fails.

    First from the two deliberate starts only (the winner's fit, its reset
    variant): around a warm start the cascade's random restart just doubles the
    time (demo: 26 → 10 s, same result). Where that does not lower the
    identification cost below ``cost_to_beat``, the cascade runs again with its
    own restarts (a powered campaign without the current needed them).
    ``work_reference``: the base model, at whose step the stages' work is budgeted: an
    effect whose step is far finer than the base's (a tyre Stribeck dip) spends no more
    in the extension than a candidate's refit may (``work.py``).
    """
    p, cost = extended_cascade(campaign, replace(settings, multistart=1), ids, scales,
                                starts, extra_free, work_reference)
    if cost < cost_to_beat or settings.multistart <= 1:
        return p, cost
    return extended_cascade(campaign, settings, ids, scales, starts, extra_free,
                            work_reference)


def reset_extension_start(scorer: StageScorer, best: CandidateScore, spec
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


def rival_through_cascade(state: DiscoveryState, score: CandidateScore
                          ) -> tuple[np.ndarray, float]:
    """The cascade refitted from a rival's stage refit ``score`` (a sensor's lag, a drift
    over the campaign), the rival free in its stage and held at its size in the others, and
    its identification cost (or the start's, where that is lower)."""
    trial_free = dict(state.extra_free)
    trial_free[score.stage] = tuple(trial_free.get(score.stage, ())) + tuple(
        n for n in score.free if n in rivals.parameters(state.model))
    return extended_cascade(state.campaign, replace(state.settings.identify, multistart=1),
                            state.ids, state.scales, [score.params], trial_free,
                            state.base.params)
