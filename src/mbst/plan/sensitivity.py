"""Sensitivity of every candidate measurement to every unknown parameter.

For each cell (scenario × input) the simulator runs, in one numba batch,
every parameter vector the analysis needs:

- K sweep points over the ranges (the centre plus a Latin hypercube in
  ln θ, seeded), each with central differences in ln θ of every unknown
  (local sensitivity dy/dln θ, so all parameters are compared per relative
  change);
- each unknown at the low and high end of its range with the others at the
  centre (seed 000's "swept across a reasonable range ... whether they could
  capture a response change": the global response swing);
- each catalogue effect at its realistic size at the centre (for ``effects``).

Everything downstream (Fisher information, selection, effect separation)
needs only the Gram matrices of these signals, so the raw time series are
reduced per cell and dropped.
"""

from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numba
import numpy as np
import pandas as pd
from tqdm import tqdm

from mbst.plan.config import PlanConfig
from mbst.plan.inputs import profile, test_input
from mbst.plan.sensors import INPUT_SENSOR, sensor_signals
from mbst.systems.eps import kernel as K
from mbst.systems.eps import model as eps_model
from mbst.systems.eps import simulate as eps
from mbst.systems.eps.params import EFFECT_CATALOGUE, PARAM_INDEX, EffectSpec


@dataclass(frozen=True)
class Cell:
    """One candidate test: a scenario candidate with an input candidate."""

    scenario_id: str
    input_id: str
    scenario: str
    motor: str
    input: dict  # absolute input entry (campaign.yaml)

    @property
    def label(self) -> str:
        return f"{self.scenario_id}/{self.input_id}"


@dataclass
class Sensitivity:
    """Reduced results of the analysis over the candidate grid.

    Arrays are indexed [k sweep point, c cell, s sensor, p unknown]; signals
    are divided by the effective noise rms ``sigma`` (sensor noise combined
    with ``model_error_fraction`` of the channel's swing in that test), so
    sums over samples are Fisher information at the analysis rate.
    """

    unknowns: list[str]
    sensors: list[str]
    cells: list[Cell]
    points: np.ndarray  # (K, P) parameter values of the sweep points
    gram: np.ndarray  # (K, C, S, P, P) Σ J Jᵀ
    colsum: np.ndarray  # (K, C, S, P) Σ J (for the campaign-wide offset)
    n_samples: np.ndarray  # (C,)
    rms: np.ndarray  # (K, C, S, P) rms of dy/dln θ per sample, noise units
    swing: np.ndarray  # (C, S, P) rms of y(high) − y(low), noise units
    effects: list[str]  # catalogue keys
    effect_gram: np.ndarray  # (C, S, P+E, P+E) per-test centred Gram of [J(centre), d_effect]
    sigma: np.ndarray  # (C, S) noise used: sensor noise ⊕ model-error share of the swing
    # (K, C, S, M, P) Σₙ J·e over the samples of a test, e the output error of the twin that
    # the identification drives with the smoothed noisy angle (M draws, noise units)
    input_error: np.ndarray | None = None
    nominal: dict[str, dict[str, np.ndarray]] = field(repr=False, default_factory=dict)
    n_simulations: int = 0
    wall_s: float = 0.0

    def cell_index(self, scenario_id: str, input_id: str) -> int:
        for c, cell in enumerate(self.cells):
            if cell.scenario_id == scenario_id and cell.input_id == input_id:
                return c
        raise KeyError(f"{scenario_id}/{input_id}")


def candidate_cells(cfg: PlanConfig) -> list[Cell]:
    """Every scenario × input pair, in config order."""
    cells = []
    for sc in cfg.scenarios:
        for inp in cfg.inputs:
            spec = test_input(inp.kind, sc.amplitude_deg * inp.amplitude_scale, inp.options)
            cells.append(Cell(sc.id, inp.id, sc.scenario, sc.motor, spec))
    return cells


def sweep_points(cfg: PlanConfig) -> np.ndarray:
    """(K, P) values: the centre, then a Latin hypercube in ln θ (deterministic in the seed)."""
    lo = np.log([u.low for u in cfg.unknowns])
    hi = np.log([u.high for u in cfg.unknowns])
    k = cfg.sweep_points
    pts = [np.array([u.nominal for u in cfg.unknowns])]
    if k > 1:
        rng = np.random.default_rng([cfg.seed, 6])
        m = k - 1
        u = np.stack([(rng.permutation(m) + rng.random(m)) / m for _ in cfg.unknowns], axis=1)
        pts += list(np.exp(lo + u * (hi - lo)))
    return np.stack(pts)


def _effect_vector(base: np.ndarray, spec: EffectSpec) -> np.ndarray:
    q = base.copy()
    for name, v in spec.default_size.items():
        q[PARAM_INDEX[name]] = v
    return q


def _run(cell: Cell, ang: np.ndarray, om: np.ndarray, dt: float, ps: np.ndarray,
         n_sub: int) -> np.ndarray:
    return eps.simulate_raw_batch(cell.scenario, cell.motor, ang, om, ps, dt, n_sub)


def _run_one(cell: Cell, ang: np.ndarray, om: np.ndarray, dt: float, p: np.ndarray,
             n_sub: int) -> np.ndarray:
    scen, mode = K.SCENARIO_CODES[cell.scenario], K.MOTOR_CODES[cell.motor]
    x0 = eps.initial_state(p, cell.scenario, float(ang[0]))
    return K.simulate_dt(ang, om, p, scen, mode, n_sub, x0, dt)


def _signals(cell: Cell, raw: np.ndarray, ps: np.ndarray, ang: np.ndarray,
             sensors: list[str], noise: np.ndarray) -> np.ndarray:
    """(runs, S, N) noise-normalised sensor signals."""
    out = np.empty((len(ps), len(sensors), raw.shape[1]))
    for r in range(len(ps)):
        sig = sensor_signals(raw[r], ps[r], cell.scenario, ang)
        for s, name in enumerate(sensors):
            out[r, s] = sig[name] / noise[s]
    return out


def _input_error(cfg: PlanConfig, cell: Cell, p: np.ndarray, n_sub: int, n: int,
                 angle_noise: float, sensors: list[str], sig_eff: np.ndarray,
                 rng: np.random.Generator) -> np.ndarray:
    """(M, S, N) noise-normalised signals of the twin driven as the identification drives it.

    The rig's angle is logged at the campaign rate with the angle sensor's noise,
    then smoothed by the model's own input preparation (window, rate, standstill)
    and the column switch widened by the rate noise left (``eps_model``), exactly
    as ``mbst identify`` builds its twin; the result is taken at the analysis rate.
    """
    t_f, ang_f = profile(cell.input, cfg.sample_rate_hz)
    dt_f = float(t_f[1] - t_f[0])
    step = max(int(round(cfg.sample_rate_hz / cfg.analysis_rate_hz)), 1)
    dt = dt_f * step
    out = np.empty((cfg.input_draws, len(sensors), n))
    for m in range(cfg.input_draws):
        noisy = ang_f + angle_noise * rng.standard_normal(len(ang_f))
        ang, rate, extra = eps_model.prepare_inputs(pd.DataFrame({INPUT_SENSOR: noisy}), dt_f,
                                                    None)
        ang, rate = _fit_length(ang[::step], n), _fit_length(rate[::step], n)
        q = eps_model.twin_params(p, float(extra["rate_noise_rad_per_s"]))
        raw = _run_one(cell, ang, rate, dt, q, n_sub)
        out[m] = _signals(cell, raw[None], q[None], ang, sensors, sig_eff)[0]
    return out


def _fit_length(x: np.ndarray, n: int) -> np.ndarray:
    return x[:n] if len(x) >= n else np.concatenate([x, np.full(n - len(x), x[-1])])


def effect_list(cfg: PlanConfig) -> list[EffectSpec]:
    if not cfg.effects_enabled:
        return []
    if cfg.effects_list is None:
        return list(EFFECT_CATALOGUE)
    return [e for e in EFFECT_CATALOGUE if e.key in cfg.effects_list]


def analyse(cfg: PlanConfig, progress: bool = False) -> Sensitivity:
    """Simulate the candidate grid and reduce it to sensitivities and Gram matrices.

    Parameters
    ----------
    cfg
        The validated planning config.
    progress
        Show a tqdm bar over the cells.

    Returns
    -------
    Sensitivity
    """
    t0 = time.perf_counter()
    cells = candidate_cells(cfg)
    sensors = [s.name for s in cfg.sensors]
    noise = np.array([s.noise for s in cfg.sensors])
    points = sweep_points(cfg)
    vecs = _run_vectors(cfg, points)
    effects = effect_list(cfg)
    eff_vecs = [_effect_vector(vecs[0], e) for e in effects]
    acc = _Reduction.empty(len(points), len(cells), len(sensors), len(cfg.unknowns),
                           len(effects), cfg.input_draws)
    angle_noise = float(noise[sensors.index(INPUT_SENSOR)])
    ones = np.ones(len(sensors))
    n_sims = 0
    pool = ThreadPoolExecutor(max_workers=max(1, numba.get_num_threads()))
    for c, cell in enumerate(tqdm(cells, desc="plan: sensitivity", unit="cell",
                                  disable=not progress)):
        t, ang = profile(cell.input, cfg.analysis_rate_hz)
        dt = float(t[1] - t[0])
        om = np.gradient(ang, dt)
        acc.n_samples[c] = len(t)
        # one step size for every base-model run of the cell: a finite difference
        # between runs with different sub-steps would measure the integrator
        n_sub = max(eps.substeps(q, cell.scenario, dt) for q in vecs)
        y = _signals(cell, _run(cell, ang, om, dt, vecs, n_sub), vecs, ang, sensors, ones)
        n_sims += len(vecs)
        acc.nominal[cell.label] = {"time_s": t, "steering_angle_rad": ang,
                                   **{s: y[0, i] for i, s in enumerate(sensors)}}
        # the model is never exactly right: a share of each channel's own swing in this
        # test counts as noise too, so no plan leans on a signal far below the model error
        swing_rms = y[0].std(axis=1)
        sig_eff = np.sqrt(noise**2 + (cfg.model_error_fraction * swing_rms) ** 2)
        sig_eff[sensors.index(INPUT_SENSOR)] = noise[sensors.index(INPUT_SENSOR)]
        acc.sigma[c] = sig_eff
        y /= sig_eff[None, :, None]
        err = (_input_error(cfg, cell, vecs[0], n_sub, len(t), angle_noise, sensors, sig_eff,
                            np.random.default_rng([cfg.seed, 11, c])) - y[0][None]
               if cfg.input_draws else None)
        n_sims += cfg.input_draws
        j0 = acc.add_sweep(c, y, err, cfg.fd_step)
        if effects:
            runs = _effect_runs(cell, ang, om, dt, vecs[0], eff_vecs, pool)
            n_sims += len(runs.raws)
            acc.effect_gram[c] = _effect_gram(cell, runs, vecs[0], eff_vecs, j0, ang,
                                              sensors, sig_eff)
    pool.shutdown()
    return Sensitivity(
        unknowns=list(cfg.unknown_names), sensors=sensors, cells=cells, points=points,
        gram=acc.gram, colsum=acc.colsum, n_samples=acc.n_samples, rms=acc.rms,
        swing=acc.swing, effects=[e.key for e in effects], effect_gram=acc.effect_gram,
        sigma=acc.sigma, nominal=acc.nominal, n_simulations=n_sims,
        wall_s=time.perf_counter() - t0,
        input_error=acc.input_error if cfg.input_draws else None,
    )


def _run_vectors(cfg: PlanConfig, points: np.ndarray) -> np.ndarray:
    """The parameter vectors of one cell (identical for every cell): per sweep point the
    centre and its ± steps in ln θ, then each unknown at the low and high end of its range."""
    idx = np.array([PARAM_INDEX[n] for n in cfg.unknown_names])
    base = cfg.nominal_vector()
    d = cfg.fd_step
    vecs = []
    for point in points:
        centre = base.copy()
        centre[idx] = point
        vecs.append(centre)
        for j in range(len(idx)):
            for sgn in (1.0, -1.0):
                q = centre.copy()
                q[idx[j]] *= np.exp(sgn * d)
                vecs.append(q)
    for j, u in enumerate(cfg.unknowns):
        for bound in (u.low, u.high):
            q = vecs[0].copy()
            q[idx[j]] = bound
            vecs.append(q)
    return np.stack(vecs)


@dataclass
class _Reduction:
    """The grid's signals reduced cell by cell (the fields of ``Sensitivity``)."""

    gram: np.ndarray
    colsum: np.ndarray
    rms: np.ndarray
    swing: np.ndarray
    n_samples: np.ndarray
    effect_gram: np.ndarray
    sigma: np.ndarray
    input_error: np.ndarray
    nominal: dict[str, dict[str, np.ndarray]]

    @classmethod
    def empty(cls, kk: int, cc: int, ss: int, pp: int, ee: int, draws: int) -> _Reduction:
        return cls(gram=np.zeros((kk, cc, ss, pp, pp)), colsum=np.zeros((kk, cc, ss, pp)),
                   rms=np.zeros((kk, cc, ss, pp)), swing=np.zeros((cc, ss, pp)),
                   n_samples=np.zeros(cc, dtype=int),
                   effect_gram=np.zeros((cc, ss, pp + ee, pp + ee)), sigma=np.zeros((cc, ss)),
                   input_error=np.zeros((kk, cc, ss, draws, pp)), nominal={})

    def add_sweep(self, c: int, y: np.ndarray, err: np.ndarray | None, d: float
                  ) -> np.ndarray:
        """Cell ``c``'s sweep runs ``y`` (noise units, in ``_run_vectors``' order) reduced;
        returns the centre's Jacobian (S, N, P)."""
        kk, pp = self.gram.shape[0], self.gram.shape[-1]
        j0 = None
        for k in range(kk):
            b = k * (2 * pp + 1)
            plus, minus = y[b + 1: b + 1 + 2 * pp: 2], y[b + 2: b + 2 + 2 * pp: 2]
            jac = (plus - minus) / (2.0 * d)  # (P, S, N)
            jac = np.transpose(jac, (1, 2, 0))  # (S, N, P)
            self.gram[k, c] = np.einsum("snp,snq->spq", jac, jac)
            self.colsum[k, c] = jac.sum(axis=1)
            self.rms[k, c] = np.sqrt(np.mean(jac**2, axis=1))
            if err is not None:
                self.input_error[k, c] = np.einsum("snp,msn->smp", jac, err)
            if k == 0:
                j0 = jac
        n_sweep = kk * (2 * pp + 1)
        sw = y[n_sweep + 1:: 2] - y[n_sweep:: 2]  # (P, S, N): high − low
        self.swing[c] = np.sqrt(np.mean(sw**2, axis=2)).T
        return j0


@dataclass
class _EffectRuns:
    """A cell's runs for the effect signatures: the centre at each effect's step size."""

    subs: list[int]  # sub-steps of each effect's run
    raws: list[np.ndarray]  # the centre at each distinct step size, then each effect


def _effect_runs(cell: Cell, ang: np.ndarray, om: np.ndarray, dt: float, centre: np.ndarray,
                 eff_vecs: list[np.ndarray], pool: ThreadPoolExecutor) -> _EffectRuns:
    # single runs of different step sizes go to a thread pool (the kernel releases the
    # GIL), so both cores stay busy
    subs = [eps.substeps(q, cell.scenario, dt) for q in eff_vecs]
    runs = [(centre, ns) for ns in sorted(set(subs))] + list(zip(eff_vecs, subs))
    return _EffectRuns(subs, list(pool.map(lambda job: _run_one(cell, ang, om, dt, *job),
                                           runs)))


def _effect_gram(cell: Cell, runs: _EffectRuns, centre: np.ndarray,
                 eff_vecs: list[np.ndarray], j0: np.ndarray, ang: np.ndarray,
                 sensors: list[str], sig_eff: np.ndarray) -> np.ndarray:
    """(S, P+E, P+E) per-test centred Gram of [J(centre), effect signatures]: each effect
    against the centre run at the effect's own step size."""
    steps = sorted(set(runs.subs))
    at_step = {ns: _signals(cell, runs.raws[i][None], centre[None], ang, sensors, sig_eff)[0]
               for i, ns in enumerate(steps)}
    sig = np.zeros((len(sensors), len(ang), len(eff_vecs)))
    for e, q in enumerate(eff_vecs):
        ye = _signals(cell, runs.raws[len(steps) + e][None], q[None], ang, sensors, sig_eff)
        sig[:, :, e] = ye[0] - at_step[runs.subs[e]]
    v = np.concatenate([j0, sig], axis=2)  # (S, N, P+E)
    v = v - v.mean(axis=1, keepdims=True)  # per-test sensor offset removed
    return np.einsum("sna,snb->sab", v, v)
