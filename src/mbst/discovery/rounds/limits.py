"""Stated detection limits checked by injection, where the structure test's refit left
them untested.

The resolution step predicts, linearised, what an effect at each size would remove from
its stage (``rounds/resolution.py``). Where the last structure round refitted the pair and
did not clear the margins, the refit ending below the stated limit, nothing contradicts the
limit (``judge_refit``: the rig may simply lack the effect). But the limit claims more:
that the structure test would have named the effect at that size. Where its output-error
refit cannot find the effect from its starts, the claim is false, and an empty answer that
rules the effect out says what these tests did not show (realistic rig 2512: a motor
presliding of stiffness 5.6 missed beside a stick-slip rack Stribeck, while the limit read
"from stiffness 20 down"; the effect at stiffness 2.0, added to that campaign's data, was
refitted back to the stiff end, 0.1 % of its stage, where the prediction said 92.6 %).

So such a limit is tested the way the structure test meets an effect: its signal (the
twin with it minus the twin without, integrated alike) is added to the stage's measured
data, and the candidate is scored there from its own starts (``StageScorer.score``). The
size added is the realistic one where the limit lies below it, else the limit: "shown at
its realistic size" is the statement relied on most, and a stronger effect is not always
the easier to find (on 2512 the same motor presliding added at stiffness 20, ten times
weaker, was recovered, 19.6 % of the stage). Recovered, it clears the margins and the
limit stands, said as checked; not recovered, the limit is withheld on both sides (they
come from one linearisation), and the pair counts as not resolved. The checks cost a candidate's refit
each, so at most ``MAX_INJECTION_CHECKS`` run per campaign, the pairs whose refit found
least first; a limit left unchecked by that cap is said to be.
"""

from __future__ import annotations

import logging
import time
from dataclasses import replace

import numpy as np

from mbst.core.model import ModelDefinition
from mbst.discovery.rounds.catalogue import stage_scorer
from mbst.discovery.rounds.resolution import (
    InjectionCheck,
    Resolution,
    resolution_round,
    scaled_size,
)
from mbst.discovery.rounds.stickslip import EFFECT as STICK_SLIP_EFFECT
from mbst.discovery.state import DiscoveryState
from mbst.discovery.structure import effective_samples
from mbst.identify.fitting import PreparedTest, twins_of_tests

log = logging.getLogger(__name__)

# a check costs about one candidate's score: 10-20 s on a clean realistic rig's free
# tie-rods, 100-230 s in a stick-slip stage (rig 2512)
MAX_INJECTION_CHECKS = 4


def checked_resolution_round(state: DiscoveryState) -> None:
    """The resolution step, then the limits its refits left untested checked by injection."""
    resolution_round(state)
    t0 = time.perf_counter()
    check_limits(state)
    state.timings["limit_checks_s"] = time.perf_counter() - t0


def check_limits(state: DiscoveryState) -> None:
    """Inject each untested limit (``untested_limit``) into its stage's data; withhold the
    ones the structure test does not recover. A failed check costs that check only."""
    min_gain = state.settings.min_relative_gain
    p = state.p_searched if state.p_searched is not None else state.p
    todo = sorted((r for r in state.resolution if untested_limit(r, min_gain, state.model)),
                  key=_least_found_first)
    for r in todo[MAX_INJECTION_CHECKS:]:
        r.injection_skipped = True  # its limit stands unchecked, and the report says so
    for r in todo[:MAX_INJECTION_CHECKS]:
        try:
            r.injection = injected_limit(state, r, p)
        except Exception as exc:  # a check of a statement never sinks the answer
            log.warning("injection check of %s failed: %s: %s", r.key, type(exc).__name__, exc)
            state.failures.append(f"limit check of {r.key}: {type(exc).__name__}: {exc}")
            continue
        if not r.injection.recovered:
            r.resolved_from = r.other_side_resolved_from = None


def untested_limit(r: Resolution, min_gain: float, model: ModelDefinition) -> bool:
    """A limit stated on the side of neutral where the last round's own refit of the pair
    ended without clearing the margins and without contradicting it. Not a Stribeck
    friction where the family runs the phase-free test (``rounds/stickslip.py``): a
    stick-slip's break-away instants hang on the noise, no output-error refit recovers it
    (the compact plan's clean rig: a rack Stribeck of 1.8 added to its data, refitted back
    to 1.0), and the envelope names it instead."""
    c = r.refit
    if c is None or c.round is not None or c.contradicts or r.aic_drop_needed is None:
        return False
    if r.effect == STICK_SLIP_EFFECT and "stick_slip" in model.discovery_rounds:
        return False
    limit = r.other_side_resolved_from if c.other_side else r.resolved_from
    return limit is not None and not c.refit_clears(min_gain, r.aic_drop_needed)


def _least_found_first(r: Resolution) -> tuple[float, float, str]:
    """The refit that found least first (to 0.1 % of its stage: below, the order would
    follow rounding); then the limit claimed most plainly."""
    at_one = r.size_at(1.0)
    return round(r.refit.refit_share, 3), -(at_one.share if at_one else 0.0), r.key


def injected_limit(state: DiscoveryState, r: Resolution, p: np.ndarray) -> InjectionCheck:
    """The structure test's score of ``r``'s pair on its stage's data with the effect added
    at the stated limit, or at the realistic size where the limit lies below it (on the
    side its refit ended)."""
    model = state.model
    spec = model.effects[r.key]
    side = r.refit.other_side
    # at the realistic size where the limit lies below it: the statement relied on most
    # ("shown at its realistic size"), and a stronger effect is not always the easier one
    # to find (rig 2512's motor presliding: recovered at stiffness 20, not at 2.0)
    stated = r.other_side_resolved_from if side else r.resolved_from
    multiple = max(stated, 1.0)
    q = np.array(p, float)
    for n, v in scaled_size(spec, model, multiple, side).items():
        q[model.param_index[n]] = v
    at_limit = scaled_size(spec, model, stated, side)
    limit = {h: float(at_limit.get(n, p[model.param_index[n]]))
             for h, n in spec.headline.items()}
    # a power law's size keeps the stage's damping force, as the resolution step's rows do
    q = stage_scorer(state, r.stage, p).keep_damping_force(q[None], p, spec)[0]
    scorer = stage_scorer(state, r.stage, p, with_signal(model.stage_tests(r.stage, state.ids),
                                                         p, q))
    _, blocks = scorer.cost_and_residuals(p)
    score = scorer.score(spec, effective_samples(blocks))
    recovered = score.relative_gain >= state.settings.min_relative_gain and \
        score.aic_delta <= -r.aic_drop_needed and not score.fell_back
    return InjectionCheck(multiple, side,
                          {h: float(q[model.param_index[n]]) for h, n in spec.headline.items()},
                          score.relative_gain, score.aic_delta, recovered, dict(score.headline),
                          limit)


def with_signal(tests: list[PreparedTest], p: np.ndarray, q: np.ndarray
                ) -> list[PreparedTest]:
    """``tests`` with what ``q`` adds to ``p``'s twin added to their measured channels (both
    twins integrated alike: one batch runs at the step its finest row needs)."""
    out = []
    for pt, (without, with_) in zip(tests, twins_of_tests(tests, [np.stack([p, q])] * len(tests)),
                                    strict=True):
        signal = {ch: with_[ch] - without[ch] for ch in pt.measured}
        if not all(np.all(np.isfinite(s)) for s in signal.values()):
            raise ValueError(f"test '{pt.id}': the model with the injected size does not "
                             "simulate")
        out.append(replace(pt, measured={ch: pt.measured[ch] + signal[ch]
                                         for ch in pt.measured}))
    return out
