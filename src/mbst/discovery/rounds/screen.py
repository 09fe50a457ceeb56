"""Which candidates a later structure round rescores: the linearised screen.

A structure round refits every candidate it scores (``structure.StageScorer.score``),
which costs tens of simulations each; the first round scores the whole catalogue. Once
an effect is in, what is left has changed, and not only for the candidates that showed
evidence before: an effect masked by a larger one (a rack position-dependent friction
behind the torsion-bar stop that miscalibrated the cascade's torsion bar, a worm-gear
backlash beside rack asymmetry) shows only against the extended model. Refitting the
whole catalogue each round would double discovery's time, so each later round first
asks, for every candidate not yet in the model, what a refit of its stage could reach
to first order:

1. the stage refitted as the next round's base (``StageScorer.base_refit``, from the
   model as it stands and its reset variant);
2. the effect at each point of its start grid (``structure.start_grid``; a candidate the
   last round refitted also at the size its refit reached) inserted there, minus the
   base: its signal on the stage's tests, in the cost's weights
   (``resolution.effect_signals``);
3. the signal scaled to fit what is left, from zero up to ``MAX_SCALE`` times, removes
   the share ``(r·d)² / (d·d) / (2C)`` of the stage cost ``C`` — with the stage's
   parameters held, and with what they can take over projected out of both (their
   Jacobian there: the linearised refit); the larger of the two counts.

A candidate whose best grid point reaches the evidence share (half the relevance margin,
as ``acceptance.shows_evidence``) is rescored by a real refit in the next round, which
decides. The estimate errs on the generous side for an effect whose shape changes with
its size (demo, after the worm-gear backlash: tire power-law damping predicted 11 %, its
refit found nothing): that costs a refit, never a finding. Measured against the refits
(realistic rig 121 after the torsion-bar stop, every candidate): position-dependent rack
friction predicted 61.7 %, refitted 62.9 %; the rest predicted 0–2.1 %, refitted 0–2.0 %.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from mbst.core.model import EffectSpec
from mbst.discovery.rounds.resolution import column_basis, effect_signals, refit_jacobian
from mbst.discovery.state import DiscoveryState
from mbst.discovery.structure import CandidateScore, StageScorer, stage_for, start_grid

# the fitted scale of a grid point's signal is trusted up to this many times its size
# (beyond the grid's largest point a first-order estimate of a nonlinear effect says little)
MAX_SCALE = 2.0


@dataclass
class ScreenScore:
    """The linearised refit's gain of one candidate on its stage."""

    key: str
    stage: str
    predicted_gain: float  # share of the stage's cost it would remove
    grid_point: dict[str, float]  # where on its start grid


def stage_residual(scorer: StageScorer, p: np.ndarray) -> np.ndarray:
    """The stage's weighted data residual at ``p`` (the layout of ``effect_signals``)."""
    prob = scorer.problem(scorer.stage_free, p)
    return prob.residuals(prob.u_of(p))[: -len(scorer.stage_free) or None]


def screen(state: DiscoveryState, last: list[CandidateScore],
           scorer_for: Callable[[str], StageScorer], scorers: dict[str, StageScorer]
           ) -> list[ScreenScore]:
    """Every catalogue candidate not in the model, screened against its stage refitted
    as the next round's base (``StageScorer.base_refit``, from the model as it stands and
    its reset variant); a candidate the last round refitted also at the size its refit
    reached. ``scorers`` gets the stage scorers (``scorer_for`` builds them) for the next
    round to go on with."""
    model = state.model
    scenarios = {st for pt in state.ids for st in model.stages_of(pt)}
    fitted = {s.key: {n: float(s.params[model.param_index[n]])
                      for n in model.effects[s.key].free} for s in last}
    by_stage: dict[str, list[EffectSpec]] = {}
    for spec in model.catalogue:
        stage = stage_for(spec, scenarios, model)
        if spec.key not in state.accepted and stage is not None:
            by_stage.setdefault(stage, []).append(spec)
    out = []
    for stage, specs in by_stage.items():
        scorer = scorers[stage] = scorer_for(stage)
        out += screen_stage(scorer, specs, scorer.base_refit()[0], fitted)
    return sorted(out, key=lambda s: -s.predicted_gain)


def screen_stage(scorer: StageScorer, specs: list[EffectSpec], p: np.ndarray,
                 fitted: dict[str, dict[str, float]] | None = None) -> list[ScreenScore]:
    """Each of ``specs`` (all acting in ``scorer``'s stage) at its best grid point
    (``fitted``: more points, key → the effect's parameters)."""
    model = scorer.model
    fitted = fitted or {}
    r = stage_residual(scorer, p)
    if not specs:
        return []
    if not np.all(np.isfinite(r)) or not r.any():
        return [ScreenScore(s.key, scorer.stage, 0.0, {}) for s in specs]
    basis = column_basis(refit_jacobian(scorer, p))
    r_left = r - basis @ (basis.T @ r)
    cost = 0.5 * float(r @ r)
    grids = [start_grid(spec, model) + ([fitted[spec.key]] if spec.key in fitted else [])
             for spec in specs]
    rows = np.repeat(p[None], sum(map(len, grids)), axis=0)
    for i, point in enumerate(pt for grid in grids for pt in grid):
        for n, v in point.items():
            rows[i, model.param_index[n]] = v
    # every grid point of every candidate in one set of rows: the stage's base is then
    # integrated once per step the rows need, not once per candidate (a sixth of the
    # screen's simulations on the demo)
    signals = np.split(effect_signals(scorer, p, rows), np.cumsum(list(map(len, grids)))[:-1])
    out = []
    for spec, grid, ds in zip(specs, grids, signals, strict=True):
        best, where = 0.0, {}
        for point, d in zip(grid, ds, strict=True):
            if not np.all(np.isfinite(d)):
                continue
            # with the stage's parameters moving as their Jacobian says, or held: friction
            # makes the first a poor guide where the refit cannot follow it (realistic rig
            # 120: 24 % of the base residual lay in the Jacobian's span and no refit took
            # it; a motor Dahl term at a grid point removed 21 % held, 3.5 % projected)
            removed = max(_best_scaled(r_left, d - basis @ (basis.T @ d)),
                          _best_scaled(r, d))
            if removed > best:
                best, where = removed, point
        out.append(ScreenScore(spec.key, scorer.stage, min(best / cost, 1.0), where))
    return out


def _best_scaled(r: np.ndarray, d: np.ndarray) -> float:
    """The most of the cost ``½·r·r`` that ``α·d`` removes for ``0 ≤ α ≤ MAX_SCALE`` (the
    residual is twin − measured: the effect helps where its signal opposes it)."""
    dd = float(d @ d)
    if dd <= 0.0:
        return 0.0
    scale = float(np.clip(-(r @ d) / dd, 0.0, MAX_SCALE))
    return 0.5 * (2.0 * scale * -(r @ d) - scale * scale * dd)
