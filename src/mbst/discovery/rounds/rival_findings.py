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
"""

from __future__ import annotations

import dataclasses
import logging

import numpy as np

from mbst.discovery import acceptance, extension, rivals
from mbst.discovery.rounds.catalogue import aic_drop, stage_scorer
from mbst.discovery.state import DiscoveryState, Finding
from mbst.discovery.structure import CandidateScore

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
        findings.append(_finding(state, score, boot, gone))
        physics = with_the_cascade(state, score) if physics is None else physics
    return findings, physics


def with_the_cascade(state: DiscoveryState, score: CandidateScore) -> np.ndarray:
    """The rival's stage refit carried through the cascade: every other stage refitted
    with the rival at its size (a sensor's lag acts on every stage that logs the channel;
    the compact plan's 2.8 ms lag, refitted in the blocked column and added to the
    free-tie-rods stage as that stage was fitted without it, took the control FIT from
    99.0 to 98.5 %). Kept only where it lowers the identification cost."""
    trial_free = dict(state.extra_free)
    trial_free[score.stage] = tuple(trial_free.get(score.stage, ())) + tuple(
        n for n in score.free if n in rivals.parameters(state.model))
    p, cost = extension.extended_cascade(
        state.campaign, dataclasses.replace(state.settings.identify, multistart=1), state.ids,
        state.scales, [score.params], trial_free)
    return p if cost < state.cost else score.params


def _refit(state: DiscoveryState, gone: dict) -> tuple[CandidateScore, dict] | None:
    """The rival ``gone`` refitted in its stage at the model as it stands, and its block
    bootstrap, if it clears the margins there."""
    scorer = stage_scorer(state, gone["stage"])
    spec = next((s for s in rivals.specs(scorer.tests, state.model)
                 if s.key == gone["rival"]), None)
    if spec is None:
        return None
    score = scorer.score(spec, state.base_n_eff)
    short = acceptance.margin_shortfall(score, state.settings.min_relative_gain,
                                        aic_drop(state, score.k_effect))
    if score.fell_back or short is not None:
        log.info("%s at the extended model: %s", spec.key, short or "its refit fell back")
        return None
    boot = acceptance.ranking_bootstrap(scorer, score, [score],
                                        state.settings.min_relative_gain,
                                        state.settings.identify.seed)
    return score, boot


def _finding(state: DiscoveryState, score: CandidateScore, boot: dict, gone: dict
             ) -> Finding:
    kind, quantity = (("drift", "time") if score.effect == rivals.DRIFT
                      else ("lag", score.component))
    size = dict(score.headline)
    said = rivals.reading(score)
    text = (f"OUTSIDE THE CATALOGUE: {said}. In round {_round_of(state, gone)} "
            f"{gone['key']} removed {100 * gone['relative_gain']:.1f} % of the "
            f"{gone['stage']} cost and this alone {100 * gone['rival_relative_gain']:.1f} %, "
            "so the catalogue name was not given; refitted at the extended model it removes "
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
