"""The backward check: is each effect the forward rounds accepted still needed at the end?

The rounds add one effect at a time, each against the model as it stood. An effect
accepted early may have stood in for one named after it: on the compact plan with a
production-size worm-gear backlash (0.35°) a motor presliding hysteresis won round 1
(0.54) and the backlash round 2. Stepwise regression answers this with a backward
step: each earlier effect is taken out of the final model (its parameters back at their
neutral values, its stage refitted with every other accepted effect free) and must again
clear the margins it was accepted by. One that does not is dropped, and the cascade is
refitted without it.
"""

from __future__ import annotations

import logging

import numpy as np

from mbst.discovery import acceptance, extension
from mbst.discovery.state import DiscoveryState
from mbst.discovery.structure import StageScorer, aic_delta
from mbst.identify.fitting import solve

log = logging.getLogger(__name__)


def backward_check(state: DiscoveryState) -> None:
    """Test every accepted effect but the last against the final model; drop the ones the
    others make up for (a record in ``state.rounds`` either way)."""
    if len(state.accepted) < 2:
        return
    checked = []
    for key in state.accepted[:-1]:
        row, p_without = _still_needed(state, key)
        checked.append(row)
        if not row["needed"]:
            _drop(state, key, row, p_without)
    state.rounds.append({"round": len(state.rounds) + 1, "kind": "backward",
                         "candidates": [], "accepted": None, "checked": checked,
                         "dropped": [r["key"] for r in checked if not r["needed"]],
                         "reason": _reason(checked)})


def _reason(checked: list[dict]) -> str:
    parts = [f"{r['key']} {'still needed' if r['needed'] else 'DROPPED'}: out of the final "
             f"model its stage's cost rises {100 * r['relative_gain']:.1f} % "
             f"(ΔAIC {r['aic_delta']:.0f})" for r in checked]
    return "backward check: " + "; ".join(parts)


def _stage_scorer(state: DiscoveryState, stage: str, free: list[str]) -> StageScorer:
    return StageScorer(state.model.stage_tests(stage, state.ids), stage, state.p,
                       state.scales, state.base.preid["upper"],
                       state.settings.identify.decimate, reset=state.compensating(),
                       free=free, work_reference=state.base.params)


def _still_needed(state: DiscoveryState, key: str) -> tuple[dict, np.ndarray]:
    """The stage refitted without ``key`` (every other accepted effect free): what the
    effect removes from there, judged by the margins it was accepted by."""
    model, spec = state.model, state.model.effects[key]
    stage = next(p.best.stage for p in state.proposals if p.best.key == key)
    scorer = _stage_scorer(state, stage,
                           [n for n in state.model_free(stage) or () if n not in spec.free])
    without = state.p.copy()
    for n in spec.free:
        without[model.param_index[n]] = model.spec(n).default
    # from the final model and from its reset variant, as the rounds' base refit starts
    starts = [without] + ([scorer.reset_start(without)] if scorer.reset else [])
    fr = solve(scorer.problem(scorer.stage_free, without), starts, max_nfev=scorer.max_nfev)
    cost_with, cost_without = (float(c) for c in scorer.costs(
        np.stack([state.p, fr.p])).sum(axis=1))
    cost_without = max(cost_without, cost_with)  # a refit that did worse: the effect stays
    n_eff = scorer.residual_n_eff(state.p)
    gain = 1.0 - cost_with / cost_without if cost_without > 0 else 0.0
    aic = aic_delta(cost_with, cost_without, n_eff, len(spec.free))
    drop = acceptance.aic_drop_needed(len(spec.free), len(model.catalogue),
                                      state.settings.min_aic_drop)
    needed = gain >= state.settings.min_relative_gain and aic <= -drop
    return {"key": key, "stage": stage, "relative_gain": gain, "aic_delta": aic,
            "aic_drop_needed": drop, "needed": bool(needed)}, fr.p


def _drop(state: DiscoveryState, key: str, row: dict, p_without: np.ndarray) -> None:
    """Take ``key`` out: its parameters neutral, not free, the cascade refitted without it."""
    spec = state.model.effects[key]
    trial_free = {st: tuple(n for n in names if n not in spec.free)
                  for st, names in state.extra_free.items()}
    p, cost = extension.extend(state.campaign, state.settings.identify, state.ids,
                               state.scales, [p_without], trial_free,
                               float("inf"), work_reference=state.base.params)
    log.info("backward check: %s dropped (%.1f %% of its stage, ΔAIC %.0f)", key,
             100 * row["relative_gain"], row["aic_delta"])
    state.accepted.remove(key)
    state.proposals = [p_ for p_ in state.proposals if p_.best.key != key]
    state.extra_free = {st: names for st, names in trial_free.items() if names}
    state.p, state.cost = p, cost
