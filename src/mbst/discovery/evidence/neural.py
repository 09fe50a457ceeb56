"""Physics + neural residual: a small neural ODE that learns what the base model lacks.

The base EPS simulation is a compiled numba kernel that torch cannot
differentiate, and the project keeps exactly one copy of the model equations,
so the physics is *not* re-implemented here. The base model's twin is taken as
given (``TestResidual.simulated``) and a small latent ODE adds a correction
with memory::

    dz/dt = (f_θ(z, s(t)) + L·[z, s(t)] − λ⊙z) / T_s,   z(0) = 0
    ŷ(t)  = y_base(t) + κ·(C·z(t) + g_θ(s(t)))

``s(t)`` are normalised features: the base model's own internal signals
(``TestResidual.states``), the measured input (angle, rate) and a one-hot of
the scenario. ``f_θ`` (2×16 tanh) and ``g_θ`` (1×16 tanh) are small MLPs, ``L`` a
linear path next to ``f_θ`` (linear filtering of the base signals is learnt in
far fewer steps than through tanh units), ``λ`` a learned positive leak that
keeps the latent state forgetful, ``T_s`` a fixed time scale that brings the
~14 Hz mesh ringing of the rig to O(1) rates for the network, ``κ`` a gain per
(scenario, channel) calibrated after training (see ``_calibrate``).

One model serves all scenarios: the scenarios share the components, and the
one-hot lets it switch a term off where a cut-out removes it (blocked column)
without splitting the few tests into even fewer per-scenario sets.

Training reads only tests with role ``identification``. The target is the
residual measured − simulated of every channel a test has, each channel divided
by its residual RMS so torque, rack position and tie-rod forces weigh alike.
The channels are already filtered alike (τ = 5 ms), so the correction learns the
filtered residual directly and is not filtered again. To fit a CPU budget
(≤ 60 s on 2 cores) training runs on short random windows on a 250 Hz grid,
``z(0) = 0`` with an unscored wash-out at the start of each window, a
fixed-step ``rk4`` from ``torchdiffeq`` (one step per two grid samples), a
fixed number of Adam steps, and window starts drawn half uniformly, half by
residual energy (the gap lives at a few reversals).

``explain`` reads the trained model back into the language of the effect
catalogue: how strongly the learned correction depends on each base-model
signal, and a sparse regression (pysindy STLSQ) of the correction on the family's
candidate library (``core.candidates``; the one the sparse regression uses), each
term tagged with a catalogue key.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np
import torch
from torch import nn
from torchdiffeq import odeint

from mbst.core.candidates import Candidate, LibraryFactory
from mbst.core.filtering import exponential_filter
from mbst.discovery.data import TestResidual

# Latent dynamics time scale: a 14 Hz ringing has rate 88 1/s, i.e. ~1.8 in these units.
TIME_SCALE_S = 0.02
# The neural ODE runs at about this rate; the filtered channels carry nothing above ~30 Hz.
TARGET_RATE_HZ = 250.0
# Fraction of every training window integrated but not scored (z(0) = 0 is wrong there).
WASHOUT_FRACTION = 0.25
# Share of the window-sampling probability that follows the residual energy (rest: uniform).
ENERGY_MIX = 0.5
# explain(): library terms correlated above this are treated as one (aliases).
ALIAS_CORRELATION = 0.95
# explain(): rows of the sparse regression are taken at about this rate (after the low-pass).
REGRESSION_RATE_HZ = 100.0
# explain(): low-pass time constant applied to the correction and the library alike.
SMOOTH_S = 0.03

# Base-model signals used as features, in a fixed order (missing ones are left out).
FEATURE_SIGNALS = (
    "angle_rad",
    "omega_rad_per_s",
    "torsion_bar_torque_nm",
    "worm_gear_mesh_angle_rad",
    "pinion_angle_rad",
    "rack_position_m",
    "rack_speed_m_per_s",
    "motor_speed_rad_per_s",
    "motor_torque_nm",
    "wheel_position_m",
    "tie_rod_force_total_n",
    "column_friction_nm",
)


def _signals(test: TestResidual) -> dict[str, np.ndarray]:
    """Input and base-model internal signals of a test, by name."""
    out = {"angle_rad": test.angle_rad, "omega_rad_per_s": test.omega_rad_per_s}
    out.update({k: v for k, v in test.states.items() if k not in out})
    return {k: np.asarray(v, dtype=np.float64) for k, v in out.items()}


@contextmanager
def _one_thread():
    """Run torch on one intra-op thread, restoring the caller's setting afterwards.

    The tensors here are tiny: extra threads only add wake-up latency (measured on the
    2-core box: 2 ms instead of 2.5 µs per tanh when the other core is busy), and one
    thread also keeps the arithmetic order, hence the result, fixed.
    """
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(threads)


def _grid(test: TestResidual) -> np.ndarray:
    """The uniform ODE grid (step 1/TARGET_RATE_HZ) over a test's time span."""
    h = 1.0 / TARGET_RATE_HZ
    n = int(np.floor((test.time_s[-1] - test.time_s[0]) / h + 1e-9)) + 1
    return test.time_s[0] + h * np.arange(n)


def _resample(time_s: np.ndarray, grid: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Columns of ``x`` (samples, …) linearly interpolated from ``time_s`` onto ``grid``."""
    x2 = x.reshape(len(time_s), -1)
    out = np.stack([np.interp(grid, time_s, x2[:, j]) for j in range(x2.shape[1])], axis=1)
    return out.reshape((len(grid),) + x.shape[1:])


class _LatentODE(nn.Module):
    """dz/dt = (f_θ([z, s(t)]) + L·[z, s(t)] − λ⊙z)/T_s, s(t) interpolated on a uniform grid.

    f_θ is a 2-layer tanh MLP, L a linear path next to it (linear filtering of the base
    signals is learnt fast), λ = softplus(ρ) a positive leak.
    """

    def __init__(self, n_features: int, n_channels: int, latent: int, hidden: int) -> None:
        super().__init__()
        self.latent = latent
        self.hidden = hidden
        self.f = nn.Sequential(
            nn.Linear(latent + n_features, hidden), nn.Tanh(),
            nn.Linear(hidden, hidden), nn.Tanh(),
            nn.Linear(hidden, latent),
        )
        self.linear = nn.Linear(latent + n_features, latent, bias=False)
        # softplus(0) ≈ 0.69: a decay time of ~0.03 s at T_s = 0.02 s before training
        self.leak = nn.Parameter(torch.zeros(latent))
        self.readout = nn.Linear(latent, n_channels, bias=False)
        self.direct = nn.Sequential(nn.Linear(n_features, hidden), nn.Tanh(),
                                    nn.Linear(hidden, n_channels))
        # start at the base model: the direct term is zero until data says otherwise
        nn.init.zeros_(self.direct[2].weight)
        nn.init.zeros_(self.direct[2].bias)
        # a small random readout, so that f_θ receives gradient from the first step
        nn.init.normal_(self.readout.weight, std=0.1)
        self._p = torch.zeros(1, 2, hidden + latent)
        self._dp = torch.zeros(1, 1, hidden + latent)
        self._wz = torch.zeros(latent, hidden + latent)
        self._layers: tuple[torch.Tensor, ...] = ()
        self._h = 1.0

    def set_input(self, s: torch.Tensor, h: float) -> None:
        """Features (batch, samples, features) on the grid t_k = k·h."""
        n = self.latent
        w1, b1 = self.f[0].weight, self.f[0].bias
        w_l = self.linear.weight
        # The feature half of the first layer and of the linear path is linear in s, so it
        # is applied to the whole grid once; interpolating the product is exact and saves
        # the per-call concatenation and most of the first matmul.
        w_s = torch.cat([w1[:, n:], w_l[:, n:]], dim=0)
        bias = torch.cat([b1, torch.zeros(n, dtype=b1.dtype)])
        self._p = s @ w_s.T + bias
        self._dp = torch.diff(self._p, dim=1)
        # z-half of both, and the leak folded in (it is a parameter: evaluated once)
        self._wz = torch.cat([w1[:, :n], w_l[:, :n] - torch.diag(nn.functional.softplus(
            self.leak))], dim=0).T
        # transposed once per trajectory, so every call is a plain addmm
        self._layers = (self.f[2].weight.T, self.f[2].bias, self.f[4].weight.T, self.f[4].bias)
        self._h = h

    def forward(self, t: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        # torchdiffeq's fixed-step rk4 (3/8 rule) also samples at t + h/3 and t + 2h/3:
        # linear interpolation between grid samples, clamped at the ends.
        u = float(t) / self._h
        i = min(max(math.floor(u), 0), self._dp.shape[1] - 1)
        w = min(max(u - i, 0.0), 1.0)
        p = self._p[:, i] + w * self._dp[:, i] if w > 0.0 else self._p[:, i]
        q = torch.addmm(p, z, self._wz)
        w2, b2, w3, b3 = self._layers
        a = torch.tanh(q[:, :self.hidden])
        a = torch.tanh(torch.addmm(b2, a, w2))
        return torch.addmm(q[:, self.hidden:], a, w3).add_(b3).mul_(1.0 / TIME_SCALE_S)

    def outputs(self, s: torch.Tensor, h: float, z0: torch.Tensor, substeps: float = 1.0
                ) -> torch.Tensor:
        """Correction (batch, samples, channels) in normalised units.

        ``substeps`` rk4 steps per sample (0.5: one step every two samples).
        """
        self.set_input(s, h)
        t = torch.arange(s.shape[1], dtype=s.dtype) * h
        z = odeint(self, z0, t, method="rk4",
                   options={"step_size": h / substeps})  # (samples, batch, latent)
        return self.readout(z.transpose(0, 1)) + self.direct(s)


def _window_starts(series: list[tuple[np.ndarray, np.ndarray, np.ndarray]], n_win: int,
                   n_wash: int) -> tuple[list[tuple[int, int]], np.ndarray]:
    """Every (test, sample) a training window can start at, and its drawing probability.

    Half of the probability is uniform over time, half proportional to the residual
    energy in the scored part of the window, so that the few reversals where the gap
    lives are seen often enough in a short training.
    """
    starts, score = [], []
    for i, (_, y, m) in enumerate(series):
        n_start = len(y) - n_win
        if n_start <= 0:
            continue
        e = np.concatenate([[0.0], np.cumsum(np.sum(m * y**2, axis=1))])
        a = np.arange(n_start)
        starts += [(i, int(k)) for k in a]
        score.append(e[a + n_win] - e[a + n_wash])
    if not starts:
        raise ValueError("every identification test is shorter than one training window")
    score = np.concatenate(score)
    prob = (1.0 - ENERGY_MIX) / len(score) + ENERGY_MIX * score / max(score.sum(), 1e-300)
    prob /= prob.sum()
    return starts, prob


@dataclass
class _TrainingWindows:
    """The training tests on the ODE grid and how windows are drawn from them.

    ``series`` holds per test the normalised features, the residual target (each channel
    divided by its residual RMS) and a mask of the channels the test has, (samples, …).
    """

    series: list[tuple[np.ndarray, np.ndarray, np.ndarray]]
    starts: list[tuple[int, int]]  # (test index, first sample) of every possible window
    prob: np.ndarray  # drawing probability of each start
    n_win: int  # samples per window, wash-out included
    n_wash: int  # leading samples integrated but not scored

    def draw(self, rng: np.random.Generator,
             batch: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """A random batch: features (whole windows), target and mask (scored part only)."""
        s_b, y_b, m_b = [], [], []
        for k in rng.choice(len(self.starts), size=batch, p=self.prob):
            i, a = self.starts[k]
            s, y, m = self.series[i]
            s_b.append(s[a:a + self.n_win])
            y_b.append(y[a:a + self.n_win])
            m_b.append(m[a:a + self.n_win])
        s_t = torch.tensor(np.stack(s_b), dtype=torch.float32)
        y_t = torch.tensor(np.stack(y_b)[:, self.n_wash:], dtype=torch.float32)
        m_t = torch.tensor(np.stack(m_b)[:, self.n_wash:], dtype=torch.float32)
        return s_t, y_t, m_t


class NeuralResidual:
    """Base physics twin plus a latent neural ODE correction, trained on identification tests.

    Parameters
    ----------
    latent : int
        Number of latent states z (2 is the minimum for a ringing).
    hidden : int
        Width of the two hidden tanh layers of f_θ (and of the one of g_θ).
    window_s : float
        Length of one training window, wash-out included.
    iterations : int
        Number of Adam steps (fixed, so the training time is predictable).
    seed : int
        Seed of the initial weights and of the window sampling; the same seed
        on the same data gives the same weights.
    batch : int
        Windows per Adam step (the cost of a step hardly depends on it: per-call overhead
        dominates at this size).
    learning_rate : float
        Initial Adam step size, cosine-annealed to a tenth of it over ``iterations``.
    substeps : float
        rk4 steps per 4 ms grid sample (0.5: one 8 ms step per two samples, ample for the
        ~14 Hz ringing, half the cost of one per sample).
    signals : sequence of str
        Input and base-model signals used as features, those a test has (default: the
        EPS rig's ``FEATURE_SIGNALS``; another family passes its own internal signals).

    Attributes
    ----------
    channels : list[str]
        Output channels (union of the channels of the training tests).
    features : list[str]
        Feature names (signals, then ``scenario=<name>`` one-hots).
    trained_on : list[str]
        Ids of the tests training read (the identification tests).
    gains : dict[str, float]
        Calibrated gain κ in [0, 1] per ``"<scenario>/<channel>"``.
    train_seconds : float
        Wall time of ``fit``.
    loss_history : list[float]
        Training loss per step: mean square of the normalised residual minus the
        correction over the scored part of the windows (1.0 = the base model's residual
        power, as the channels are scaled by their residual RMS).

    Notes
    -----
    Measured on the seed-1 demo campaign (10 tests, 500 Hz) with the defaults: about
    30 s of training on 2 busy CPU cores.
    """

    def __init__(self, latent: int = 3, hidden: int = 16, window_s: float = 0.5,
                 iterations: int = 200, seed: int = 0, batch: int = 32,
                 learning_rate: float = 3e-2, substeps: float = 0.5,
                 signals: Sequence[str] = FEATURE_SIGNALS) -> None:
        self.latent = latent
        self.signals = tuple(signals)
        self.hidden = hidden
        self.window_s = window_s
        self.iterations = iterations
        self.seed = seed
        self.batch = batch
        self.learning_rate = learning_rate
        self.substeps = substeps
        self.channels: list[str] = []
        self.features: list[str] = []
        self.scenarios: list[str] = []
        self.train_seconds = 0.0
        self.loss_history: list[float] = []
        self.trained_on: list[str] = []
        self.gains: dict[str, float] = {}
        self._mean: np.ndarray | None = None
        self._scale: np.ndarray | None = None
        self._channel_scale: np.ndarray | None = None
        self._net: _LatentODE | None = None

    # ------------------------------------------------------------------ features
    def _feature_matrix(self, test: TestResidual) -> np.ndarray:
        """Normalised features (samples, features) on the test's own grid."""
        sig = _signals(test)
        n = len(test.time_s)
        cols = []
        for name in self.features:
            if name.startswith("scenario="):
                cols.append(np.full(n, 1.0 if test.scenario == name[9:] else 0.0))
            else:
                cols.append(sig.get(name, np.zeros(n)))
        x = np.stack(cols, axis=1)
        return (x - self._mean) / self._scale

    def _resampled(self, test: TestResidual) -> tuple[np.ndarray, np.ndarray]:
        """ODE grid of a test and its normalised features on it.

        Every test, whatever its sample rate (200 Hz – 2 kHz), runs on the same
        step, so windows of different tests batch together and the learned
        dynamics do not depend on the logger's rate.
        """
        grid = _grid(test)
        return grid, _resample(test.time_s, grid, self._feature_matrix(test))

    # ------------------------------------------------------------------ training
    def fit(self, tests: list[TestResidual]) -> NeuralResidual:
        """Train on the tests with role ``identification`` (control tests are never read).

        Parameters
        ----------
        tests : list[TestResidual]
            Tests of one campaign, twins simulated with the identified base model.

        Returns
        -------
        NeuralResidual
            ``self``, trained.
        """
        t_start = time.perf_counter()
        train = [t for t in tests if t.role == "identification"]
        if not train:
            raise ValueError("no identification test to train the neural residual on")
        self.trained_on = [t.id for t in train]
        torch.manual_seed(self.seed)
        with _one_thread():
            self._train(train, np.random.default_rng(self.seed))
        self.train_seconds = time.perf_counter() - t_start
        return self

    def _train(self, train: list[TestResidual], rng: np.random.Generator) -> None:
        """Normalise, draw windows, run the Adam steps, then calibrate the gains."""
        self._fit_features(train)
        self._fit_channel_scale(train)
        windows = self._training_windows(train)
        net = _LatentODE(len(self.features), len(self.channels), self.latent, self.hidden)
        self._optimise(net, windows, rng)
        self._net = net
        self._calibrate(train)

    def _fit_features(self, train: list[TestResidual]) -> None:
        """Channels, scenarios, feature names and the features' normalisation (mean, std)."""
        self.channels = sorted({ch for t in train for ch in t.channels},
                               key=lambda c: (c != "steering_torque_nm", c))
        self.scenarios = sorted({t.scenario for t in train})
        sigs = [_signals(t) for t in train]
        names = [n for n in self.signals if any(n in s for s in sigs)]
        stacked = {n: np.concatenate([s.get(n, np.zeros(len(t.time_s)))
                                      for s, t in zip(sigs, train)]) for n in names}
        # a signal constant over the whole campaign carries no information
        names = [n for n in names if np.std(stacked[n]) > 0.0]
        self.features = names + [f"scenario={s}" for s in self.scenarios]
        self._mean = np.array([stacked[n].mean() for n in names] + [0.0] * len(self.scenarios))
        self._scale = np.array([stacked[n].std() for n in names] + [1.0] * len(self.scenarios))

    def _fit_channel_scale(self, train: list[TestResidual]) -> None:
        """Residual RMS per channel over the training tests: every channel weighs alike."""
        scale = []
        for ch in self.channels:
            r = np.concatenate([t.residual(ch) for t in train if ch in t.measured])
            scale.append(max(float(np.sqrt(np.mean(r**2))), 1e-12))
        self._channel_scale = np.array(scale)

    def _training_windows(self, train: list[TestResidual]) -> _TrainingWindows:
        """Normalised data per test on the ODE grid and the window-start distribution."""
        series = []
        for t in train:
            grid, s = self._resampled(t)
            y = np.zeros((len(s), len(self.channels)))
            m = np.zeros_like(y)
            for j, ch in enumerate(self.channels):
                if ch in t.measured:
                    y[:, j] = np.interp(grid, t.time_s, t.residual(ch)) / self._channel_scale[j]
                    m[:, j] = 1.0
            series.append((s, y, m))
        h = 1.0 / TARGET_RATE_HZ
        n_win = max(4, int(round(self.window_s / h)))
        n_wash = int(round(WASHOUT_FRACTION * n_win))
        starts, prob = _window_starts(series, n_win, n_wash)
        return _TrainingWindows(series, starts, prob, n_win, n_wash)

    def _optimise(self, net: _LatentODE, windows: _TrainingWindows,
                  rng: np.random.Generator) -> None:
        """``iterations`` Adam steps (cosine-annealed, gradient norm clipped to 1) on random
        batches of windows, scoring the masked residual after each window's wash-out."""
        opt = torch.optim.Adam(net.parameters(), lr=self.learning_rate)
        sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=self.iterations,
                                                           eta_min=0.1 * self.learning_rate)
        self.loss_history = []
        z0 = torch.zeros(self.batch, self.latent)
        h = 1.0 / TARGET_RATE_HZ
        for _ in range(self.iterations):
            s_t, y_t, m_t = windows.draw(rng, self.batch)
            out = net.outputs(s_t, h, z0, self.substeps)[:, windows.n_wash:]
            loss = (((out - y_t) ** 2) * m_t).sum() / m_t.sum().clamp_min(1.0)
            opt.zero_grad()
            loss.backward()
            nn.utils.clip_grad_norm_(net.parameters(), 1.0)
            opt.step()
            sched.step()
            self.loss_history.append(float(loss.detach()))

    def _calibrate(self, train: list[TestResidual]) -> None:
        """Shrink the correction where it does not pay off open loop on the training tests.

        Training scores short windows; the correction is used open loop over whole
        tests. Per (scenario, channel) the least-squares gain κ = <r, c>/<c, c> of the
        full-length correction c against the residual r, clipped to [0, 1], keeps a
        correction that helps and fades one that fits windows but not whole tests
        (e.g. stick-slip whose phase is not repeatable). Identification tests only.
        """
        num: dict[tuple[str, str], float] = {}
        den: dict[tuple[str, str], float] = {}
        self.gains = {}
        for t, c in zip(train, self._raw_corrections(train)):
            for ch in t.measured:
                key = (t.scenario, ch)
                num[key] = num.get(key, 0.0) + float(np.dot(t.residual(ch), c[ch]))
                den[key] = den.get(key, 0.0) + float(np.dot(c[ch], c[ch]))
        for key in num:
            g = num[key] / den[key] if den[key] > 0 else 0.0
            self.gains[f"{key[0]}/{key[1]}"] = float(np.clip(g, 0.0, 1.0))

    def _gain(self, scenario: str, channel: str) -> float:
        # a scenario not seen in training gets the smallest gain of that channel
        key = f"{scenario}/{channel}"
        if key in self.gains:
            return self.gains[key]
        same = [g for k, g in self.gains.items() if k.endswith("/" + channel)]
        return min(same) if same else 0.0

    # ------------------------------------------------------------------ prediction
    def correction(self, test: TestResidual) -> dict[str, np.ndarray]:
        """Learned correction per channel of ``test``, open loop over the whole test.

        The latent ODE starts at rest (z = 0) at the first sample and runs on the
        250 Hz grid; the result is interpolated back onto the test's own time
        base and scaled by the calibrated gain of its (scenario, channel).
        """
        raw = self._raw_correction(test)
        return {ch: self._gain(test.scenario, ch) * c for ch, c in raw.items()}

    def _raw_correction(self, test: TestResidual) -> dict[str, np.ndarray]:
        return self._raw_corrections([test])[0]

    def _raw_corrections(self, tests: Sequence[TestResidual]) -> list[dict[str, np.ndarray]]:
        """Ungained corrections of several tests, integrated as one batch.

        The integration cost is per solver step, not per trajectory, so a batch of
        whole tests (padded with their last sample) costs about as much as one.
        """
        if self._net is None:
            raise RuntimeError("NeuralResidual.fit has not been called")
        out: list[dict[str, np.ndarray]] = [{} for _ in tests]
        res = [self._resampled(t) for t in tests]
        n = max(len(g) for g, _ in res)
        batch = np.stack([np.pad(s, ((0, n - len(s)), (0, 0)), mode="edge") for _, s in res])
        with torch.no_grad(), _one_thread():
            y = self._net.outputs(torch.tensor(batch, dtype=torch.float32),
                                  1.0 / TARGET_RATE_HZ, torch.zeros(len(tests), self.latent),
                                  self.substeps).double().numpy()
        for b, (t, (grid, _)) in enumerate(zip(tests, res)):
            for j, ch in enumerate(self.channels):
                if ch in t.measured:
                    out[b][ch] = np.interp(t.time_s, grid,
                                           y[b, :len(grid), j] * self._channel_scale[j])
        for t, o in zip(tests, out):
            for ch in t.measured:
                o.setdefault(ch, np.zeros(len(t.time_s)))
        return out

    def corrections(self, tests: Sequence[TestResidual]) -> list[dict[str, np.ndarray]]:
        """``correction`` of several tests at once (one batched integration)."""
        raw = self._raw_corrections(tests)
        return [{ch: self._gain(t.scenario, ch) * c for ch, c in r.items()}
                for t, r in zip(tests, raw)]

    def predict(self, test: TestResidual) -> dict[str, np.ndarray]:
        """Corrected channels: base twin + learned correction (same keys as ``test.measured``)."""
        corr = self.correction(test)
        return {ch: test.simulated[ch] + corr[ch] for ch in test.measured}

    def state_dict(self) -> dict[str, torch.Tensor]:
        """Trained weights (for comparisons and storage)."""
        if self._net is None:
            raise RuntimeError("NeuralResidual.fit has not been called")
        return {k: v.detach().clone() for k, v in self._net.state_dict().items()}


# ---------------------------------------------------------------------------------- explain
def _correlation_ratio(x: np.ndarray, y: np.ndarray, bins: int = 20) -> float:
    """η: share of std(y) explained by the binned conditional mean E[y | x] (quantile bins)."""
    if np.std(x) == 0 or np.std(y) == 0:
        return 0.0
    edges = np.unique(np.quantile(x, np.linspace(0, 1, bins + 1)))
    if len(edges) < 3:
        return 0.0
    idx = np.clip(np.searchsorted(edges, x, side="right") - 1, 0, len(edges) - 2)
    counts = np.bincount(idx, minlength=len(edges) - 1)
    sums = np.bincount(idx, weights=y, minlength=len(edges) - 1)
    means = np.divide(sums, counts, out=np.zeros_like(sums), where=counts > 0)
    between = np.sum(counts * (means - y.mean()) ** 2)
    return float(np.sqrt(between / np.sum((y - y.mean()) ** 2)))


def _state_dependence(tests: list[TestResidual], corr: np.ndarray) -> dict[str, float]:
    """Correlation ratio of ``corr`` (tests concatenated) against every signal, high to low."""
    sigs = [_signals(t) for t in tests]
    names = [n for n in FEATURE_SIGNALS if any(n in s for s in sigs)]
    names += sorted({n for s in sigs for n in s} - set(names))
    dep = {}
    for n in names:
        x = np.concatenate([s.get(n, np.zeros(len(t.time_s))) for s, t in zip(sigs, tests)])
        dep[n] = _correlation_ratio(x, corr)
    return dict(sorted(dep.items(), key=lambda kv: -kv[1]))


def explain(model: NeuralResidual, tests: list[TestResidual], library: LibraryFactory,
            channel: str = "steering_torque_nm", threshold: float = 0.05,
            smooth_s: float = SMOOTH_S) -> dict:
    """Read what the neural residual learned on ``channel``.

    Parameters
    ----------
    model : NeuralResidual
        A trained model.
    tests : list[TestResidual]
        Tests to read the correction on (those without ``channel`` are skipped).
    library : LibraryFactory
        The family's candidate library (``ModelDefinition.candidate_library``), the
        same terms the sparse regression ranks the catalogue with.
    channel : str
        Output channel to explain.
    threshold : float
        STLSQ threshold on standardised coefficients (units of std(correction)
        per std(term)).
    smooth_s : float
        Time constant of the low-pass applied to the correction and to every
        library term before the regression (averages the mesh ringing out).

    Returns
    -------
    dict
        ``state_dependence``: {signal: η}, correlation ratio of the correction
        against each base-model signal (binned conditional mean, 0…1), sorted
        high to low. ``terms``: [(term, catalogue key, coefficient)] kept by the
        sparse regression, largest standardised effect first, coefficient in the
        channel's unit per unit of the (filtered) term; ``base:<component>``
        keys tag terms the base model already has (a mis-identified level, not a
        missing effect). ``ranking``: [(catalogue key, share)], share = std of the
        key's part of the sparse fit over the sum of those of all catalogue keys
        (summing to 1), largest first. ``nominal_share``: the part of the fit (same
        measure) carried by the ``base:`` terms instead.
        ``variance_explained``: R² of the sparse fit of the (low-passed)
        correction. ``residual_explained``: 1 − ‖r − c‖²/‖r‖² of the correction c
        against the measured residual r; near 0, the reading describes noise the
        network followed rather than an effect. ``aliases``: {kept term: [terms
        dropped as near-duplicates of it]}; a kept term speaks for its aliases too.
    """
    used = [t for t in tests if channel in t.measured]
    if not used:
        raise ValueError(f"no test carries channel '{channel}'")
    corrections = [c[channel] for c in model.corrections(used)]
    corr = np.concatenate(corrections)
    resid = np.concatenate([t.residual(channel) for t in used])
    # how much of the measured residual the correction accounts for: near 0, the rest of
    # this reading describes noise the model followed, not an effect
    base = {"state_dependence": _state_dependence(used, corr),
            "residual_explained": float(1.0 - np.sum((resid - corr) ** 2)
                                        / max(np.sum(resid**2), 1e-300))}
    return {**base, **_sparse_reading(used, corrections, library, threshold, smooth_s)}


def _sparse_reading(used: list[TestResidual], corrections: list[np.ndarray],
                    library: LibraryFactory, threshold: float, smooth_s: float) -> dict:
    """``terms``, ``ranking``, ``nominal_share``, ``variance_explained`` and ``aliases`` of
    ``explain``: the low-passed correction regressed (STLSQ) on the library's terms."""
    y_reg, theta, cands = _regression_rows(used, corrections, library, smooth_s)
    std = theta.std(axis=0)
    xs = (theta - theta.mean(axis=0)) / np.where(std > 0, std, 1.0)
    kept, aliases = _prune_aliases(xs, std, [c.name for c in cands])
    y_std = float(np.std(y_reg))
    if y_std == 0.0 or not kept:
        return {"terms": [], "ranking": [], "nominal_share": 0.0,
                "variance_explained": 0.0, "aliases": aliases}
    xs, std, cands = xs[:, kept], std[kept], [cands[j] for j in kept]
    ys = (y_reg - y_reg.mean()) / y_std
    beta = _stlsq(xs, ys, threshold)
    order = np.argsort(-np.abs(beta), kind="stable")
    terms = [(cands[j].name, cands[j].key, float(beta[j] * y_std / std[j]))
             for j in order if beta[j] != 0.0]
    return {"terms": terms, **_key_shares(xs, beta, cands, order),
            "variance_explained": float(1.0 - np.sum((ys - xs @ beta) ** 2) / np.sum(ys**2)),
            "aliases": aliases}


def _regression_rows(used: list[TestResidual], corrections: list[np.ndarray],
                     library: LibraryFactory, smooth_s: float
                     ) -> tuple[np.ndarray, np.ndarray, list[Candidate]]:
    """The regression's target (low-passed correction), term matrix and candidates.

    The correction rings after reversals (a mesh mode the latent ODE reproduces); static
    library terms cannot ring. The same low-pass on both sides of the regression keeps the
    shelf / hysteresis shape the catalogue effects differ by and averages the ringing out.
    After the low-pass, ~100 Hz carries everything: fewer rows, same regression.
    """
    step = [max(1, int(round(1.0 / (REGRESSION_RATE_HZ * t.dt_s)))) for t in used]
    y_reg = np.concatenate([exponential_filter(c, t.dt_s, smooth_s)[::k]
                            for c, t, k in zip(corrections, used, step)])
    theta, cands = _term_matrix(used, library, step, smooth_s)
    return y_reg, theta, cands


def _term_matrix(used: list[TestResidual], library: LibraryFactory, step: list[int],
                 smooth_s: float) -> tuple[np.ndarray, list[Candidate]]:
    """The library's terms of every test, filtered like the channels the correction was
    trained on (the campaign's τ), then low-passed and decimated like the correction."""
    lib = library(used)
    rows = [exponential_filter(exponential_filter(lib.transform(t), t.dt_s, t.tau_s),
                               t.dt_s, smooth_s)[::k] for t, k in zip(used, step)]
    return np.vstack(rows), list(lib.candidates)


def _prune_aliases(xs: np.ndarray, std: np.ndarray,
                   names: list[str]) -> tuple[list[int], dict[str, list[str]]]:
    """Near-duplicate terms (motor and rack speed are proportional through a stiff mesh,
    so their signs coincide) make least squares split a term into large opposite
    coefficients. Keep the first of every group with |r| > ALIAS_CORRELATION and report
    the rest as its aliases."""
    gram = np.abs(xs.T @ xs) / len(xs)  # |correlation| between terms
    kept: list[int] = []
    aliases: dict[str, list[str]] = {}
    for j in range(len(names)):
        if std[j] <= 0:
            continue
        if kept and gram[j, kept].max() > ALIAS_CORRELATION:
            first = kept[int(np.argmax(gram[j, kept]))]
            aliases.setdefault(names[first], []).append(names[j])
            continue
        kept.append(j)
    return kept, aliases


def _stlsq(xs: np.ndarray, ys: np.ndarray, threshold: float) -> np.ndarray:
    import pysindy as ps

    # ridge scaled with the sample count: a mild tie-breaker, not a shrinkage of real terms
    opt = ps.STLSQ(threshold=threshold, alpha=1e-3 * len(ys), max_iter=30)
    opt.fit(xs, ys)
    return np.asarray(opt.coef_, dtype=float).reshape(-1)


def _key_shares(xs: np.ndarray, beta: np.ndarray, cands: list[Candidate],
                order: np.ndarray) -> dict:
    """``ranking`` and ``nominal_share`` of ``explain``.

    A key's weight is the std of its own part of the fit, Σ_j∈key β_j·x_j: a key with
    many candidate terms (several gap widths) gains nothing from their number or their
    cancelling. The ranking answers "which catalogue effect": terms the base model
    already has are reported as one share next to it, not ranked among the effects.
    """
    weight: dict[str, float] = {}
    for key in dict.fromkeys(cands[j].key for j in order if beta[j] != 0.0):
        idx = [j for j in range(len(cands)) if cands[j].key == key and beta[j] != 0.0]
        weight[key] = float(np.std(xs[:, idx] @ beta[idx]))
    total = sum(weight.values())
    effects = {k: w for k, w in weight.items() if not k.startswith("base:")}
    total_eff = sum(effects.values())
    ranking = [(k, w / total_eff) for k, w in sorted(effects.items(), key=lambda kv: -kv[1])]
    return {"ranking": ranking, "nominal_share": 1.0 - total_eff / total if total > 0 else 0.0}


# ---------------------------------------------------------------------------------- plot
def _unit(name: str) -> tuple[str, float]:
    """Display unit and factor from a signal name's suffix (rack positions in mm)."""
    for suffix, unit, k in (("_nm", "N·m", 1.0), ("_rad_per_s", "rad/s", 1.0),
                            ("_m_per_s", "mm/s", 1e3), ("_rad", "rad", 1.0), ("_m", "mm", 1e3),
                            ("_n", "N", 1.0)):
        if name.endswith(suffix):
            return unit, k
    return "-", 1.0


def plot_learned(model: NeuralResidual, tests: Sequence[TestResidual], path,
                 channel: str = "steering_torque_nm", n_tests: int = 3) -> None:
    """Plot what the neural residual learned on ``channel``.

    One row per test (control tests first, then the identification tests with the
    largest residual): the measured residual (measured − base twin) with the learned
    correction over it, on the whole test and zoomed on the largest residual event.
    The last row shows the correction against the base-model signal it depends on
    most (correlation ratio over all ``tests``) for the tests shown, one colour per test.

    Parameters
    ----------
    model : NeuralResidual
        A trained model.
    tests : Sequence[TestResidual]
        Candidate tests.
    path : str or Path
        PNG file to write.
    channel : str
        Channel to show.
    n_tests : int
        Number of tests shown over time (2–3 reads best).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    used = [t for t in tests if channel in t.measured]
    if not used:
        raise ValueError(f"no test carries channel '{channel}'")
    shown = _shown_tests(used, channel, n_tests)
    fig = plt.figure(figsize=(13, 3.0 * (len(shown) + 1.3)), layout="constrained")
    grid = fig.add_gridspec(len(shown) + 1, 3, height_ratios=[1.0] * len(shown) + [1.4])
    corrections = {t.id: c[channel] for t, c in zip(used, model.corrections(used))}
    for row, t in enumerate(shown):
        _residual_row(fig, grid, row, t, channel, corrections[t.id])
    _dependence_row(fig, grid, used, shown, channel, corrections)
    fig.suptitle(f"Physics + neural residual on {channel}: learned correction vs measured "
                 f"residual (measured − base model)", fontsize=12)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _shown_tests(used: list[TestResidual], channel: str, n_tests: int) -> list[TestResidual]:
    """The tests ``plot_learned`` shows over time: control tests first, then the
    identification tests with the largest residual."""
    ctrl = [t for t in used if t.role == "control"]
    ident = sorted((t for t in used if t.role != "control"),
                   key=lambda t: -float(np.std(t.residual(channel))))
    return (ctrl + ident)[:n_tests]


def _dependence_row(fig, grid, used: list[TestResidual], shown: list[TestResidual],
                    channel: str, corrections: dict[str, np.ndarray]) -> None:
    """Last row of ``plot_learned``: the correction of the shown tests against the signal
    it depends on most (correlation ratio over all ``used`` tests), one colour per test."""
    unit, k = _unit(channel)
    dep = _state_dependence(used, np.concatenate([corrections[t.id] for t in used]))
    top = next(iter(dep))
    s_unit, s_k = _unit(top)
    ax = fig.add_subplot(grid[-1, :])
    # colours apart from the time plots' (orange there is the correction itself)
    for t, colour in zip(shown, ("tab:blue", "tab:purple", "tab:brown", "tab:cyan", "tab:olive")):
        x = _signals(t).get(top)
        if x is not None:
            ax.plot(x * s_k, corrections[t.id] * k, lw=0.7, alpha=0.85, color=colour,
                    label=f"{t.id} ({t.role})")
    ax.set_xlabel(f"{top} [{s_unit}]")
    ax.set_ylabel(f"learned correction [{unit}]")
    ax.set_title(f"correction vs the signal it depends on most: {top} "
                 f"(correlation ratio {dep[top]:.2f})", fontsize=10, loc="left")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="upper left")


def _residual_row(fig, grid, row: int, t: TestResidual, channel: str,
                  correction: np.ndarray) -> None:
    """One test of ``plot_learned``: residual, learned correction and what remains, over
    the whole test and zoomed on the largest residual event."""
    from mbst.core.metrics import fit_percent

    unit, k = _unit(channel)
    r = t.residual(channel) * k
    c = correction * k
    fit_b = fit_percent(t.measured[channel], t.simulated[channel])
    fit_n = fit_percent(t.measured[channel], t.simulated[channel] + correction)
    peak = int(np.argmax(np.abs(t.residual(channel))))
    lo = max(t.time_s[0], t.time_s[peak] - 0.15)
    zoom = (t.time_s >= lo) & (t.time_s <= lo + 0.5)
    for ax, m in ((fig.add_subplot(grid[row, :2]), slice(None)),
                  (fig.add_subplot(grid[row, 2]), zoom)):
        ax.plot(t.time_s[m], r[m], color="0.35", lw=1.0, label="measured residual")
        ax.plot(t.time_s[m], c[m], color="tab:orange", lw=1.3, label="learned correction")
        ax.plot(t.time_s[m], (r - c)[m], color="tab:green", lw=0.7, alpha=0.8,
                label="remaining after correction")
        ax.axhline(0.0, color="0.8", lw=0.6, zorder=0)
        ax.set_xlabel("time [s]")
        ax.set_ylabel(f"{channel} residual [{unit}]", fontsize=8)
        ax.grid(alpha=0.3)
    ax.set_title("zoom on the largest residual", fontsize=9)
    fig.axes[-2].set_title(f"{t.id}  ({t.scenario}, {t.role})   FIT base {fit_b:.1f} % → "
                           f"physics+neural {fit_n:.1f} %", fontsize=10, loc="left")
    if row == 0:
        fig.axes[-2].legend(loc="upper right", fontsize=8, ncol=3)
