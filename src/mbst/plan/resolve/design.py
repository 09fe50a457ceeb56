"""Model discrimination: the next tests that let discovery decide its open questions.

For a question (an effect at a size, against the model discovery left) the
two competing models are the model with and without the effect. Their
expected separation on a set of tests is what discovery's structure test
would see (Box–Hill / T-optimal design, linearised as in the resolution step,
``discovery/rounds/resolution.py``): the part ``E`` of the effect's signal
(twin with the effect minus twin without, in the cost's weights) that a refit
of the stage's free parameters cannot take over, against the stage's cost
``C``. The predicted share ``E / (C + E)`` and ``ΔAIC = n_eff · ln(C / (C + E))
+ 2k`` are judged by discovery's own margins.

Every test (logged or predicted, ``candidates.py``) is reduced once to its
blocks — its cost, its residual, the Jacobian of the stage's free
parameters and the signal of each question — so any set of tests is scored
by stacking blocks: the refit is joint over the set, as in discovery.

A rival question (a finding and a look-alike discovery did not rule out) is
scored the same way between its two models: the part of the named model's
signal that the rival's refit (the stage's parameters and the rival's own)
cannot take over. Discovery rules a rival out when the finding wins in 95 %
of block-bootstrap resamples; for a separation ``E`` against noise, the cost
difference has mean ``E`` and a spread that makes that ``sqrt(LR)/2 ≥ 1.645``
with ``LR = n_eff · ln((C + E)/C)``: ``LR ≥ 10.8`` (``RIVAL_LR``).

A signature question (an unexplained finding read two ways, ``signatures.py``)
is scored as a rival one on the finding's channel alone: the best reading's
learned term is the signal, the rival reading's features with the channel's
scale join the stage's refit, and the cost is the channel's.

The selection is greedy on test time: each step adds the candidate that
brings the open questions furthest towards their margins per second of test,
until every question clears them with a safety factor or the budget is spent.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from scipy.stats import norm

from mbst.discovery.acceptance import SEPARATED_SHARE, aic_drop_needed
from mbst.discovery.data import residual_data
from mbst.discovery.rounds.resolution import (
    column_basis,
    effect_signals,
    predicted_score,
    refit_jacobian,
)
from mbst.discovery.structure import StageScorer, effective_samples
from mbst.identify.fitting import PreparedTest, solve
from mbst.plan.resolve.questions import Question
from mbst.plan.resolve.signatures import signature_rows

# the prediction is linear and erred either way near the margins (resolution.py): design
# until each question clears both margins by this factor
SAFETY = 1.5
# the same test repeated at most this often (each repeat: new noise, the same signal)
MAX_REPEATS = 3
# What a test costs besides its duration when tests are compared (setting it up, bringing
# the rig to rest): without it three 2-s triangles beat one 11-s sine per second, and on
# the bench their start from rest, where twin and rig differ most, took back what their
# prediction promised (stribeck column, seed 1: predicted 18.7 % of the stage, named 8.9 %).
# The budget itself counts test time only.
TEST_OVERHEAD_S = 10.0
# the likelihood ratio between two rivals at which the named one wins in SEPARATED_SHARE
# of resamples (module doc)
RIVAL_LR = float((2.0 * norm.ppf(SEPARATED_SHARE)) ** 2)
# evaluations of the rival's refit on the campaign (about what discovery's candidate gets)
RIVAL_REFIT_NFEV = 30
# the least z a campaign's bootstrap is read as (a share of 60 %): below it the rival's
# observed separation says little about how optimistic the linear prediction is
MIN_OBSERVED_Z = float(norm.ppf(0.6))


@dataclass
class TestBlocks:
    """One test reduced to what scoring any set of tests needs."""

    id: str
    stage: str
    duration_s: float
    rows: int  # residual rows (samples × channels, decimated)
    cost: float  # 0.5 Σ r² of the model as it stands, in the cost's weights
    residuals: list[np.ndarray]  # unweighted residual blocks (effective samples)
    jacobians: list[dict[str, np.ndarray]]  # per linearisation point: name -> column
    signals: list[np.ndarray]  # per point: (questions of the stage, rows)
    # per point, per rival question: the rival model's refit Jacobian (rows, its columns)
    rival_jacobians: list[dict[str, np.ndarray]] = field(default_factory=list)
    channels: list[str] = field(default_factory=list)  # the channel of each residual block
    channel_costs: dict[str, float] = field(default_factory=dict)  # cost per channel


@dataclass
class Margins:
    """Discovery's acceptance margins, as the resolution step judges them."""

    min_gain: float
    min_aic_drop: float | None
    candidates: int  # catalogue size (the significance margin's multiple comparisons)

    def drop(self, q: Question) -> float:
        if q.competing:
            return q.lr_needed or RIVAL_LR
        return aic_drop_needed(q.free_count, self.candidates, self.min_aic_drop)

    def progress(self, q: Question, share: float, aic: float) -> float:
        """How far a prediction is towards both margins × SAFETY (1: clears both); a
        rival question has the separation margin only (both models explain the stage)."""
        towards_aic = -aic / (SAFETY * self.drop(q))
        if q.competing:
            return float(np.clip(towards_aic, 0.0, 1.0))
        return float(np.clip(min(share / (SAFETY * self.min_gain), towards_aic), 0.0, 1.0))

    def clears(self, q: Question, share: float, aic: float) -> bool:
        return (q.competing or share >= self.min_gain) and aic <= -self.drop(q)


@dataclass
class Context:
    """What every test of one stage is reduced with."""

    p: np.ndarray
    scales: dict[str, float]
    free: dict[str, list[str]]
    reset: dict[str, float]
    decimate: int
    questions: list[Question]
    margins: Margins
    blocks: dict[str, TestBlocks] = field(default_factory=dict)

    def stage_questions(self, stage: str) -> list[Question]:
        return [q for q in self.questions if q.stage == stage]


def test_blocks(ctx: Context, pt: PreparedTest, stage: str, duration_s: float) -> TestBlocks:
    """Reduce one test (its stage's scorer on it alone: same free set, same weights)."""
    scorer = StageScorer([pt], stage, ctx.p, ctx.scales, decimate=ctx.decimate,
                         free=ctx.free.get(stage), reset=ctx.reset)
    model = scorer.model
    costs, res = scorer.cost_and_residuals(ctx.p)
    points = [ctx.p] + ([scorer.reset_start(ctx.p)] if scorer.reset else [])
    jacs, sigs, rival_jacs = [], [], []
    qs = ctx.stage_questions(stage)
    prob = scorer.problem(scorer.stage_free, ctx.p)
    # the signature questions' rows: the readings are functions of the model's own signals
    readings = {q.key: signature_rows(q, prob, pt, residual_data(pt, ctx.p))
                for q in qs if q.signature is not None}
    for point in points:
        jac = refit_jacobian(scorer, point)
        jacs.append({n: jac[:, i] for i, n in enumerate(scorer.stage_free)})
        sig = np.zeros((len(qs), jac.shape[0]))
        sizes = [i for i, q in enumerate(qs) if not q.competing]
        if sizes:
            sig[sizes] = effect_signals(scorer, point, np.stack(
                [qs[i].models(point, model)[1] for i in sizes]))
        rival_jacs.append({})
        for i, q in enumerate(qs):
            if q.rival is not None:
                sig[i], rival_jacs[-1][q.key] = _rival_blocks(ctx, scorer, q, point)
            elif q.signature is not None:
                sig[i], cols = readings[q.key]
                rival_jacs[-1][q.key] = np.hstack([jac, cols])
        sigs.append(sig)
    channels = list(pt.measured)
    costs_of = {ch: 0.5 * float(np.sum((r * prob._weights(pt, ch)) ** 2))
                for ch, r in zip(channels, res, strict=True)}
    return TestBlocks(pt.id, stage, duration_s, len(jac), float(costs[0]), res, jacs, sigs,
                      rival_jacs, channels, costs_of)


def refit_rival(ctx: Context, q: Question, tests: list[PreparedTest]) -> Question:
    """The rival question with the rival model refitted on the campaign's tests of its
    stage (its own parameters and the stage's, from its size in discovery's round), so
    that the design linearises at the rival's own fit. Linearised at the named model's
    stage parameters instead, a presliding-vs-position-dependent rack pair that discovery
    could not separate was promised 99.9 % of the stage before any test."""
    model = tests[0].model
    rival, _ = q.models(ctx.p, model)
    scorer = StageScorer(tests, q.stage, ctx.p, ctx.scales, decimate=ctx.decimate,
                         free=list(dict.fromkeys([*ctx.free.get(q.stage, []), *q.rival.free])),
                         reset=ctx.reset)
    fr = solve(scorer.problem(scorer.stage_free, rival), [rival], max_nfev=RIVAL_REFIT_NFEV,
               interior=0.0)
    values = {**q.rival_values,
              **{n: float(fr.p[model.param_index[n]]) for n in scorer.stage_free}}
    headline = {h: values[n] for h, n in q.rival.headline.items()}
    return replace(q, rival_values=values, headline=headline)


def calibrate_rivals(ctx: Context, logged: dict[str, list[str]]) -> None:
    """Each rival's needed likelihood ratio, from what discovery's bootstrap saw.

    The linear prediction on the campaign's own tests gives ``z = sqrt(LR)/2``; the
    bootstrap saw the finding win in a share ``Φ(z_obs)`` of resamples. Where the
    prediction is the more optimistic (a rig the model does not fit exactly: coloured,
    uneven residuals), the designed tests must reach ``RIVAL_LR`` times that optimism
    squared. On a realistic bench (presliding rack, rig 104) the campaign's tests were
    predicted at z 1.8 and 2.9 for the finding's two look-alikes, where the bootstrap saw
    0.67 and 0.91.
    """
    before = _all_scores(ctx, logged)
    for q in ctx.questions:
        if not q.competing or q.observed_share is None or q.key not in before:
            continue
        z_pred = float(np.sqrt(max(-before[q.key][1], 0.0))) / 2.0
        z_obs = max(float(norm.ppf(min(q.observed_share, 0.999))), MIN_OBSERVED_Z)
        q.lr_needed = RIVAL_LR * max(1.0, (z_pred / z_obs) ** 2)


def _rival_blocks(ctx: Context, scorer: StageScorer, q: Question, p: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray]:
    """The named model's signal against the rival's (the rival's twin subtracted) and
    what the rival's refit can change: its stage's parameters and its own, at its model."""
    rival, _ = q.models(p, scorer.model)
    free = list(dict.fromkeys([*scorer.stage_free, *q.rival.free]))
    own = StageScorer(scorer.tests, scorer.stage, ctx.p, ctx.scales, decimate=ctx.decimate,
                      free=free, reset=ctx.reset)
    return effect_signals(scorer, rival, p[None])[0], refit_jacobian(own, rival)


def _left_energy(sig: np.ndarray, jac: np.ndarray) -> np.ndarray:
    """0.5·|signal|² left after projecting out what ``jac``'s columns can take over."""
    basis = column_basis(jac)
    left = sig - (sig @ basis) @ basis.T
    e = 0.5 * np.einsum("ij,ij->i", left, left)
    return np.where(np.isfinite(e), e, np.nan)


def score(ctx: Context, stage: str, blocks: list[TestBlocks]) -> list[tuple[float, float]]:
    """Predicted (share, ΔAIC) of each question of ``stage`` on this set of tests."""
    qs = ctx.stage_questions(stage)
    cost = sum(b.cost for b in blocks)
    n_eff = effective_samples([r for b in blocks for r in b.residuals])
    names = sorted({n for b in blocks for jac in b.jacobians for n in jac})
    energy = np.full(len(qs), np.nan)
    for k in range(len(blocks[0].jacobians)):
        # the refit is joint over the set: a parameter a test does not see is a zero column
        jac = np.vstack([np.column_stack([b.jacobians[k].get(n, np.zeros(b.rows))
                                          for n in names]) if names else np.zeros((b.rows, 0))
                         for b in blocks])
        sig = np.hstack([b.signals[k] for b in blocks])
        e = _left_energy(sig, jac)
        for i, q in enumerate(qs):
            if q.competing:
                own = np.vstack([b.rival_jacobians[k][q.key] for b in blocks])
                e[i] = _left_energy(sig[i:i + 1], own)[0]
        energy = np.fmax(energy, e)
    out = []
    for q, e in zip(qs, energy, strict=True):
        c, n = cost, n_eff
        if q.signature is not None:  # judged on its channel, as the unexplained round is
            c, n = _channel_cost(blocks, q.signature.channel)
        out.append(predicted_score(c, 0.0 if np.isnan(e) else float(e), n, q.free_count))
    return out


def _channel_cost(blocks: list[TestBlocks], channel: str) -> tuple[float, float]:
    """One channel's cost over a set of tests, and its effective samples."""
    cost = sum(b.channel_costs.get(channel, 0.0) for b in blocks)
    res = [r for b in blocks for ch, r in zip(b.channels, b.residuals, strict=True)
           if ch == channel]
    return cost, effective_samples(res) if res else 0.0


@dataclass
class Step:
    """One greedy step: the test added and every question's prediction after it."""

    test: str
    duration_s: float
    progress: float  # summed progress towards the margins this test brought
    scores: dict[str, tuple[float, float]]


def _all_scores(ctx: Context, chosen: dict[str, list[str]]) -> dict[str, tuple[float, float]]:
    out = {}
    for stage, ids in chosen.items():
        for q, s in zip(ctx.stage_questions(stage), score(ctx, stage, [ctx.blocks[i] for i in ids]),
                        strict=True):
            out[q.key] = s
    return out


def _total_progress(ctx: Context, scores: dict[str, tuple[float, float]],
                    focus: set[str] | None = None) -> float:
    return sum(ctx.margins.progress(q, *scores[q.key]) for q in ctx.questions
               if focus is None or q.key in focus)


def greedy(ctx: Context, logged: dict[str, list[str]], candidates: list[str],
           budget_s: float, focus: set[str] | None = None
           ) -> tuple[list[Step], dict[str, tuple[float, float]]]:
    """Add candidates (ids in ``ctx.blocks``) while they help and the budget lasts.

    ``logged``: the campaign's own test ids per stage. A candidate may be added up to
    ``MAX_REPEATS`` times (a repeat adds evidence, not share). ``focus``: only these
    questions count (default: all). Returns the steps and the predictions on the
    campaign alone.
    """
    chosen = {st: list(ids) for st, ids in logged.items()}
    before = _all_scores(ctx, chosen)
    current, spent, steps = dict(before), 0.0, []
    uses = dict.fromkeys(candidates, 0)
    wanted = len(focus) if focus is not None else len(ctx.questions)
    while _total_progress(ctx, current, focus) < wanted - 1e-9:
        best = None
        for cid in candidates:
            b = ctx.blocks[cid]
            if (uses[cid] >= MAX_REPEATS or spent + b.duration_s > budget_s
                    or not ctx.stage_questions(b.stage)):
                continue
            scores = {**current,
                      **_all_scores(ctx, {b.stage: chosen.get(b.stage, []) + [cid]})}
            gain = _total_progress(ctx, scores, focus) - _total_progress(ctx, current, focus)
            per_s = gain / (b.duration_s + TEST_OVERHEAD_S)
            if gain > 1e-6 and (best is None or per_s > best[0]):
                best = (per_s, cid, gain, scores)
        if best is None:
            break
        _, cid, gain, scores = best
        b = ctx.blocks[cid]
        chosen[b.stage] = chosen.get(b.stage, []) + [cid]
        uses[cid] += 1
        spent += b.duration_s
        current = scores
        steps.append(Step(cid, b.duration_s, gain, dict(scores)))
    return steps, before


def time_needed(ctx: Context, steps: list[Step]) -> dict[str, float | None]:
    """Per question, the added test time after which it clears 1.5× both margins along
    ``steps`` (None: not along them)."""
    out: dict[str, float | None] = dict.fromkeys((q.key for q in ctx.questions), None)
    spent = 0.0
    for s in steps:
        spent += s.duration_s
        for q in ctx.questions:
            if out[q.key] is None and ctx.margins.progress(q, *s.scores[q.key]) >= 1.0:
                out[q.key] = spent
    return out
