"""What a residual correlates with, in a generic library that names no catalogue effect.

Each group of features is one physical reading of a residual (a "signature"):

``lag:<channel>``
    d/dt of the channel's own twin: the channel is logged late (or early) on
    the angle that drives the model — a sensor's filter, a bus delay. Its
    coefficient is minus the lag in seconds.
``periodic:<angle>``
    sin and cos of N·angle, with N per revolution chosen by the data: a ripple
    locked to a rotating part (motor cogging, a universal joint's 2nd order).
``polynomial:<quantity>``
    the quantity, its square and cube: a gain, ratio or stiffness that varies
    along the travel or with load.
``drift:time``
    the direction of motion (and the twin) times the test's place in the
    campaign: friction or a gain that changes as the rig warms up.

The features come from the model's own signals (``TestResidual.states``, its
input angle and twins) put through the preprocessing's exponential filter, so
they see the residual's filtering. Each group is scored by the share of the
residual it predicts on tests it was not fitted on (leave one test out), and
the chance level of that share comes from the residual itself: phase-randomised
copies keep its spectrum (its noise colour) and lose any tie to the rig's
motion, and go through the same search. Held-out control tests never enter.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field

import numpy as np
import pysindy as ps

from mbst.core.filtering import exponential_filter
from mbst.discovery.data import TestResidual

# harmonics per revolution searched for a ripple locked to a rotating part
MAX_PERIODS_PER_REV = 64
# samples per test kept for the regressions (the filtered residual is smooth)
SAMPLES_PER_TEST = 1500
# periods of a ripple a test must sweep for the ripple to count as periodic in that angle
MIN_PERIODS_SEEN = 2
# a ripple repeats: the share its term explains on either side of the tests' middle angle
# within this ratio (``_one_sided_ripple``); a structure at one place is not a ripple
REPEAT_RATIO = 0.5
# orders this near the ripple's order or one of its multiples, or dividing it, are its own
# reading (a ripple that is no pure sine; a test that sweeps few periods), not a rival order
NEAR_ORDER = 1
# held-out folds: the tests, or contiguous stretches of them where a campaign has fewer
MIN_FOLDS = 4
SURROGATES = 19  # chance level: the largest of 19 phase-randomised copies (p ≤ 0.05)

__all__ = ["ChannelSignature", "GroupScore", "abscissa", "describe_channel", "feature_groups",
           "feature_names", "learned_term"]


@dataclass
class GroupScore:
    """One signature group's fit to a channel's residual."""

    group: str
    cv_share: float  # share of the residual predicted on held-out tests
    coefficients: np.ndarray
    harmonic: int = 0  # periods per revolution of a periodic group
    scenarios: tuple[str, ...] = ()  # the cut-outs it was fitted on (the drift's blocks)

    def quantities(self) -> dict[str, float]:
        """The group's size in physical terms (the lag in s, the ripple's order)."""
        kind, _, _ = self.group.partition(":")
        if kind == "lag":
            return {"lag_s": -float(self.coefficients[0])} if len(self.coefficients) else {}
        if kind == "periodic":
            return {"periods_per_rev": float(self.harmonic)}
        if kind == "drift":  # the level's change from the first test to the last, per cut-out
            return {f"change_{sc}": float(self.coefficients[2 * i + 1])
                    for i, sc in enumerate(self.scenarios) if 2 * i + 1 < len(self.coefficients)}
        return {}


@dataclass
class ChannelSignature:
    """What one channel's residual correlates with, and how far above chance."""

    channel: str
    gain_error: float  # measured/simulated − 1, taken out before the search (calibration)
    # how much of the learned term a test it was not fitted on bears out (0…1, held out)
    learned_gain: float
    residual_rms: float
    noise_rms: float
    best: GroupScore | None
    chance_share: float  # the largest held-out share of the phase-randomised copies
    p_value: float
    ranking: list[GroupScore] = field(default_factory=list)
    # the share above chance a signature must predict to count: the margin a catalogue
    # effect must remove of its stage (``min_relative_gain``)
    min_share: float = 0.0
    # why a periodic reading was dropped (it sat on one side of the sweep, or no one order
    # stood out from the others), or ''
    not_a_ripple: str = ""

    @property
    def explained_rms(self) -> float:
        share = self.best.cv_share if self.best else 0.0
        return self.residual_rms * math.sqrt(max(share, 0.0))

    @property
    def above_chance(self) -> float:
        """The held-out share the best group predicts beyond the best phase-randomised copy."""
        return (self.best.cv_share if self.best else 0.0) - self.chance_share

    @property
    def structured(self) -> bool:
        """Above chance by the margin and above the noise floor: a structure worth naming.

        Without the margin, a realistic clean rig (drawn rig, known values 10 % off, AR(1)
        noise) got an unexplained "polynomial in torsion-bar torque" in the rack position
        at 1.1× its noise floor, 11 % of the residual against 4 % by chance: the small
        mismatch every real model leaves, which the catalogue would not name either."""
        return (self.best is not None and self.above_chance > 0
                and self.above_chance >= self.min_share
                and self.explained_rms > self.noise_rms)


def _filtered(t: TestResidual, x: np.ndarray) -> np.ndarray:
    return exponential_filter(x, t.dt_s, t.tau_s) if t.tau_s > 0 else np.asarray(x, float)


def _signals(t: TestResidual, input_name: str) -> dict[str, np.ndarray]:
    """The model's own signals a residual may correlate with (speeds, frictions and the
    mesh's small deflection are left to the lag group and the catalogue)."""
    skip = ("_speed_", "_friction_", "mesh")
    out = {input_name: t.angle_rad}
    out.update({k: v for k, v in t.states.items() if not any(s in k for s in skip)})
    return {k: v for k, v in out.items() if np.ptp(v) > 0}


def feature_groups(t: TestResidual, channel: str, place: float, input_name: str = "input",
                   scenarios: tuple[str, ...] = ()
                   ) -> dict[str, np.ndarray | dict[int, np.ndarray]]:
    """The generic library on one test: group → (samples, features), or, for a periodic
    group, harmonic → (samples, features). ``place``: the test's place in the campaign
    (−½…½); ``input_name``: the driving input's name (``SystemFamily.input_channel``);
    ``scenarios``: the cut-outs of the tests fitted together (the drift's blocks)."""
    twin = t.simulated[channel]
    groups: dict = {f"lag:{channel}": np.gradient(twin, t.dt_s)[:, None],
                    "gain": twin[:, None]}
    signals = _signals(t, input_name)
    for name, q in signals.items():  # in the quantity's own units: tests share the law
        groups[f"polynomial:{name}"] = _filtered(t, np.column_stack([q, q * q, q ** 3]))
    angles = {k: a for k, a in signals.items() if k.endswith("_angle_rad")
              and np.ptp(a) * MAX_PERIODS_PER_REV >= MIN_PERIODS_SEEN * 2 * math.pi}
    for name, a in angles.items():
        groups[f"periodic:{name}"] = _orders(t, a)
    groups["drift:time"] = _drift(t, place, scenarios or (t.scenario,))
    return groups


def _drift(t: TestResidual, place: float, scenarios: tuple[str, ...]) -> np.ndarray:
    """A friction level that changes over the campaign: the direction of motion, alone and
    times the test's place, one block per cut-out (each cut-out's stage fits its own
    levels, so each has its own mean level to change from)."""
    scale = 0.05 * (np.std(t.omega_rad_per_s) or 1.0)
    sign = np.tanh(t.omega_rad_per_s / scale)
    out = np.zeros((len(sign), 2 * len(scenarios)))
    if t.scenario in scenarios:
        j = 2 * scenarios.index(t.scenario)
        out[:, j], out[:, j + 1] = sign, place * sign
    return out


def _orders(t: TestResidual, angle: np.ndarray) -> dict[int, np.ndarray]:
    """sin and cos of each order N of ``angle``, times 1, s and s² (s: the angle's speed
    over the test's largest): the rig's dynamics between the ripple and the sensor pass each
    frequency N·ω with its own gain and phase, which a fixed pair cannot follow."""
    speed = np.abs(np.gradient(angle, t.dt_s))
    s = speed / (speed.max() or 1.0)
    mod = np.column_stack([np.ones_like(s), s, s * s])
    out = {}
    # a ripple is periodic only where the test sweeps two of its periods at least: less is a
    # smooth function of the angle, the polynomial group's reading
    for n in range(int(math.ceil(MIN_PERIODS_SEEN * 2 * math.pi / max(np.ptp(angle), 1e-12))),
                   MAX_PERIODS_PER_REV + 1):
        sc = np.column_stack([np.sin(n * angle), np.cos(n * angle)])
        out[n] = _filtered(t, (sc[:, :, None] * mod[:, None, :]).reshape(len(s), -1))
    return out


@dataclass
class _Library:
    """One channel over the tests that log it: residuals and each candidate's features,
    decimated and centred per test, with their Gram matrices (a surrogate changes the
    residual only, so the search over groups and harmonics reuses them)."""

    y: list[np.ndarray]
    features: dict[tuple[str, int], list[np.ndarray]]
    grams: dict[tuple[str, int], list[np.ndarray]]
    scenarios: tuple[str, ...]
    scales: dict[tuple[str, int], np.ndarray]
    # the angles a periodic group may follow, sample for sample with ``y``
    angles: dict[str, list[np.ndarray]] = field(default_factory=dict)

    def stats(self, ys: list[np.ndarray]) -> dict[tuple[str, int], list[tuple]]:
        return {key: [(g, x.T @ y, float(y @ y)) for g, x, y in
                      zip(self.grams[key], xs, ys, strict=True)]
                for key, xs in self.features.items()}


def _library(tests: list[TestResidual], channel: str, places: dict[str, float],
             input_name: str) -> _Library:
    ys, per_test = [], []
    logged = [t for t in tests if channel in t.measured]
    scenarios = tuple(dict.fromkeys(t.scenario for t in logged))
    for t in logged:
        step = max(1, len(t.time_s) // SAMPLES_PER_TEST)
        ys.append(_centre(t.residual(channel)[::step]))
        flat = {(f"angle:{k}", 0): q[::step, None] for k, q in _signals(t, input_name).items()
                if k.endswith("_angle_rad")}
        groups = feature_groups(t, channel, places.get(t.id, 0.0), input_name, scenarios)
        for k, v in groups.items():
            for n, x in (v.items() if isinstance(v, dict) else [(0, v)]):
                flat[(k, n)] = _centre(x[::step])
        per_test.append(flat)
    keys = sorted({k for f in per_test for k in f})
    feats = {}
    for key in keys:
        width = next(f[key].shape[1] for f in per_test if key in f)
        feats[key] = [f.get(key, np.zeros((len(y), width))) for f, y in zip(per_test, ys)]
    if 0 < len(ys) < MIN_FOLDS:  # one or two long tests: contiguous stretches are the folds
        k = -(-MIN_FOLDS // len(ys))
        ys = [b for y in ys for b in np.array_split(y, k)]
        feats = {key: [b for x in xs for b in np.array_split(x, k)] for key, xs in feats.items()}
    angles = {key[0].partition(":")[2]: [x[:, 0] for x in feats.pop(key)]
              for key in [k for k in feats if k[0].startswith("angle:")]}
    # each column on the scale of its spread over all tests: the search's tiny ridge then
    # weighs q and q³ alike (the learned term's coefficients are mapped back, ``_raw``)
    scales = {}
    for key, xs in feats.items():
        sd = np.concatenate(xs).std(axis=0)
        scales[key] = np.where(sd > 0, sd, 1.0)
        feats[key] = [x / scales[key] for x in xs]
    grams = {k: [x.T @ x for x in xs] for k, xs in feats.items()}
    return _Library(ys, feats, grams, scenarios, scales, angles)


def _centre(x: np.ndarray) -> np.ndarray:
    return x - x.mean(axis=0)


def _solve(g: np.ndarray, b: np.ndarray) -> np.ndarray:
    ridge = 1e-9 * (np.trace(g) / len(g) or 1.0)
    return np.linalg.solve(g + ridge * np.eye(len(g)), b)


def _in_sample(stats: list[tuple]) -> float:
    g, b = sum(s[0] for s in stats), sum(s[1] for s in stats)
    return float(b @ _solve(g, b))


def _cv_share(stats: list[tuple]) -> float:
    """Share of the residual a group predicts on held-out tests (leave one test out),
    from per-test Gram matrices: SSE_k = yᵀy − 2cᵀb_k + cᵀG_k c."""
    total = sum(s[2] for s in stats)
    if total <= 0 or len(stats) < 2:
        return 0.0
    g_all, b_all = sum(s[0] for s in stats), sum(s[1] for s in stats)
    sse = 0.0
    for g, b, yy in stats:
        c = _solve(g_all - g, b_all - b)
        sse += yy - 2.0 * float(c @ b) + float(c @ g @ c)
    return 1.0 - sse / total


def _score_groups(lib: _Library, ys: list[np.ndarray]) -> list[GroupScore]:
    """Each group at its best harmonic (in-sample), scored on held-out tests."""
    stats = lib.stats(ys)
    best: dict[str, tuple[float, int]] = {}
    for (group, n), st in stats.items():
        r = _in_sample(st)
        if group not in best or r > best[group][0]:
            best[group] = (r, n)
    scores = [GroupScore(g, _cv_share(stats[(g, n)]), np.zeros(0), n, lib.scenarios)
              for g, (_, n) in best.items()]
    return sorted(scores, key=lambda s: -s.cv_share)


def _fit(xs: list[np.ndarray], ys: list[np.ndarray]) -> np.ndarray:
    """The learned term's coefficients: pysindy's STLSQ on standardised columns."""
    x, y = np.concatenate(xs), np.concatenate(ys)
    sd = x.std(axis=0)
    sd[sd == 0] = 1.0
    opt = ps.STLSQ(threshold=1e-3 * float(np.std(y) or 1.0), alpha=1e-9, normalize_columns=False)
    with warnings.catch_warnings():  # a group with nothing to explain is a valid answer
        warnings.simplefilter("ignore", UserWarning)
        opt.fit(x / sd, y)
    return np.ravel(opt.coef_) / sd


def _take_out_gain(lib: _Library) -> float:
    """Fit and remove the channel's scale against its twin (a known ratio or a sensor gain
    a little off is calibration, as an offset is, not an effect); returns the relative
    scale error (measured/simulated − 1)."""
    scale = float(lib.scales.pop(("gain", 0))[0])
    twins = [x * scale for x in lib.features.pop(("gain", 0))]
    lib.grams.pop(("gain", 0))
    x, y = np.concatenate(twins)[:, 0], np.concatenate(lib.y)
    xx = float(x @ x)
    g = float(x @ y) / xx if xx > 0 else 0.0
    lib.y = [yk - g * xk[:, 0] for yk, xk in zip(lib.y, twins, strict=True)]
    return g


def _held_out_gain(stats: list[tuple], xs: list[np.ndarray], ys: list[np.ndarray]) -> float:
    """The gain κ ∈ [0, 1] that best scales the held-out predictions onto the residual: the
    learned term is applied at κ, so a signature that predicts little is applied little."""
    g_all, b_all = sum(st[0] for st in stats), sum(st[1] for st in stats)
    num = den = 0.0
    for (g, b, _), x, y in zip(stats, xs, ys, strict=True):
        pred = x @ _solve(g_all - g, b_all - b)
        num += float(y @ pred)
        den += float(pred @ pred)
    return float(np.clip(num / den, 0.0, 1.0)) if den > 0 else 0.0


def _surrogate(y: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """The same spectrum with random phases: the residual's colour, no tie to the motion."""
    f = np.fft.rfft(y)
    phase = np.exp(2j * math.pi * rng.random(len(f)))
    phase[0] = 1.0
    return np.fft.irfft(np.abs(f) * phase, n=len(y))


def describe_channel(tests: list[TestResidual], channel: str, places: dict[str, float],
                     noise_rms: float, seed: int = 0, surrogates: int = SURROGATES,
                     input_name: str = "input", min_share: float = 0.0
                     ) -> ChannelSignature | None:
    """Rank the signature groups on one channel's residual and set them against chance
    (``surrogates`` phase-randomised copies; 0: no chance level, p = 1). ``min_share``: the
    held-out share above chance a structure must reach (``ChannelSignature.structured``)."""
    lib = _library(tests, channel, places, input_name)
    if not lib.y:
        return None
    gain = _take_out_gain(lib)
    ranking = _score_groups(lib, lib.y)
    # the copies keep every group, periodic ones too: a dropped reading leaves the chance
    # level where it was, the stricter side
    rng = np.random.default_rng([seed, 31])
    chance = [max(s.cv_share for s in _score_groups(lib, [_surrogate(y, rng) for y in lib.y]))
              for _ in range(surrogates)]
    not_a_ripple = _one_sided_ripple(lib, ranking)
    if not not_a_ripple and ranking and \
            ranking[0].cv_share - max(chance, default=math.inf) >= min_share:
        # only a reading that would count is questioned for its order: a ripple too weak
        # to clear chance by the margin stays the (small) ripple it is
        not_a_ripple = _no_order_stands_out(lib, ranking, min_share)
    if not_a_ripple:
        ranking = [g for g in ranking if not g.group.startswith("periodic:")]
    best = ranking[0] if ranking else None
    shrink = 0.0
    if best is not None:
        key = (best.group, best.harmonic)
        best.coefficients = _fit(lib.features[key], lib.y) / lib.scales[key]
        shrink = _held_out_gain(lib.stats(lib.y)[key], lib.features[key], lib.y)
    obs = best.cv_share if best else 0.0
    y = np.concatenate(lib.y)
    return ChannelSignature(
        channel=channel, gain_error=gain, learned_gain=shrink, residual_rms=float(np.sqrt(np.mean(y * y))), noise_rms=noise_rms,
        best=best, chance_share=float(max(chance, default=math.inf)),
        p_value=(1 + sum(c >= obs for c in chance)) / (1 + surrogates), ranking=ranking,
        min_share=min_share, not_a_ripple=not_a_ripple)


def _one_sided_ripple(lib: _Library, ranking: list[GroupScore]) -> str:
    """Why the best group, a periodic one, is no ripple: it sits on one side of the sweep.

    A ripple locked to a rotating part (a cogging, a joint's second order) repeats over
    the angle: its term explains the residual alike on either side of the tests' middle
    angle. A structure at one place (a rack friction that rises at one position, left
    over beside its catalogue name) is fitted by a high order over the narrow range the
    tests sweep, and predicts held-out tests that pass the same place: an
    independent-simulator-like rig (seed 911) got "a ripple in steering_torque_nm
    periodic in motor_angle_rad, 22 periods per revolution" at 0.68 beside its named
    position-dependent rack friction. Returns '' for a ripple that repeats (or a best
    group that is not periodic), else the reading dropped.
    """
    if not ranking or not ranking[0].group.startswith("periodic:"):
        return ""
    best = ranking[0]
    key = (best.group, best.harmonic)
    quantity = best.group.partition(":")[2]
    if quantity not in lib.angles:
        return ""
    coef = _fit(lib.features[key], lib.y)
    term = np.concatenate([x @ coef for x in lib.features[key]])
    y = np.concatenate(lib.y)
    angle = np.concatenate(lib.angles[quantity])
    middle = float(np.median(angle))
    # the share of the residual the one term explains on either side of the middle angle
    sides = [1.0 - float(np.sum((y[m] - term[m]) ** 2) / np.sum(y[m] ** 2))
             if m.any() and np.any(y[m]) else 0.0
             for m in (angle < middle, angle >= middle)]
    if max(sides) <= 0 or min(sides) >= REPEAT_RATIO * max(sides):
        return ""
    return (f"{best.group} at {best.harmonic} periods per revolution explains "
            f"{100 * max(sides):.0f} % of the residual on one side of the tests' middle "
            f"angle and {100 * min(sides):.0f} % on the other: a structure at one place, "
            "not a ripple")


def _no_order_stands_out(lib: _Library, ranking: list[GroupScore], margin: float) -> str:
    """Why the best group, a periodic one, is no ripple: an unrelated order predicts nearly
    as much.

    A ripple locked to a rotating part is predicted by its order (and its harmonics) and
    hardly by the orders between (a 0.02 ripple at order 18 on four 30° sines: 22 % held
    out, the best unrelated order, 15, 8 %). A residual that repeats with the motion in
    another way (a transient after each reversal that the model's friction lacks) is
    predicted alike by many unrelated orders, since every feature of the angle repeats
    with the motion too and the filtered features weigh the slow stretches around the
    reversals most; the phase-randomised copies lose that tie, so the chance level alone
    does not see it. An
    independent-simulator-like rig (seed 1501, an unfitted column presliding, 1 kHz) got "a
    ripple in steering_torque_nm periodic in motor_angle_rad, 47 periods per revolution" at
    0.76 with 16 % held out, against 11 % at order 31, 9 % at 37 and 6 % at 53. The order
    must predict more than the best unrelated one by the margin a signature must clear
    above chance (``margin``). Returns '' where it does (or the best group is not periodic).
    """
    if not ranking or not ranking[0].group.startswith("periodic:"):
        return ""
    best = ranking[0]
    n0, group = best.harmonic, best.group
    rivals = [(_cv_share(st), n) for (g, n), st in lib.stats(lib.y).items()
              if g == group and not _related_order(n, n0)]
    if not rivals:
        return ""
    share1, n1 = max(rivals)
    if best.cv_share - share1 > margin:
        return ""
    return (f"{group} at {n0} periods per revolution predicts {100 * best.cv_share:.0f} % "
            f"held out and order {n1}, unrelated, {100 * share1:.0f} %: no one order stands "
            "out, a structure that repeats with the motion, not a ripple")


def _related_order(n: int, n0: int) -> bool:
    """Whether order ``n`` is near ``n0``, near one of its multiples, or divides it."""
    near_multiple = min(abs(n - k * n0) for k in range(1, n // n0 + 2)) <= NEAR_ORDER
    return near_multiple or n0 % n == 0


def learned_term(t: TestResidual, sig: ChannelSignature, place: float,
                 input_name: str = "input") -> np.ndarray:
    """The channel's fitted correction on a test it may not have seen: its scale error and
    its best signature group (the "physics + learned" model)."""
    twin = t.simulated[sig.channel]
    out = sig.gain_error * _centre(twin)
    if sig.best is None or not len(sig.best.coefficients):
        return out
    x = feature_groups(t, sig.channel, place, input_name, sig.best.scenarios).get(sig.best.group)
    if isinstance(x, dict):
        x = x.get(sig.best.harmonic)
    return out if x is None else out + sig.learned_gain * (_centre(x) @ sig.best.coefficients)


def abscissa(t: TestResidual, score: GroupScore, place: float,
             input_name: str = "input") -> tuple[np.ndarray, str]:
    """What to draw a channel's residual against to see its signature, and its label."""
    kind, _, quantity = score.group.partition(":")
    if kind == "lag":
        return np.gradient(t.simulated[quantity], t.dt_s), f"d/dt of the {quantity} twin [/s]"
    if kind == "drift":
        return np.full(len(t.time_s), place), "test's place in the campaign (first −½, last ½)"
    signal = _signals(t, input_name).get(quantity, np.zeros(len(t.time_s)))
    if kind == "periodic":
        return (np.mod(score.harmonic * signal, 2 * math.pi),
                f"{score.harmonic}·{quantity} mod 2π [rad]")
    return signal, quantity


def feature_names(score: GroupScore) -> list[str]:
    """Names of a group's features, in the order of its coefficients."""
    kind, _, q = score.group.partition(":")
    if kind == "lag":
        return [f"d/dt {q}"]
    if kind == "polynomial":
        return [q, f"{q}^2", f"{q}^3"]
    if kind == "periodic":
        n = score.harmonic
        return [f"{f}({n}·{q})·{m}" for f in ("sin", "cos") for m in ("1", "s", "s^2")]
    return [f"{t}[{sc}]" for sc in score.scenarios for t in ("sign(ω)", "place·sign(ω)")]
