"""Friction damper: parameters, catalogue and compiled simulator.

The physics an engineer writes first for a band brake driven by an actuator
(docs/friction-damper.md): the band's stiffness in series with a Coulomb slip
(an elastoplastic element), a viscous term and the load cell's offset::

    F = F_band + c·ẋ + F_offset,   F_band = k·(x − s),   |F_band| ≤ F_c,

where ``s`` is where the band has slipped to. The catalogue adds what it
lacks, in the family's own terms: play (backlash) between actuator and band,
direction-dependent (asymmetric) slip levels — a band brake is self-energising
one way —, a contact that stiffens with load (force ∝ deflection^n), Stribeck
friction and relaxation of the band's stored force while it sticks.

The displacement is imposed, so the model is one pass over the measured
displacement: no integration, no step-size question.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numba as nb
import numpy as np

from mbst.core.model import EffectSpec, ParamSpec

if TYPE_CHECKING:
    from mbst.identify.fitting import PreparedTest
    from mbst.io.campaign import Campaign

PARAM_SPECS: tuple[ParamSpec, ...] = (
    # nominal elastoplastic band
    ParamSpec("band.stiffness_n_per_m", "N/m", 5e6, 1e4, 1e9, "base", "band", True),
    ParamSpec("band.coulomb_n", "N", 1e4, 1.0, 1e6, "base", "band", True),
    ParamSpec("band.viscous_ns_per_m", "N·s/m", 0.0, 0.0, 1e6, "base", "band"),
    # the load cell is zeroed before a test (the data set's earthquake runs read about
    # 0.1 kN at rest): an offset fitted beside symmetric levels would stand in for the
    # band's direction-dependent level, the effect a band brake is known for
    ParamSpec("load_cell.force_offset_n", "N", 0.0, -1e5, 1e5, "fixed", "load_cell"),
    # effects, neutral by default
    ParamSpec("band.backlash.width_m", "m", 0.0, 0.0, 0.02, "effect", "band"),
    ParamSpec("band.asymmetric_friction.ratio", "-", 1.0, 0.25, 4.0, "effect", "band", True),
    ParamSpec("band.contact_stiffening.exponent", "-", 1.0, 1.0, 4.0, "effect", "band"),
    ParamSpec("band.stribeck_friction.static_to_coulomb_ratio", "-", 1.0, 1.0, 4.0,
              "effect", "band"),
    ParamSpec("band.stribeck_friction.stribeck_velocity", "m/s", 0.005, 1e-4, 0.2,
              "effect", "band", True),
    ParamSpec("band.force_relaxation.rate_per_s", "1/s", 0.0, 0.0, 50.0, "effect", "band"),
)
PARAM_INDEX = {s.name: i for i, s in enumerate(PARAM_SPECS)}
(I_K, I_FC, I_C, I_OFF, I_GAP, I_ASYM, I_EXP, I_STAT, I_VS, I_RELAX) = range(len(PARAM_SPECS))

# the contact law's reference deflection: at 1 mm beyond the play the band carries
# k·1 mm whatever the exponent, so the stiffness keeps its unit and meaning
D_REF_M = 1e-3


def _effect(effect: str, size: dict[str, float], size_parameters: tuple[str, ...] = (),
            absorbed_by: tuple[str, ...] = ()) -> EffectSpec:
    prefix = f"band.{effect}."
    return EffectSpec(effect, "band", {n[len(prefix):]: n for n in size}, tuple(size), size,
                      absorbed_by=absorbed_by, size_parameters=size_parameters)


CATALOGUE: tuple[EffectSpec, ...] = (
    # a play hides behind a softer band: the fit without it lowers k
    _effect("backlash", {"band.backlash.width_m": 1.5e-3},
            absorbed_by=("band.stiffness_n_per_m",)),
    _effect("asymmetric_friction", {"band.asymmetric_friction.ratio": 1.3}),
    _effect("contact_stiffening", {"band.contact_stiffening.exponent": 1.8},
            absorbed_by=("band.stiffness_n_per_m",)),
    _effect("stribeck_friction",
            {"band.stribeck_friction.static_to_coulomb_ratio": 1.3,
             "band.stribeck_friction.stribeck_velocity": 0.005},
            ("band.stribeck_friction.static_to_coulomb_ratio",),
            absorbed_by=("band.coulomb_n",)),
    _effect("force_relaxation", {"band.force_relaxation.rate_per_s": 1.0}),
)

BASE_PARAMS = ("band.stiffness_n_per_m", "band.coulomb_n", "band.viscous_ns_per_m")
CASCADE = (("imposed_displacement", BASE_PARAMS),)
# band_slip_direction: +1/−1 while the band slips forwards/backwards at its level, else 0
INTERNAL = ("velocity_m_per_s", "band_force_n", "band_deflection_m", "band_slip_direction")
N_OUT = 1 + len(INTERNAL)


# -------------------------------------------------------------------------------------
# the equations (compiled)
# -------------------------------------------------------------------------------------
@nb.njit(cache=True, inline="always")
def _contact_force(a, k, n):
    """Band force at deflection ``a`` ≥ 0 beyond the play."""
    return k * D_REF_M * (a / D_REF_M) ** n


@nb.njit(cache=True, inline="always")
def _deflection(f, k, n):
    """Deflection beyond the play at which the band carries force ``f`` ≥ 0."""
    return D_REF_M * (f / (k * D_REF_M)) ** (1.0 / n)


@nb.njit(cache=True, inline="always")
def _slip_levels(p, v_abs):
    """Slip level in the +/− direction at speed |v|."""
    level = p[I_FC]
    if p[I_STAT] > 1.0:
        level *= 1.0 + (p[I_STAT] - 1.0) * math.exp(-(v_abs / p[I_VS]) ** 2)
    return level, level * p[I_ASYM]


@nb.njit(cache=True)
def _run(x, v, p, f0, dt, out):
    k, n, half_gap = p[I_K], p[I_EXP], 0.5 * p[I_GAP]
    keep = math.exp(-dt * p[I_RELAX])
    # the band's initial state carries the measured initial force
    up, down = _slip_levels(p, abs(v[0]))
    # (an initial force of exactly zero: at rest in the play, at its centre)
    f_init = 0.0
    if f0 != 0.0:
        f_init = min(max(f0 - p[I_OFF] - p[I_C] * v[0], -0.999 * down), 0.999 * up)
    s = x[0]
    if f_init > 0.0:
        s = x[0] - half_gap - _deflection(f_init, k, n)
    elif f_init < 0.0:
        s = x[0] + half_gap + _deflection(-f_init, k, n)
    for i in range(x.shape[0]):
        up, down = _slip_levels(p, abs(v[i]))
        d = x[i] - s
        a = abs(d) - half_gap
        f = 0.0
        if a > 0.0:
            if keep < 1.0:
                # the stored force relaxes: the band creeps towards its unloaded state
                a *= keep
                s = x[i] - math.copysign(half_gap + a, d)
            f = math.copysign(_contact_force(a, k, n), d)
        if f > up:
            f = up
            s = x[i] - half_gap - _deflection(up, k, n)
        elif f < -down:
            f = -down
            s = x[i] + half_gap + _deflection(down, k, n)
        out[i, 0] = f + p[I_OFF] + p[I_C] * v[i]
        out[i, 1] = v[i]
        out[i, 2] = f
        out[i, 3] = x[i] - s
        out[i, 4] = 1.0 if f >= up else (-1.0 if f <= -down else 0.0)


@nb.njit(parallel=True, cache=True)
def simulate_kernel(x, v, ps, f0, dt):
    """Outputs (B, N, N_OUT) for B parameter vectors: force, then internals."""
    out = np.empty((ps.shape[0], x.shape[0], N_OUT))
    for b in nb.prange(ps.shape[0]):
        _run(x, v, ps[b], f0, dt, out[b])
    return out


# -------------------------------------------------------------------------------------
# hooks of the model definition
# -------------------------------------------------------------------------------------
INIT_SAMPLES = 10  # the initial force: the median of the first samples (sensor noise)
NOISE_SAMPLES = 64  # and its noise: the first samples' differences
VELOCITY_WINDOW_S = 0.01  # centred moving average of the differentiated displacement


def _centred_average(x: np.ndarray, dt_s: float, window_s: float) -> np.ndarray:
    n = max(int(round(window_s / dt_s)) | 1, 1)
    if n <= 1 or len(x) < n:
        return x
    pad = n // 2
    xp = np.pad(x, pad, mode="edge")
    return np.convolve(xp, np.ones(n) / n, mode="valid")


def prepare_inputs(frame, dt_s: float, spec, window_s: float = 0.0
                   ) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]:
    """The measured displacement drives the model as recorded; its rate is the
    differentiated displacement averaged over 10 ms without lag (the recorded
    velocity, where present, is not needed)."""
    x = frame["displacement_m"].to_numpy(float)
    v = _centred_average(np.gradient(x, dt_s), dt_s, VELOCITY_WINDOW_S)
    force = frame["friction_force_n"].to_numpy(float) if "friction_force_n" in frame else None
    return x, v, {"initial_force_n": np.array([initial_force(force)])}


def initial_force(force_n: np.ndarray | None) -> float:
    """The band's force at the start: the median of the first samples, or zero where
    that is within three noise deviations of zero — a band at rest in its play carries
    none, and the play's position is then its centre, not one edge picked by noise."""
    if force_n is None or len(force_n) == 0:
        return 0.0
    f0 = float(np.median(force_n[:INIT_SAMPLES]))
    head = force_n[:NOISE_SAMPLES]
    noise = float(np.std(np.diff(head)) / np.sqrt(2.0)) if len(head) > 2 else 0.0
    return 0.0 if abs(f0) <= 3.0 * noise else f0


def simulate_batch(pt: PreparedTest, ps: np.ndarray) -> list[dict[str, np.ndarray]]:
    """Simulate a prepared test for each row of ``ps``."""
    ps = np.ascontiguousarray(np.atleast_2d(ps), dtype=np.float64)
    f0 = float(pt.inputs.get("initial_force_n", np.zeros(1))[0])
    raw = simulate_kernel(np.ascontiguousarray(pt.input_signal, dtype=np.float64),
                          np.ascontiguousarray(pt.input_rate, dtype=np.float64), ps, f0,
                          pt.dt_s)
    out = []
    for r in raw:
        d = {"friction_force_n": r[:, 0]}
        for i, name in enumerate(INTERNAL):
            d[f"internal.{name}"] = r[:, 1 + i]
        out.append(d)
    return out


def pre_identify(campaign: Campaign, tests: list[PreparedTest], p: np.ndarray) -> dict:
    """Starting values from the force levels and the slope after reversals.

    Slip level: half the span between the force's 3rd and 97th percentiles over the
    identification tests (their mean, where the levels differ, is left to discovery). Stiffness: the median slope dF/dx where
    the force is between a fifth and four fifths of the way from one level to the
    other — the band's elastic part of each reversal, away from any play.
    """
    out: dict = {"values": {}, "upper": {}, "notes": []}
    forces = [pt.raw["friction_force_n"] for pt in tests if "friction_force_n" in pt.raw]
    if not forces:
        out["notes"].append("no test with a friction force: start from the defaults")
        return out
    allf = np.concatenate(forces)
    lo, hi = np.percentile(allf, [3.0, 97.0])
    level, offset = max(0.5 * (hi - lo), 1.0), 0.5 * (hi + lo)
    slopes = []
    for pt in tests:
        if "friction_force_n" not in pt.raw:
            continue
        f = pt.raw["friction_force_n"] - offset
        df, dx = np.diff(f), np.diff(pt.input_signal)
        mid = (np.abs(f[1:]) < 0.8 * level) & (np.abs(f[1:]) > 0.2 * level) & (np.abs(dx) > 0)
        if np.any(mid):
            slopes.append(np.abs(df[mid] / dx[mid]))
    k = float(np.median(np.concatenate(slopes))) if slopes else PARAM_SPECS[I_K].default
    k = float(np.clip(k, PARAM_SPECS[I_K].lower, PARAM_SPECS[I_K].upper))
    out["values"] = {"band.coulomb_n": float(level), "band.stiffness_n_per_m": k}
    out["levels"] = {"percentile_3_n": float(lo), "percentile_97_n": float(hi),
                     "median_elastic_slope_n_per_m": k}
    return out
