"""A reality outside the catalogue that matched a round's winner, read as what it is.

A round declines its winner when a sensor's own lag or a drift of the friction levels
over the campaign removes as much of its stage (``discovery/rivals.py``), and the stage's
misfit goes to the unexplained round. Its generic library reads a lag linearly (d/dt of
the twin) and a drift as a level per cut-out: the compact plan with a 3 ms torque lag
(seed 1), where the lag removed 53 % of the blocked column, ended with no finding at all,
and "nothing" is not what that rig has.

So the rival is refitted once more, at the extended model, in the stage where it matched
the most. Where it still clears the margins a catalogue effect must clear, it is an
``unexplained`` finding with its size in the rig's terms (the lag in ms, the levels'
change over the campaign in %), its confidence the block bootstrap's as for a catalogue
name; its refit is the physics under the "physics + learned" row, and the generic
library then reads what is left after it.

A sensor's lag declines no winner where no catalogue effect comes near, yet it still biases
every stage fitted on its channel: a clean realistic rig on the powered compact plan (a
3 ms torque-sensor lag) left the tie-rod forces reading "the model lags by 1.2 ms" (50 %
of their residual held out); the torque lag, refitted in the loaded stage (2.8 ms, 29 %
of it) and carried through the cascade, left nothing there. So where the generic library
reads a lag, each lag the family declares is refitted in every stage that logs its
channel (``lag_findings``), and the strongest that clears the margins is the finding.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from dataclasses import dataclass

import numpy as np

from mbst.core.model import EffectSpec
from mbst.discovery import acceptance, extension, rivals
from mbst.discovery.rounds.catalogue import aic_drop, stage_scorer
from mbst.discovery.state import DiscoveryState, Finding, total_cost
from mbst.discovery.structure import CandidateScore, StageScorer

log = logging.getLogger(__name__)


def rival_findings(state: DiscoveryState) -> tuple[list[Finding], np.ndarray | None]:
    """The declined rivals that still clear the margins at the extended model, strongest
    first, and the parameters of the strongest one's stage refit (``None``: none)."""
    matched: dict[str, dict] = {}
    for rec in state.rounds:
        # stated values a bit off are the campaign's statement, not the rig's: the round
        # says which would move, and they are never changed (``rivals.py``)
        for gone in (g for g in rec.get("rival_declined", [])
                     if not g["rival"].startswith(rivals.STATED)):
            kept = matched.get(gone["rival"])
            if kept is None or gone["rival_relative_gain"] > kept["rival_relative_gain"]:
                matched[gone["rival"]] = gone
    findings: list[Finding] = []
    physics = None
    for gone in sorted(matched.values(), key=lambda g: -g["rival_relative_gain"]):
        refit = _refit(state, gone)
        if refit is None:
            continue
        score, boot = refit
        how = (f"In round {_round_of(state, gone)} {gone['key']} removed "
               f"{100 * gone['relative_gain']:.1f} % of the {gone['stage']} cost and this "
               f"alone {100 * gone['rival_relative_gain']:.1f} %, so the catalogue name was "
               "not given; refitted at the extended model it removes")
        findings.append(_finding(score, boot, how))
        physics = with_the_cascade(state, score) if physics is None else physics
    return findings, physics


def drift_findings(state: DiscoveryState, p: np.ndarray
                   ) -> tuple[list[Finding], np.ndarray | None]:
    """A drift of the friction levels over the campaign that no round's winner matched,
    screened at ``p`` in every stage whose tests stand at two places or more in the running
    order (one Gauss–Newton step: the drift is linear in its parameter, ``rivals.py``),
    refitted where the step reaches ``SCREEN_SHARE`` of the margin, and the strongest that
    clears the margins a catalogue effect must clear, as a finding with its refit carried
    through the cascade; else ``[]``, ``None``.

    A drift declines only a winner that comes near it, and the generic library reads a
    level per cut-out on held-out tests, where leaving a test out leaves its level unknown:
    realistic rig 2507 (the Coulomb levels falling 30 % as the rig warms up, no catalogue
    effect) ended with no finding at all, its best catalogue candidate at 6.9 %, while the
    drift refitted in the free tie-rods removed 37 % of the stage (ΔAIC −111)."""
    if any(f.effect == "unexplained" and (f.signature or {}).get("kind") == "drift"
           for f in state.findings):
        return [], None
    cleared = []
    for stage in dict.fromkeys(pt.scenario for pt in state.ids):
        scorer = stage_scorer(state, stage, base=p)
        for spec in rivals.specs(scorer.tests, state.model):
            if spec.effect != rivals.DRIFT:
                continue
            step = scorer.linearised_share(spec)
            log.info("drift in %s at the extended model: one step removes %.1f %%",
                     stage, 100 * step)
            if step >= rivals.SCREEN_SHARE * state.settings.min_relative_gain:
                found = _cleared(state, scorer, spec)
                if found is not None:
                    cleared.append(found)
    if not cleared:
        return [], None
    score, boot = max(cleared, key=lambda c: c[0].relative_gain)
    how = (f"No round's winner came near it, so no round set it beside one; let change "
           f"over the campaign's running order in {score.stage} with the stage's "
           "parameters, the friction levels remove")
    return [_finding(score, boot, how)], with_the_cascade(state, score)


def lag_scores(state: DiscoveryState, p: np.ndarray
               ) -> list[tuple[StageScorer, CandidateScore]]:
    """Each sensor lag the family declares, refitted at ``p`` in every stage that logs its
    channel."""
    scores = []
    for stage in dict.fromkeys(pt.scenario for pt in state.ids):
        scorer = stage_scorer(state, stage, base=p)
        scores += [(scorer, scorer.score(spec, state.base_n_eff))
                   for spec in rivals.specs(scorer.tests, state.model)
                   if spec.effect == rivals.LAG]
    return scores


def lag_findings(state: DiscoveryState, scores: list[tuple[StageScorer, CandidateScore]],
                 read: str) -> tuple[list[Finding], np.ndarray | None]:
    """The strongest of the lags' stage refits (``lag_scores``) that clears the margins, as
    a finding (``read``: what the generic library read), and its refit carried through the
    cascade; else ``[]``, ``None``."""
    cleared = [(scorer, score) for scorer, score in scores if _clears(state, score)]
    if not cleared:
        return [], None
    scorer, score = max(cleared, key=lambda c: c[1].relative_gain)
    how = (f"{read}: a delayed sensor biases every stage fitted on it. Refitted in "
           f"{score.stage} with the stage's parameters, the sensor's lag removes")
    return ([_finding(score, _bootstrap(state, scorer, score), how)],
            with_the_cascade(state, score))


@dataclass
class CascadeLag:
    """A sensor's lag refitted in one stage and carried through the whole cascade."""

    score: CandidateScore  # its stage refit
    physics: np.ndarray  # the cascade with it
    cost: float  # the identification cost there
    cost_before: float  # and at the model it was added to
    aic_delta: float  # over the whole campaign (its effective samples)
    lag_s: float  # the lag in the cascade's physics


def lags_through_cascade(state: DiscoveryState, p: np.ndarray,
                         scores: list[tuple[StageScorer, CandidateScore]]
                         ) -> list[CascadeLag]:
    """The lags' stage refits that lowered their stage, each carried through the cascade,
    where the whole campaign's cost falls by the likelihood-ratio margin.

    No stage need clear the share margin alone: a lag acts on every stage fitted on its
    channel. A clean realistic rig on the demo plan (seed 1216, a 3 ms torque-sensor lag,
    known values 15 % off) read "the model lags the tie-rod forces by 1.2 ms" (49 % of
    their residual held out); the lag removed 2.4 / 4.6 / 5.1 % of each stage, and carried
    through the cascade from the free tie-rods (3.05 ms) it lowered the campaign's cost by
    5.3 % (ΔAIC −25 against the −10.4 the test needs) and left no reading at all."""
    cost_before, _ = total_cost(state.ids, p, state.scales, state.settings.identify.decimate)
    trials = []
    for _, score in sorted(scores, key=lambda c: -c[1].relative_gain):
        if score.fell_back or score.relative_gain <= 0.0:
            continue
        physics, cost = extension.rival_through_cascade(state, score)
        aic = state.base_n_eff * math.log(cost / cost_before) + 2 * score.k_effect
        if cost < cost_before and aic <= -aic_drop(state, score.k_effect):
            lag = next(n for n in score.free if n in rivals.parameters(state.model))
            trials.append(CascadeLag(score, physics, cost, cost_before, aic,
                                     state.model.as_dict(physics)[lag]))
    return trials


def cascade_lag_finding(trial: CascadeLag, how: str, confidence: float) -> Finding:
    """A lag carried through the cascade as an ``unexplained`` finding, its size the
    cascade's; ``how``: what it takes of the library's reading."""
    score = dataclasses.replace(trial.score, headline={"lag_s": trial.lag_s},
                                aic_delta=trial.aic_delta)
    gain = 1.0 - trial.cost / trial.cost_before
    said = rivals.reading(score)
    text = (f"OUTSIDE THE CATALOGUE: {said}. {how}. No stage clears the margins alone "
            f"({score.stage}: {100 * trial.score.relative_gain:.1f} %); refitted "
            f"there and carried through the cascade it lowers the identification cost by "
            f"{100 * gain:.1f} % (ΔAIC {trial.aic_delta:.0f} over the campaign)")
    return Finding(
        effect="unexplained", component="", parameters={}, confidence=confidence,
        evidence=text, stage=score.stage, relative_gain=gain, aic_delta=trial.aic_delta,
        cv={"held_out": "tests", "identification_cost_share": gain},
        signature={"kind": "lag", "quantity": score.component, "lag_s": trial.lag_s,
                   "stages": [score.stage], "reading": said, "refitted": "physics",
                   "through": "cascade", "share_of_residual": gain, "channels": []},
    )


def with_the_cascade(state: DiscoveryState, score: CandidateScore) -> np.ndarray:
    """The rival's stage refit carried through the cascade: every other stage refitted
    with the rival at its size (a sensor's lag acts on every stage that logs the channel;
    the compact plan's 2.8 ms lag, refitted in the blocked column and added to the
    free-tie-rods stage as that stage was fitted without it, took the control FIT from
    99.0 to 98.5 %). Kept only where it lowers the identification cost."""
    p, cost = extension.rival_through_cascade(state, score)
    return p if cost < state.cost else score.params


def _refit(state: DiscoveryState, gone: dict) -> tuple[CandidateScore, dict] | None:
    """The rival ``gone`` refitted in its stage at the model as it stands, and its block
    bootstrap, if it clears the margins there."""
    scorer = stage_scorer(state, gone["stage"])
    spec = next((s for s in rivals.specs(scorer.tests, state.model)
                 if s.key == gone["rival"]), None)
    return None if spec is None else _cleared(state, scorer, spec)


def _cleared(state: DiscoveryState, scorer: StageScorer, spec: EffectSpec
             ) -> tuple[CandidateScore, dict] | None:
    """``spec`` refitted with ``scorer``'s stage, and its block bootstrap, if it clears the
    margins a catalogue effect must clear there."""
    score = scorer.score(spec, state.base_n_eff)
    return (score, _bootstrap(state, scorer, score)) if _clears(state, score) else None


def _clears(state: DiscoveryState, score: CandidateScore) -> bool:
    short = acceptance.margin_shortfall(score, state.settings.min_relative_gain,
                                        aic_drop(state, score.k_effect))
    if score.fell_back or short is not None:
        log.info("%s at the extended model: %s", score.key, short or "its refit fell back")
        return False
    return True


def _bootstrap(state: DiscoveryState, scorer: StageScorer, score: CandidateScore) -> dict:
    return acceptance.ranking_bootstrap(scorer, score, [score],
                                        state.settings.min_relative_gain,
                                        state.settings.identify.seed)


def _finding(score: CandidateScore, boot: dict, how: str) -> Finding:
    """A rival's refit as an ``unexplained`` finding; ``how``: why it was refitted, up to
    "it removes"."""
    kind, quantity = (("drift", "time") if score.effect == rivals.DRIFT
                      else ("lag", score.component))
    size = dict(score.headline)
    said = rivals.reading(score)
    text = (f"OUTSIDE THE CATALOGUE: {said}. {how} "
            f"{100 * score.relative_gain:.1f} % of the stage (ΔAIC {score.aic_delta:.0f}); "
            "block bootstrap: above the margin in "
            f"{100 * boot.get('wins_share', 0.0):.0f} % of the resamples")
    return Finding(
        effect="unexplained", component="",
        parameters={}, confidence=float(boot.get("confidence") or 0.0), evidence=text,
        stage=score.stage, relative_gain=score.relative_gain, aic_delta=score.aic_delta,
        cv={"held_out": "block bootstrap", "wins_share": boot.get("wins_share")},
        signature={"kind": kind, "quantity": quantity, **size, "stages": [score.stage],
                   "reading": said, "refitted": "physics",
                   # its share of the stage's residual cost (a physics refit: no terms)
                   "share_of_residual": score.relative_gain, "channels": []},
    )


def _round_of(state: DiscoveryState, gone: dict) -> int:
    return next((rec["round"] for rec in state.rounds if gone in rec.get("rival_declined", [])),
                0)
