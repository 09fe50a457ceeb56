"""The assist curve from measured points: motor current against the torque sensor.

With ``motor_current_a`` logged, every powered test measures the assist law
directly: ``N·k_m·i = A(T_tb) − c_ad·ω_sw`` (eps-model.md), with the
torsion-bar torque ``T_tb = T_sw − F_col(ω_sw)`` from the torque sensor. The
output-error fit instead compares the current with the twin's, whose
torsion-bar torque comes from the smoothed measured angle: its noise (errors
in variables, correlated over the smoothing window) moved the city curve's
slope at zero torque by −43 % on the compact powered bench.

Here both sides are measured, each with white sensor noise of known level,
and orthogonal distance regression (``odrpack``, ODRPACK95) weighs the error
in the torque as well as in the current. Every mode's curve and every speed's
active damping are fitted at once with what the points need beside them: the
column's Coulomb and viscous friction and the torque offset (on the torque
side: a 3 % error in the column's Coulomb term moved city c1 by 9 %) and the
current offset. The laws are the kernel's own (``assist_torque``, the column's
``friction``). The curves and dampings are then held: the cascade fits the
rest around them.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from odrpack import odr_fit
from scipy.optimize import least_squares

from mbst.core.filtering import white_noise_std
from mbst.systems.eps import assist as eps_assist
from mbst.systems.eps import kernel as K

CURRENT = "motor_current_a"
TORQUE = "steering_torque_nm"
# Samples where the steering wheel turns slower than this share of its peak rate are
# left out: there the column friction's sign is the smoothed rate's noise.
MOVING_SHARE = 0.05
# fewer moving samples than this and a test adds nothing to the regression
MIN_POINTS = 20
_COLUMN = ("steering_column.coulomb_nm", "steering_column.viscous_nms_per_rad",
           "offset.steering_torque_nm")


@dataclass
class BoostCurveFit:
    """Curves per mode from the measured points, with what was fitted beside them."""

    values: dict[str, float]
    std_error: dict[str, float]
    nuisance: dict[str, float]
    tests: list[str]
    noise: dict[str, float]
    method: str
    converged: bool
    points: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict, repr=False)

    def record(self) -> dict[str, Any]:
        """JSON-ready summary (params.json ``preidentification.boost_curve``)."""
        return {"method": self.method, "tests": self.tests, "values": self.values,
                "std_error": self.std_error, "fitted_beside": self.nuisance,
                "noise": self.noise, "converged": self.converged,
                "points": {m: int(len(t)) for m, (t, _) in self.points.items()}}


def _curve_param(mode: str, q: str) -> str:
    return f"assist.{q}" if mode == "default" else eps_assist.mode_param(mode, q)


def usable(pt: Any) -> bool:
    """A powered test that logs both the torque and the motor current."""
    return pt.spec.motor == "assist" and CURRENT in pt.raw and TORQUE in pt.raw


@dataclass(frozen=True)
class _Beta:
    """The regression's unknowns by name: a curve per mode, a damping per speed, and what
    is fitted beside them (the column's friction, the torque offset, the current offset
    in assist units)."""

    curves: np.ndarray  # (modes, curve coefficients)
    damping: np.ndarray  # per vehicle speed
    column_coulomb: float
    column_viscous: float
    torque_offset: float
    assist_offset: float


@dataclass
class _Points:
    """The moving samples of the usable tests, pooled: ``x`` rows are the measured torque,
    the rate, the mode index and the speed index; ``y`` the assist torque N·k_m·i."""

    x: np.ndarray
    y: np.ndarray
    modes: list[str]
    speeds: list[float | None]
    torque_noise: float
    assist_noise: float
    test_ids: list[str]

    @property
    def mode_of(self) -> np.ndarray:
        return self.x[2].astype(int)

    @property
    def speed_of(self) -> np.ndarray:
        return self.x[3].astype(int)


class _AssistLaw:
    """The kernel's own laws (one model definition): each (mode, speed) group runs on a
    vector with its curve and damping in the generic slots, as ``eps_assist.route`` does."""

    def __init__(self, pts: _Points, param_index: dict[str, int], p: np.ndarray,
                 family: str) -> None:
        self.qs = eps_assist.curve_names(family)
        self.shape = (len(self.qs), len(pts.modes), len(pts.speeds))
        self.n_gear = float(p[param_index["worm_gear_ratio"]])
        groups = sorted({(int(m), int(v))
                         for m, v in zip(pts.mode_of, pts.speed_of, strict=True)})
        self.masks = {g: (pts.mode_of == g[0]) & (pts.speed_of == g[1]) for g in groups}
        self.base = np.array(p, dtype=np.float64, copy=True)
        self.base[param_index["assist.family"]] = eps_assist.FAMILIES[family]
        self.slots = [param_index[f"assist.{q}"] for q in self.qs]
        self.i_cad, self.i_fc, self.i_visc = (
            param_index[n] for n in (f"assist.{eps_assist.DAMPING}", _COLUMN[0], _COLUMN[1]))

    def unpack(self, beta: np.ndarray) -> _Beta:
        nq, nm, ns = self.shape
        fc, visc, t_off, a_off = beta[nq * nm + ns:]
        return _Beta(beta[:nq * nm].reshape(nm, nq), beta[nq * nm:nq * nm + ns],
                     fc, visc, t_off, a_off)

    @staticmethod
    def torsion_bar_torque(torque: np.ndarray, w: np.ndarray, q: np.ndarray, t_off: float
                           ) -> np.ndarray:
        t = torque - t_off
        return t - K.column_friction_along(w, np.abs(t), q)

    def __call__(self, xx: np.ndarray, beta: np.ndarray) -> np.ndarray:
        b = self.unpack(beta)
        out = np.empty(xx.shape[1])
        for (m, v), sel in self.masks.items():
            q = self.base.copy()
            q[self.slots] = b.curves[m]
            q[self.i_cad], q[self.i_fc], q[self.i_visc] = (b.damping[v], b.column_coulomb,
                                                          b.column_viscous)
            w = np.ascontiguousarray(xx[1][sel])
            t_tb = self.torsion_bar_torque(xx[0][sel], w, q, b.torque_offset)
            out[sel] = self.n_gear * K.assist_torque_along(t_tb, w, q)
        return out + b.assist_offset


def _pool(used: list, gain: float) -> _Points | None:
    """The moving samples of every usable test (None: no test has enough)."""
    moving = {}
    for pt in used:
        w = np.abs(np.asarray(pt.omega_rad_per_s, float))
        keep = w > MOVING_SHARE * np.max(w) if len(w) else np.zeros(0, bool)
        if keep.sum() >= MIN_POINTS:
            moving[pt.id] = keep
    used = [pt for pt in used if pt.id in moving]
    if not used:
        return None
    modes = sorted({pt.spec.assist_mode or "default" for pt in used})
    # a test without a vehicle speed runs on the generic damping (eps_assist.route)
    speeds = sorted({pt.spec.vehicle_speed_kph for pt in used},
                    key=lambda v: (v is None, v or 0.0))
    cols, ys, sx, sy = [], [], [], []
    for pt in used:
        w = np.asarray(pt.omega_rad_per_s, float)
        keep = moving[pt.id]
        n = int(keep.sum())
        cols.append(np.vstack([
            pt.raw[TORQUE][keep], w[keep],
            np.full(n, modes.index(pt.spec.assist_mode or "default"), float),
            np.full(n, speeds.index(pt.spec.vehicle_speed_kph), float)]))
        ys.append(gain * pt.raw[CURRENT][keep])
        sx.append(white_noise_std(pt.raw[TORQUE], pt.dt_s))
        sy.append(gain * white_noise_std(pt.raw[CURRENT], pt.dt_s))
    x, y = np.hstack(cols), np.concatenate(ys)
    return _Points(x, y, modes, speeds,
                   max(float(np.mean(sx)), 1e-6 * max(float(np.ptp(x[0])), 1e-9)),
                   max(float(np.mean(sy)), 1e-6 * max(float(np.ptp(y)), 1e-9)),
                   [pt.id for pt in used])


def fit_boost_curve(tests: list, param_index: dict[str, int], p: np.ndarray,
                    family: str = "eps") -> BoostCurveFit | None:
    """Fit the assist curve of every mode and the damping of every speed the tests cover.

    Parameters
    ----------
    tests
        Prepared identification tests; those that are powered and log
        ``motor_current_a`` and ``steering_torque_nm`` are used (raw channels).
    param_index, p
        The campaign model's parameter layout and the values to start from
        (known gear ratio and torque constant; column friction and offsets).
    family
        ``eps`` (c1, c2, c3) or ``hps`` (c1).

    Returns
    -------
    BoostCurveFit or None
        None when no test qualifies.
    """
    used = [pt for pt in tests if usable(pt)]
    if not used:
        return None
    gain = float(p[param_index["worm_gear_ratio"]]) * float(
        p[param_index["motor_torque_constant_nm_per_a"]])
    pts = _pool(used, gain)
    if pts is None:
        return None
    law = _AssistLaw(pts, param_index, p, family)
    nq, nm, ns = law.shape
    lo = np.r_[np.tile([0.0, 0.0, 1.0][:nq], nm), np.zeros(ns), 0.0, 0.0, -5.0, -50.0]
    hi = np.r_[np.tile([20.0, 20.0, 4.0][:nq], nm), np.ones(ns), 1.0, 0.2, 5.0, 50.0]
    beta0 = np.clip(np.r_[np.tile([1.0, 0.5, 2.0][:nq], nm), np.zeros(ns),
                          [float(p[param_index[n]]) for n in _COLUMN], 0.0],
                    lo + 1e-9, hi - 1e-9)
    # a start from the current's side alone (least squares): from the bounds the ODR
    # stalled with the damping at zero
    beta0 = least_squares(lambda b: law(pts.x, b) - pts.y, beta0, bounds=(lo, hi),
                          x_scale="jac").x
    beta0 = np.clip(beta0, lo + 1e-6 * (hi - lo), hi - 1e-6 * (hi - lo))
    # only the torque has an error; rate, mode and speed are exact
    fit = odr_fit(law, pts.x, pts.y, beta0, bounds=(lo, hi),
                  weight_x=np.array([pts.torque_noise ** -2, 1.0, 1.0, 1.0]),
                  weight_y=pts.assist_noise ** -2, fix_x=np.array([False, True, True, True]),
                  maxit=200)
    method = "orthogonal distance regression (odrpack)"
    if not fit.success:
        method += f", {fit.stopreason}"
    return _record(law, pts, fit, gain, method)


def _record(law: _AssistLaw, pts: _Points, fit: Any, gain: float,
            method: str) -> BoostCurveFit:
    """The fitted values by parameter name, with their standard errors and the points."""
    nq, nm, _ = law.shape
    b, sd = law.unpack(fit.beta), fit.sd_beta
    values, std = {}, {}
    for k, mode in enumerate(pts.modes):
        for j, q in enumerate(law.qs):
            values[_curve_param(mode, q)] = float(b.curves[k, j])
            std[_curve_param(mode, q)] = float(sd[k * nq + j])
    for j, v in enumerate(pts.speeds):
        name = eps_assist.speed_param(v) if v is not None else f"assist.{eps_assist.DAMPING}"
        values[name] = float(b.damping[j])
        std[name] = float(sd[nq * nm + j])
    values["offset.motor_current_a"] = float(b.assist_offset / gain)
    nuisance = {n: float(v) for n, v in
                zip(_COLUMN, (b.column_coulomb, b.column_viscous, b.torque_offset))}
    q = law.base.copy()
    q[law.i_fc], q[law.i_visc] = b.column_coulomb, b.column_viscous
    points = {}
    for k, mode in enumerate(pts.modes):
        sel = pts.mode_of == k
        w = np.ascontiguousarray(pts.x[1][sel])
        t_tb = law.torsion_bar_torque(pts.x[0][sel], w, q, b.torque_offset)
        a = pts.y[sel] - b.assist_offset + b.damping[pts.speed_of[sel]] * w
        points[mode] = (t_tb, a)
    return BoostCurveFit(values, std, nuisance, pts.test_ids,
                         {"torque_nm": pts.torque_noise, "assist_nm": pts.assist_noise},
                         method, bool(fit.success), points)
