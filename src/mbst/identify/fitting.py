"""Output-error fitting of the physics model to filtered test data.

Shared by identification (the cascade) and discovery (refits with an
inserted effect). Tests are prepared once (filtered, input rate computed);
a ``FitProblem`` frees a subset of the parameter vector and exposes
residuals and a batched finite-difference Jacobian to
``scipy.optimize.least_squares``.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from types import SimpleNamespace

import numpy as np
import pandas as pd
from scipy.optimize import least_squares

from mbst.core.filtering import (
    INPUT_WINDOW_S,
    exponential_filter,
    filtered_noise_gain,
    white_noise_std,
)
from mbst.core.model import ModelDefinition
from mbst.identify.work import WORK_BUDGET_FACTOR, WorkMeter, WorkSpent, simulation_steps
from mbst.io.campaign import Campaign, CampaignError, TestSpec, running_order_places

log = logging.getLogger(__name__)

# campaign.yaml key that marks a campaign written by `mbst preprocess` (already filtered)
PREPROCESSED_KEY = "preprocessed"


@dataclass
class PreparedTest:
    """One test ready for fitting: model input and filtered measured outputs."""

    spec: TestSpec
    time_s: np.ndarray
    input_signal: np.ndarray
    input_rate: np.ndarray
    measured: dict[str, np.ndarray]
    dt_s: float
    tau_s: float
    raw: dict[str, np.ndarray] = field(default_factory=dict, repr=False)
    model: ModelDefinition | None = field(default=None, repr=False)
    inputs: dict[str, np.ndarray] = field(default_factory=dict, repr=False)
    # white-noise level of each filtered measured channel (sensor noise, not misfit)
    noise: dict[str, float] = field(default_factory=dict, repr=False)
    # rms of what the input sensor's noise, through the model, leaves on each channel
    # (``input_noise_floors``; empty until discovery measures it)
    input_floor: dict[str, float] = field(default_factory=dict, repr=False)
    # the test's place in the campaign's running order, −½ (first) … ½ (last): where a
    # rig that drifts over the campaign stands (``ModelDefinition.campaign_drift``)
    place: float = 0.0

    @property
    def angle_in_rad(self) -> np.ndarray:
        """The steering rig's name for the driving input (the measured angle)."""
        return self.input_signal

    @property
    def omega_rad_per_s(self) -> np.ndarray:
        return self.input_rate

    @property
    def id(self) -> str:
        return self.spec.id

    def floor(self, channel: str) -> float:
        """What the true model would leave on ``channel``: the sensor's own noise with the
        input's noise through the model (``input_floor``), both as the fit sees them."""
        return math.hypot(self.noise.get(channel, 0.0), self.input_floor.get(channel, 0.0))

    @property
    def scenario(self) -> str:
        return self.spec.scenario


def prepare_test(campaign: Campaign, spec: TestSpec, tau_s: float,
                 input_window_s: float = INPUT_WINDOW_S) -> PreparedTest:
    """Filter a test's channels and derive the model input.

    The family's model says how its input is derived (the EPS rig: the
    measured angle smoothed without lag); simulated outputs then get the same
    causal exponential filter as the measured ones, so both sides carry the
    same phase lag (eps-model.md, "Preprocessing").
    """
    done = campaign.extra.get(PREPROCESSED_KEY)
    if done and tau_s > 0:
        # filtering twice would compare a twice-filtered measurement with a once-filtered twin
        raise CampaignError(
            f"is already filtered (campaign.yaml 'preprocessed:', from "
            f"{done.get('from', '?') if isinstance(done, dict) else done}); fit the raw "
            "campaign it came from, or pass --tau 0",
            campaign=campaign.name, path=campaign.path / "campaign.yaml")
    pt = prepare_frame(campaign.model(), campaign.frame(spec.id), spec, tau_s, input_window_s)
    pt.place = running_order_places([s.id for s in campaign.tests]).get(spec.id, 0.0)
    return pt


def prepare_frame(model: ModelDefinition, df: pd.DataFrame, spec: TestSpec, tau_s: float,
                  input_window_s: float = INPUT_WINDOW_S) -> PreparedTest:
    """``prepare_test`` of a logged frame that is not (yet) in a campaign: a test the
    planner predicts goes through the very preprocessing a logged one will."""
    t = df["time_s"].to_numpy(float)
    dt = float((t[-1] - t[0]) / (len(t) - 1))
    signal, rate, inputs = model.prepare_inputs(df, dt, spec, input_window_s)
    measured = {}
    raw = {}
    noise = {}
    gain = filtered_noise_gain(dt, tau_s)
    for ch in model.output_channels:
        if ch in df.columns:
            raw[ch] = df[ch].to_numpy(float)
            measured[ch] = exponential_filter(raw[ch], dt, tau_s)
            noise[ch] = white_noise_std(raw[ch], dt) * gain
    return PreparedTest(spec, t, signal, rate, measured, dt, tau_s, raw, model, inputs, noise)


def input_noise_floors(frames: dict[str, pd.DataFrame], tests: list[PreparedTest],
                       p: np.ndarray, input_channel: str, seed: int = 0) -> None:
    """Set each test's ``input_floor``: how far the model's twin moves when its input
    carries a second draw of the input sensor's noise (at the level measured on it).

    The model is driven by the measured input, smoothed; the rig by the true one. The
    input's noise through the model is then part of every residual no model removes: on
    the compact plan, 2× the torque sensor's noise on a blocked column and 2–5× the motor
    angle sensor's (0.05° of steering angle × the worm-gear ratio), where a phase-free
    ripple of 1.1× the motor angle's noise was taken for structure.
    """
    alts = []
    rng = np.random.default_rng([seed, 13])
    for pt in tests:
        frame = frames[pt.id].copy()
        raw = frame[input_channel].to_numpy(float)
        frame[input_channel] = raw + white_noise_std(raw, pt.dt_s) * rng.standard_normal(len(raw))
        alts.append(prepare_frame(pt.model, frame, pt.spec, pt.tau_s))
    twins = twins_of_tests(tests + alts, [p[None]] * (2 * len(tests)))
    for pt, (a,), (b,) in zip(tests, twins[: len(tests)], twins[len(tests):], strict=True):
        pt.input_floor = {ch: float(np.std(b[ch] - a[ch])) if np.all(np.isfinite(b[ch]))
                          else 0.0 for ch in pt.measured}


def _filtered(pt: PreparedTest, sim: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    out = {ch: exponential_filter(sim[ch], pt.dt_s, pt.tau_s) for ch in pt.measured}
    for k, v in sim.items():
        if k.startswith("internal."):
            out[k] = v
    return out


def twins_of_tests(pts: list[PreparedTest], pss: list[np.ndarray]
                   ) -> list[list[dict[str, np.ndarray]]]:
    """Simulated channels of several tests, each for its own parameter rows, filtered like
    their measured twins (internal signals, ``internal.*``, unfiltered).

    Every simulation of identification and discovery comes through here: the
    family's ``simulate_tests`` spreads them over the cores as one set.
    """
    if not pts:
        return []
    many = pts[0].model.simulate_tests
    # a rig that drifts over the campaign runs each test at its own levels
    pss = [pt.model.at_place(np.atleast_2d(ps), pt.place) for pt, ps in zip(pts, pss, strict=True)]
    sims = many(pts, [np.atleast_2d(ps) for ps in pss]) if many is not None else [
        pt.model.simulate_batch(pt, ps) for pt, ps in zip(pts, pss, strict=True)]
    return [[_filtered(pt, sim) for sim in rows] for pt, rows in zip(pts, sims, strict=True)]


def step_groups(pt: PreparedTest, ps: np.ndarray) -> list[np.ndarray]:
    """Indices of the rows of ``ps`` grouped by the integration step each needs on ``pt``.

    A batch runs at the finest step any of its rows needs (``simulate_tests``); rows
    grouped so are each integrated as they would be alone. One group where the family
    has no step rule.
    """
    ps = np.atleast_2d(ps)
    steps = pt.model.row_steps
    if steps is None or len(ps) < 2:
        return [np.arange(len(ps))]
    n = np.asarray(steps(pt, ps))
    return [np.flatnonzero(n == k) for k in np.unique(n)]


def batches_by_step(pts: list[PreparedTest], pss: list[np.ndarray],
                    lead: np.ndarray | None = None
                    ) -> tuple[list[PreparedTest], list[np.ndarray], list[tuple[int, np.ndarray]]]:
    """Each test's rows split into batches of rows that need the same step
    (``step_groups``), as ``twins_of_tests`` takes them: the tests, the batches, and
    for each batch (test index, row indices). With ``lead``, that row comes first in every
    batch, integrated at the batch's step (what a difference to it needs)."""
    flat_pts, flat_ps, where = [], [], []
    for t, (pt, ps) in enumerate(zip(pts, pss, strict=True)):
        ps = np.atleast_2d(ps)
        for idx in step_groups(pt, ps):
            flat_pts.append(pt)
            flat_ps.append(ps[idx] if lead is None else np.vstack([lead[None], ps[idx]]))
            where.append((t, idx))
    return flat_pts, flat_ps, where


def twins_each_alone(pts: list[PreparedTest], pss: list[np.ndarray]
                     ) -> list[list[dict[str, np.ndarray]]]:
    """``twins_of_tests`` with every row integrated at the step it needs itself, as one
    residual evaluation integrates it: for rows that are separate candidates (a grid, a
    bootstrap), not the perturbations of one Jacobian. A Stribeck grid's steepest dip
    set the step of the whole grid, twice the work of its rows alone.
    """
    flat_pts, flat_ps, where = batches_by_step(pts, pss)
    out: list[list] = [[None] * len(np.atleast_2d(ps)) for ps in pss]
    for (t, idx), rows in zip(where, twins_of_tests(flat_pts, flat_ps), strict=True):
        for i, tw in zip(idx, rows, strict=True):
            out[t][i] = tw
    return out


def simulate_twin(pt: PreparedTest, p: np.ndarray) -> dict[str, np.ndarray]:
    """Simulated channels of a prepared test, filtered like their measured twins.

    Internal signals (``internal.*``) come unfiltered.
    """
    return twins_of_tests([pt], [np.asarray(p, float)[None]])[0][0]


def channel_scales(tests: list[PreparedTest]) -> dict[str, float]:
    """Pooled standard deviation of each measured channel (residual weights)."""
    pooled: dict[str, list[np.ndarray]] = {}
    for pt in tests:
        for ch, y in pt.measured.items():
            pooled.setdefault(ch, []).append(y - y.mean())
    return {ch: float(np.std(np.concatenate(v))) or 1.0 for ch, v in pooled.items()}


# the prior's weight on noise-free data, where the noise floor is zero
PRIOR_WEIGHT_FLOOR = 1e-9
# A weighted residual beyond this (or not finite) comes from a simulation that diverged:
# it is set to this size, so the optimiser sees a large finite cost and steps back. Fitted
# residuals are O(1) (channels are scaled by their spread); squared and summed over 1e5
# samples the bound stays far from overflow, where least_squares would stop with
# "array must not contain infs or NaNs" and the answer would be lost.
DIVERGED_RESIDUAL = 1e6


class FitProblem:
    """Least-squares problem over the free parameters ``free``.

    Parameters are mapped to an unconstrained-ish coordinate ``u``: the log
    for positive log-scale parameters, value/typical otherwise, so that
    finite differences and trust regions see comparable steps.
    """

    def __init__(
        self,
        tests: list[PreparedTest],
        channels: dict[str, list[str]],
        free: list[str],
        base: np.ndarray,
        scales: dict[str, float],
        lower: dict[str, float] | None = None,
        upper: dict[str, float] | None = None,
        decimate: int = 1,
        prior_weight: float | None = None,
        prior: dict[str, tuple[float, float]] | None = None,
        stated: frozenset[str] = frozenset(),
    ) -> None:
        self.tests = tests
        self.channels = channels
        self.free = list(free)
        self.base = np.array(base, dtype=float)
        self.scales = scales
        self.decimate = max(1, int(decimate))
        self.model = tests[0].model if tests else None
        self.idx = np.array([self.model.param_index[n] for n in self.free], dtype=int)
        specs = [self.model.param_specs[i] for i in self.idx]
        lo = np.array([(lower or {}).get(s.name, s.lower) for s in specs])
        hi = np.array([(upper or {}).get(s.name, s.upper) for s in specs])
        self.log = np.array([s.log_scale and s.lower > 0 for s in specs])
        self.typ = np.array([max(abs(s.default), (s.upper - s.lower) / 20.0, 1e-12)
                             for s in specs])
        self.lb = self._to_u(lo)
        self.ub = self._to_u(hi)
        self.ties = self._ties(prior or {}, lo, hi)
        self.n_eval = 0
        # integration steps spent by the current run, its limit and best point (``work.py``)
        self.work = WorkMeter()
        # steps of one evaluation at the problem's base (where its weak prior holds what
        # the data cannot see): the work budget's unit, set at the first solve
        self.reference_steps: float | None = None
        # residual evaluations whose simulation diverged (mapped to DIVERGED_RESIDUAL)
        self.n_diverged = 0
        # the last residual evaluation (u, data residual of each test): least_squares asks
        # for the Jacobian where it has just evaluated the residuals
        self._last: tuple[np.ndarray, list[np.ndarray]] | None = None
        # weak prior towards the start: keeps a parameter the data cannot see where it
        # was (flagged non-identifiable) instead of letting it drift to a bound
        self.u_prior = self.u_of(self.base)
        if prior_weight is None:
            prior_weight = self.noise_floor()
        self.prior_w = np.array([0.0 if n.startswith("offset.") else prior_weight
                                 for n in self.free])
        # an explicit prior (value, std of ln θ), e.g. a plan's ranges: Gaussian on the
        # scale of the data's noise, so it yields to data in proportion to their information
        floor = self.noise_floor() if prior else 0.0
        for j, n in enumerate(self.free):
            if prior and n in prior:
                value, std_log = prior[n]
                self.u_prior[j] = math.log(value) if self.log[j] else value / self.typ[j]
                std_u = std_log if self.log[j] else abs(value) * std_log / self.typ[j]
                self.prior_w[j] = floor / max(std_u, 1e-12)
        # priors the campaign states (a datasheet value ± σ) are information like data: they
        # count in the standard errors; a plan's range prior only steadies the search
        self.stated = np.array([bool(prior) and n in prior and n in stated for n in self.free])
        # how much the fitted residual's variance (model error, residual memory) exceeds the
        # sensor noise the stated priors were weighted against (``inflate_stated``)
        self.prior_inflation = 1.0

    def inflate_stated(self, factor: float) -> None:
        """Weigh the stated priors against residuals ``factor`` × the sensor noise's variance.

        Data whose residual is larger or longer-correlated than white sensor noise carry
        less information than their sample count says; a prior weighted against the sensor
        noise alone is then overruled along every direction the data barely see.
        """
        factor = max(float(factor), 1.0)
        self.prior_w = np.where(self.stated,
                                self.prior_w * math.sqrt(factor / self.prior_inflation),
                                self.prior_w)
        self.prior_inflation = factor

    def _ties(self, prior: dict, lo: np.ndarray, hi: np.ndarray
              ) -> dict[int, tuple[int, float, float, float]]:
        """Free parameters held at a free partner's value × a ratio (``ModelDefinition.ties``):
        position in ``free`` → (partner's position, ratio, this problem's bounds of it). The
        ratio is the start's (the typical one, or the split a base fit settled on); a prior
        stated for either sets the split instead."""
        out = {}
        for name, (partner, typical) in self.model.ties.items() if self.model else ():
            if name not in self.free or partner not in self.free or name in prior \
                    or partner in prior:
                continue
            i, k = self.model.param_index[name], self.model.param_index[partner]
            ratio = self.base[i] / self.base[k] if self.base[i] > 0 and self.base[k] > 0 \
                else typical
            j = self.free.index(name)
            out[j] = (self.free.index(partner), ratio, float(lo[j]), float(hi[j]))
        return out

    # coordinates ------------------------------------------------------------------
    def _to_u(self, theta: np.ndarray) -> np.ndarray:
        theta = np.asarray(theta, float)
        return np.where(self.log, np.log(np.maximum(theta, 1e-300)), theta / self.typ)

    def _from_u(self, u: np.ndarray) -> np.ndarray:
        return np.where(self.log, np.exp(u), u * self.typ)

    def dtheta_du(self, u: np.ndarray) -> np.ndarray:
        return np.where(self.log, np.exp(u), self.typ)

    def u_of(self, p: np.ndarray) -> np.ndarray:
        return np.clip(self._to_u(p[self.idx]), self.lb, self.ub)

    def p_of(self, u: np.ndarray) -> np.ndarray:
        p = self.base.copy()
        theta = self._from_u(u)
        for j, (k, ratio, lo, hi) in self.ties.items():
            theta[j] = min(max(theta[k] * ratio, lo), hi)
        p[self.idx] = theta
        return p

    # residuals --------------------------------------------------------------------
    def _weights(self, pt: PreparedTest, ch: str) -> float:
        # each test counts alike whatever its length; channels in units of their spread
        n = len(pt.time_s[:: self.decimate])
        return 1.0 / (self.scales[ch] * math.sqrt(n))

    def _res_of_twin(self, pt: PreparedTest, twin: dict[str, np.ndarray]) -> np.ndarray:
        parts = []
        for ch in self.channels[pt.id]:
            w = self._weights(pt, ch)
            parts.append(((twin[ch] - pt.measured[ch]) * w)[:: self.decimate])
        return np.concatenate(parts) if parts else np.zeros(0)

    def noise_floor(self) -> float:
        """RMS sensor noise of one weighted residual: the prior's weight for one unit of u.

        A Gaussian prior of one unit of u (a factor e for a log-scale
        parameter) around the start, on the scale of the data's own noise: it
        holds a direction the data cannot see, and yields to any the data can.
        A fixed weight did not: on clean data it pulled the column's viscous
        friction to −68 % of its true value.
        """
        var = [(pt.noise.get(ch, 0.0) * self._weights(pt, ch)) ** 2
               for pt in self.tests for ch in self.channels[pt.id]]
        return max(math.sqrt(float(np.mean(var))) if var else 0.0, PRIOR_WEIGHT_FLOOR)

    def block_sizes(self) -> list[int]:
        """Length of each (test, channel) block of the data residuals, in order."""
        return [len(pt.time_s[:: self.decimate]) for pt in self.tests
                for _ in self.channels[pt.id]]

    def residuals(self, u: np.ndarray) -> np.ndarray:
        p = self.p_of(u)
        self.work.charge(self.steps(p[None]))
        self.n_eval += 1
        twins = twins_of_tests(self.tests, [p[None]] * len(self.tests))
        out = [self._res_of_twin(pt, tw[0]) for pt, tw in zip(self.tests, twins, strict=True)]
        self._last = (np.array(u, float, copy=True), out)
        r = self._bounded(np.concatenate([*out, self.prior_w * (u - self.u_prior)]))
        self.work.seen(u, r)
        return r

    def steps(self, ps: np.ndarray) -> float:
        """Integration steps of simulating the rows ``ps`` on every test (``work.py``)."""
        return sum(simulation_steps(pt, ps) for pt in self.tests)

    def count_work_at(self, reference: np.ndarray | None) -> None:
        """Budget this problem's work at ``reference``'s step instead of its base's
        (``work.py``); ``None`` leaves the base."""
        if reference is not None:
            self.reference_steps = self.steps(np.asarray(reference, float)[None])

    def budget(self, max_nfev: int) -> float:
        """The steps a run of ``max_nfev`` evaluations may spend: ``WORK_BUDGET_FACTOR`` ×
        what they cost at the reference step, each with its Jacobian."""
        columns = sum(1 for j, n in enumerate(self.free)
                      if n not in self.model.offset_channels and j not in self.ties)
        return WORK_BUDGET_FACTOR * max_nfev * (2 + columns) * (self.reference_steps or 0.0)

    def _bounded(self, r: np.ndarray) -> np.ndarray:
        """``r`` with a diverged simulation's residuals at ``±DIVERGED_RESIDUAL``."""
        with np.errstate(invalid="ignore"):
            bad = ~(np.abs(r) <= DIVERGED_RESIDUAL)
        if not bad.any():
            return r
        self.n_diverged += 1
        big = np.where(np.isfinite(r), np.sign(r), 1.0) * DIVERGED_RESIDUAL
        return np.where(bad, big, r)

    def _reusable(self, pt: PreparedTest, ps: np.ndarray) -> bool:
        """Whether the batch ``ps[1:]`` with row 0 simulated alone gives the numbers of the
        batch ``ps``: the batch runs at the finest step of its rows, so row 0 must need
        exactly what the others need at most (then neither side changes its step)."""
        steps = self.model.row_steps
        if len(ps) < 2 or steps is None:
            return len(ps) >= 2
        n = steps(pt, ps)
        return bool(n[0] == n[1:].max())

    def jacobian(self, u: np.ndarray) -> np.ndarray:
        """Jacobian of the residuals at ``u``: the data rows, then the prior's."""
        return np.concatenate([self._difference_jacobian(u), np.diag(self.prior_w)], axis=0)

    def _difference_jacobian(self, u: np.ndarray) -> np.ndarray:
        """Forward differences of the data residuals, all perturbations of a test simulated
        in one batch; a sensor offset's column is exact and costs no simulation (it shifts
        its channel, and the filter passes a constant unchanged).

        The unperturbed point is taken from the residual evaluation at ``u`` when
        that is bitwise what the batch would give (least_squares asks for the
        Jacobian where it has just evaluated): one simulation fewer per batch.
        """
        h = 1e-5 * np.maximum(1.0, np.abs(u))
        # step away from the nearer bound so the perturbed point stays feasible
        sgn = np.where(u + h > self.ub, -1.0, 1.0)
        # a tied level follows its partner (``p_of``): its own coordinate moves nothing
        simulated = [j for j, n in enumerate(self.free)
                     if n not in self.model.offset_channels and j not in self.ties]
        us = [u] + [u + sgn[j] * h[j] * np.eye(len(u))[j] for j in simulated]
        ps = np.stack([self.p_of(v) for v in us])
        last = self._last[1] if self._last is not None and np.array_equal(
            self._last[0], u) else None
        reuse = [last is not None and self._reusable(pt, ps) for pt in self.tests]
        if simulated:
            self.work.charge(sum(simulation_steps(pt, ps[1:] if r else ps)
                                 for pt, r in zip(self.tests, reuse, strict=True)))
        sims = twins_of_tests(self.tests, [ps[1:] if r else ps for r in reuse]) \
            if simulated else [[]] * len(self.tests)
        slope = self.dtheta_du(u)
        cols = []
        for i, pt in enumerate(self.tests):
            block = self._offset_columns(pt, slope)
            if simulated:
                if reuse[i]:
                    twins, r0 = [None, *sims[i]], last[i]
                else:
                    twins = sims[i]
                    r0 = self._res_of_twin(pt, twins[0])
                r0 = self._bounded(r0)
                for k, j in enumerate(simulated):
                    block[:, j] = (self._bounded(self._res_of_twin(pt, twins[k + 1])) - r0) \
                        / (sgn[j] * h[j])
            cols.append(block)
        self.n_eval += len(us)
        jac = np.concatenate(cols, axis=0)
        return np.where(np.isfinite(jac), jac, 0.0)

    def _offset_columns(self, pt: PreparedTest, slope: np.ndarray) -> np.ndarray:
        """Jacobian block of test ``pt``: the sensor offsets' columns filled, zeros else."""
        n = len(pt.time_s[:: self.decimate])
        chans = self.channels[pt.id]
        block = np.zeros((n * len(chans), len(self.free)))
        for j, name in enumerate(self.free):
            ch = self.model.offset_channels.get(name)
            if ch in chans:
                k = chans.index(ch)
                block[k * n:(k + 1) * n, j] = self._weights(pt, ch) * slope[j]
        return block

    def cost(self, u: np.ndarray) -> float:
        r = self.residuals(u)
        return 0.5 * float(r @ r)

    def noise_cost(self) -> float:
        """The cost that the sensor noise alone leaves at the true parameters (expected)."""
        return 0.5 * sum(self.block_sizes()) * self.noise_floor() ** 2


@dataclass
class FitResult:
    p: np.ndarray
    u: np.ndarray
    cost: float
    std_error: dict[str, float]
    correlation: np.ndarray
    at_bound: dict[str, bool]
    identifiable: dict[str, bool]
    n_residuals: int
    n_eval: int
    starts: list[float]
    # evaluations whose simulation diverged (a large finite cost the optimiser stepped back
    # from); status of the kept start (scipy's least_squares: 0 = budget spent, > 0 converged)
    n_diverged: int = 0
    status: int = 0
    # the kept start stopped at its work budget (``work.py``): status 0, no further steps
    work_spent: bool = False
    # the residual's variance (with its memory) over what white sensor noise would give
    noise_inflation: float = 1.0


STALE_STARTS = 3


def solve(
    problem: FitProblem,
    starts: list[np.ndarray],
    max_nfev: int = 60,
    more_starts: Callable[[], np.ndarray] | None = None,
    max_more: int = 0,
    good_cost: float = 0.0,
    interior: float = 1e-6,
) -> FitResult:
    """Run least_squares from each start (parameter vectors); keep the best.

    With ``more_starts``, up to ``max_more`` further starts are drawn from it
    while the best cost is still above ``good_cost``, until ``STALE_STARTS`` in a
    row find nothing clearly better (a cost the model cannot go below).
    A start on a bound is moved inside by ``interior`` of the range; with 0, only
    by least_squares' own 1e-10 (a nested model's neutral start, whose effect sits on
    its bound, must cost what the base costs).
    """
    best = None
    costs = []
    if problem.reference_steps is None:
        problem.reference_steps = problem.steps(problem.base[None])

    def run(p0: np.ndarray):
        u0 = problem.u_of(p0)
        # keep strictly inside the bounds (trf needs interior starts)
        span = problem.ub - problem.lb
        u0 = np.clip(u0, problem.lb + interior * span, problem.ub - interior * span)
        res = _least_squares_within_budget(problem, u0, max_nfev)
        costs.append(float(res.cost))
        return res

    for p0 in starts:
        res = run(p0)
        if best is None or res.cost < best.cost:
            best = res
    stale = 0  # further starts in a row that found no clearly better basin
    while more_starts is not None and len(costs) < len(starts) + max_more and (
            best.cost > good_cost) and stale < STALE_STARTS:
        res = run(more_starts())
        stale = 0 if res.cost < 0.9 * best.cost else stale + 1
        if res.cost < best.cost:
            best = res
    return _summarise(problem, best, costs)


def precision_at(problem: FitProblem, p: np.ndarray) -> FitResult:
    """Standard errors and correlations of ``problem``'s free parameters at ``p`` itself,
    as a fit ending there would report them (the same sandwich), without a step taken."""
    u = problem.u_of(p)
    r = problem.residuals(u)
    end = SimpleNamespace(x=u, cost=0.5 * float(r @ r), fun=r, jac=problem.jacobian(u),
                          status=0, work_spent=False)
    return _summarise(problem, end, [end.cost])


def _least_squares_within_budget(problem: FitProblem, u0: np.ndarray, max_nfev: int):
    """scipy's least_squares from ``u0``; where its simulations spend the problem's work
    budget first (``work.py``), its best evaluated point, as least_squares would report a
    spent evaluation budget (status 0)."""
    problem.work.start(problem.budget(max_nfev))
    try:
        return least_squares(problem.residuals, u0, jac=problem.jacobian,
                             bounds=(problem.lb, problem.ub), method="trf", x_scale="jac",
                             max_nfev=max_nfev, ftol=1e-8, xtol=1e-8, gtol=1e-8)
    except WorkSpent:
        meter = problem.work
        log.info("a fit stopped at its work budget (%.3g steps, %.1f× one evaluation at "
                 "its base): kept its best point", meter.spent,
                 meter.spent / max(problem.reference_steps or 1.0, 1.0))
        searched, meter.limit = meter.spent, float("inf")
        jac = problem.jacobian(meter.best_u)  # for the standard errors, not the search
        meter.spent = searched
        return SimpleNamespace(x=meter.best_u, cost=meter.best_cost, fun=meter.best_r,
                               jac=jac, status=0, work_spent=True)
    finally:
        problem.work.limit = float("inf")  # evaluations outside a run are not budgeted


# a parameter whose standard error exceeds this share of its value is reported as not
# identifiable from the tests given
IDENTIFIABLE_REL_STD = 0.1


# a parameter within this share of its range (in the optimiser's coordinates: decades for
# a log-scaled one) of a bound ended on it
AT_BOUND_SHARE = 1e-4


def on_bound(u: np.ndarray, lb: np.ndarray, ub: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Which of ``u`` lie on their lower and which on their upper bound (``AT_BOUND_SHARE``)."""
    span = ub - lb
    return u - lb < AT_BOUND_SHARE * span, ub - u < AT_BOUND_SHARE * span


def bound_side(value: float, lower: float, upper: float, log_scale: bool) -> str | None:
    """``lower``, ``upper`` or ``None``: one value by ``on_bound``'s rule, in decades for a
    parameter searched in them."""
    if log_scale and lower > 0:
        value, lower, upper = (np.log(max(x, 1e-300)) for x in (value, lower, upper))
    at_lower, at_upper = on_bound(np.array([value]), np.array([lower]), np.array([upper]))
    return "lower" if at_lower[0] else "upper" if at_upper[0] else None


def residual_memory(r: np.ndarray, max_lag: int | None = None) -> int:
    """Lags over which a residual block stays correlated (first autocorrelation below 0.05).

    Filtered channels, a smoothed input and any unmodelled dynamics make
    neighbouring residuals alike; treating them as independent samples makes
    standard errors look several times smaller than they are.
    """
    r = np.asarray(r, float) - np.mean(r)
    n = len(r)
    if n < 8 or not np.any(r):
        return 0
    max_lag = min(max_lag or n // 4, n // 4)
    spec = np.fft.rfft(r, 2 * n)
    acf = np.fft.irfft(spec * np.conj(spec))[: max_lag + 1]
    acf = acf / acf[0]
    below = np.nonzero(acf < 0.05)[0]
    return int(below[0]) if below.size else max_lag


def hac_meat(jac: np.ndarray, r: np.ndarray, blocks: list[int], n_params: int) -> np.ndarray:
    """Newey–West (Bartlett) estimate of cov(Jᵀr), block by block.

    With white residuals this is s²·JᵀJ and the covariance reduces to the
    classical s²·(JᵀJ)⁻¹; with correlated ones it widens it by as much as the
    residual memory of each (test, channel) block says.
    """
    meat = np.zeros((jac.shape[1], jac.shape[1]))
    dof = max(len(r) - n_params, 1) / max(len(r), 1)
    start = 0
    for size in blocks:
        g = jac[start:start + size] * r[start:start + size, None]
        lags = residual_memory(r[start:start + size])
        meat += g.T @ g
        for lag in range(1, lags + 1):
            c = g[lag:].T @ g[:-lag]
            meat += (1.0 - lag / (lags + 1)) * (c + c.T)
        start += size
    return meat / dof


def _summarise(problem: FitProblem, res, costs: list[float]) -> FitResult:
    u = res.x
    jac = res.jac[: -len(u)]  # data rows only: the prior must not make a parameter look identified
    m, n = jac.shape
    # pseudo-inverse: a rank-deficient Jacobian is the non-identifiable case, not an error
    uu, sv, vt = np.linalg.svd(jac, full_matrices=False)
    tol = sv.max() * 1e-9 if sv.size else 0.0
    inv = np.zeros_like(sv)
    inv[sv > tol] = 1.0 / sv[sv > tol] ** 2
    bread = (vt.T * inv) @ vt
    meat = hac_meat(jac, res.fun[:m], problem.block_sizes(), n)
    floor2 = problem.noise_floor() ** 2
    inflation = float(np.trace(meat) / max(floor2 * np.trace(jac.T @ jac), 1e-300))
    if problem.stated.any():
        # a stated prior is one more measurement of its parameter, with the variance per
        # unit of its weighted residual that it was weighted for
        info_prior = np.diag((problem.prior_w * problem.stated) ** 2)
        bread = np.linalg.pinv(jac.T @ jac + info_prior, hermitian=True)
        meat = meat + problem.prior_inflation * floor2 * info_prior
    cov_u = bread @ meat @ bread
    std_u = np.sqrt(np.maximum(np.diag(cov_u), 0.0))
    d = problem.dtheta_du(u)
    theta = problem.p_of(u)[problem.idx]
    std_theta = std_u * d
    for j, (k, ratio, _, _) in problem.ties.items():
        std_theta[j] = std_theta[k] * ratio  # it moves with its partner, by assumption
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = cov_u / np.outer(std_u, std_u)
    corr = np.where(np.isfinite(corr), corr, 0.0)
    # a direction the data do not constrain has a (near) zero singular value
    weak = np.zeros(n, bool)
    for k, s in enumerate(sv):
        if s <= tol or s < 1e-6 * sv.max():
            weak |= np.abs(vt[k]) > 0.3
    weak &= ~problem.stated  # its stated prior holds it
    weak[list(problem.ties)] = True  # the split is assumed, not measured
    at_lower, at_upper = on_bound(u, problem.lb, problem.ub)
    at_bound = at_lower | at_upper
    rel = np.where(np.abs(theta) > 0, std_theta / np.maximum(np.abs(theta), 1e-300), np.inf)
    identifiable = ~weak & (rel < IDENTIFIABLE_REL_STD)
    names = problem.free
    return FitResult(
        p=problem.p_of(u),
        u=u,
        cost=float(res.cost),
        std_error={nm: float(v) for nm, v in zip(names, std_theta, strict=True)},
        correlation=corr,
        at_bound={nm: bool(v) for nm, v in zip(names, at_bound, strict=True)},
        identifiable={nm: bool(v) for nm, v in zip(names, identifiable, strict=True)},
        n_residuals=m,
        n_eval=problem.n_eval,
        starts=costs,
        n_diverged=problem.n_diverged,
        status=int(res.status),
        work_spent=bool(getattr(res, "work_spent", False)),
        noise_inflation=inflation,
    )
