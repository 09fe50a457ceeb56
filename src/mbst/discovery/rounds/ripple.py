"""A ripple locked to a rotating part, read in the residual's fast part and refitted as physics.

A motor's cogging torque repeats N times per revolution of the motor. It reaches the
torque sensor as an oscillation at N times the motor's speed, filtered by the inertias,
and as a level wherever the motor creeps or holds, which the generic library fits with
whatever else varies slowly: the compact plan with a 4 mN·m cogging (seed 1) read "periodic
in motor_angle_rad, 1 period per revolution" on the whole residual, and that reading's
learned term lowered the control FIT (99.18 → 99.00 %). The residual's fast part
(high-passed as the stick-slip round sees it) keeps the oscillation and loses the levels:
there the same campaign reads order 18, 19 % of the fast residual held out against 4 % by
chance.

So where a family declares a ripple (``ModelDefinition.ripple``) and the fast part of a
stage's residual repeats with that part's angle beyond every phase-randomised copy, the
ripple is refitted at that order (its sine and cosine parts with the stage's parameters)
at the model as it stands. Where it clears the margins a catalogue effect must clear, it
is an ``unexplained`` finding with its size (amplitude at the part, periods per
revolution), its confidence the block bootstrap's; its refit, carried through the cascade,
is the physics under "physics + learned". It is never a catalogue name.
"""

from __future__ import annotations

import dataclasses
import logging
import math

import numpy as np

from mbst.core.family import get_system
from mbst.core.filtering import highpass
from mbst.core.model import Ripple
from mbst.discovery import acceptance, rivals
from mbst.discovery.data import TestResidual, residual_data
from mbst.discovery.rounds.catalogue import aic_drop, stage_scorer
from mbst.discovery.rounds.rival_findings import with_the_cascade
from mbst.discovery.signature import SURROGATES, ChannelSignature, describe_channel
from mbst.discovery.state import DiscoveryState, Finding
from mbst.discovery.structure import CandidateScore, StageScorer
from mbst.io.campaign import running_order_places

log = logging.getLogger(__name__)

# a fast residual predicted beyond every phase-randomised copy (p = 1/20) repeats with the
# motion
LOCK_P_VALUE = 1.0 / (1 + SURROGATES)


def fast_part(t: TestResidual) -> TestResidual:
    """``t`` with each channel's residual high-passed as the stick-slip round sees it."""
    return dataclasses.replace(t, measured={
        ch: t.simulated[ch] + highpass(t.residual(ch), t.dt_s) for ch in t.measured})


@dataclasses.dataclass
class Lock:
    """A stage whose fast residual in ``channel`` repeats with a rotating part's angle."""

    stage: str
    channel: str
    signature: ChannelSignature

    @property
    def order(self) -> int:
        return int(self.signature.best.harmonic)


def strongest_lock(tests: list[TestResidual], angle: str, places: dict[str, float],
                   seed: int = 0, input_name: str = "input", beyond_chance: bool = True
                   ) -> Lock | None:
    """The stage and channel whose fast residual repeats with ``angle`` furthest above
    chance (``LOCK_P_VALUE``); ``None`` where none does. ``beyond_chance`` False: the
    best reading of the fast residual is enough where it is periodic in ``angle`` (a
    candidate's order for a refit that decides by itself)."""
    best: tuple[float, Lock] | None = None
    for stage in dict.fromkeys(t.scenario for t in tests):
        fast = [fast_part(t) for t in tests if t.scenario == stage]
        for ch in dict.fromkeys(c for t in fast for c in t.measured):
            # the ranking first, the chance level only where the angle leads (the demo's
            # three stages: 5 s of copies for readings no ripple is)
            first = describe_channel(fast, ch, places, 0.0, seed=seed, surrogates=0,
                                     input_name=input_name)
            if (first is None or first.best is None or first.best.group != f"periodic:{angle}"
                    or first.best.cv_share <= 0):
                continue
            sig = describe_channel(fast, ch, places, 0.0, seed=seed, input_name=input_name)
            if beyond_chance and sig.p_value > LOCK_P_VALUE:
                continue
            lead = sig.best.cv_share - sig.chance_share
            if (lead > 0 or not beyond_chance) and (best is None or lead > best[0]):
                best = (lead, Lock(stage, ch, sig))
    return None if best is None else best[1]


def ripple_findings(state: DiscoveryState, p: np.ndarray
                    ) -> tuple[list[Finding], np.ndarray | None]:
    """The family's ripple refitted at the order the fast residual at ``p`` repeats with,
    if it clears the margins: its finding and the parameters with it, else ``[]``,
    ``None``."""
    if state.model.ripple is None:
        return [], None
    # a stick-slip the ripple matched (``stickslip._declined_for_a_ripple``): the same
    # search, in that stage, as the stick-slip round ran it
    key = rivals.ripple_spec(state.model.ripple).key
    matched = next((g["stage"] for rec in state.rounds for g in rec.get("rival_declined", [])
                    if g["rival"] == key), None)
    found = refit_at_lock(state, p, matched, beyond_chance=matched is None)
    if found is None:
        return [], None
    lock, scorer, score = found
    boot = acceptance.ranking_bootstrap(scorer, score, [score],
                                        state.settings.min_relative_gain,
                                        state.settings.identify.seed)
    return [_finding(state, score, boot, lock)], with_the_cascade(state, score)


def refit_at_lock(state: DiscoveryState, p: np.ndarray, stage: str | None = None,
                  beyond_chance: bool = True
                  ) -> tuple[Lock, StageScorer, CandidateScore] | None:
    """The ripple refitted at ``p`` in the stage (or ``stage``) whose fast residual repeats
    with its part's angle (``strongest_lock``), at that order; ``None`` where none repeats,
    or where the refit does not clear the margins a catalogue effect must clear."""
    ripple = state.model.ripple
    if ripple is None:
        return None
    tests = [residual_data(pt, p) for pt in state.ids if stage in (None, pt.scenario)]
    lock = strongest_lock(tests, ripple.angle,
                          running_order_places([s.id for s in state.campaign.tests]),
                          state.settings.identify.seed,
                          get_system(state.model.name).input_channel, beyond_chance)
    if lock is None:
        return None
    base = state.model.vector_from({ripple.order: lock.order}, base=p)
    scorer = stage_scorer(state, lock.stage, base=base)
    score = scorer.score(rivals.ripple_spec(ripple), state.base_n_eff)
    short = acceptance.margin_shortfall(score, state.settings.min_relative_gain,
                                        aic_drop(state, score.k_effect))
    if score.fell_back or short is not None:
        log.info("ripple at order %d in %s: %s", lock.order, lock.stage,
                 short or "its refit fell back")
        return None
    return lock, scorer, score


def ripple_size(score: CandidateScore) -> tuple[float, float]:
    """Amplitude and phase of a ripple's refit: a·sin x + b·cos x = A·sin(x + φ)."""
    a, b = score.headline.get("sine_nm", 0.0), score.headline.get("cosine_nm", 0.0)
    return math.hypot(a, b), math.atan2(b, a)


def ripple_reading(ripple: Ripple, score: CandidateScore, order: int) -> str:
    """What a ripple's refit says, in the rig's terms."""
    return (f"a torque ripple of {1e3 * ripple_size(score)[0]:.1f} mN·m at the "
            f"{ripple.component}, {order} periods per revolution of {ripple.angle} (a cogging)")


def _finding(state: DiscoveryState, score: CandidateScore, boot: dict, lock: Lock
             ) -> Finding:
    ripple = state.model.ripple
    amplitude, phase = ripple_size(score)
    fast = lock.signature
    said = ripple_reading(ripple, score, lock.order)
    how = ("repeats with" if fast.best.cv_share > fast.chance_share
           else "is read best, though not beyond chance alone, as periodic in")
    text = (f"OUTSIDE THE CATALOGUE: {said}. The fast part of the {lock.stage} residual in "
            f"{lock.channel} {how} {ripple.angle} at order {lock.order} "
            f"({100 * fast.best.cv_share:.1f} % held out against "
            f"{100 * fast.chance_share:.1f} % by chance); refitted at that order with the "
            f"stage's parameters, the ripple removes {100 * score.relative_gain:.1f} % of "
            f"the stage cost (ΔAIC {score.aic_delta:.0f}); block bootstrap: above the "
            f"margin in {100 * boot.get('wins_share', 0.0):.0f} % of the resamples")
    return Finding(
        effect="unexplained", component=ripple.component, parameters={},
        confidence=float(boot.get("confidence") or 0.0), evidence=text,
        stage=score.stage, relative_gain=score.relative_gain, aic_delta=score.aic_delta,
        cv={"held_out": "block bootstrap", "wins_share": boot.get("wins_share")},
        signature={"kind": "periodic", "quantity": ripple.angle,
                   "periods_per_rev": float(lock.order), "amplitude": amplitude,
                   "phase_rad": phase, "stages": [score.stage], "reading": said,
                   "refitted": "physics", "share_of_residual": score.relative_gain,
                   "fast_share": fast.best.cv_share, "fast_chance_share": fast.chance_share,
                   "channels": []},
    )
