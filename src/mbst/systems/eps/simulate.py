"""Front-end of the EPS model: initial state, sub-stepping, sensors.

``simulate`` is what identification, discovery and the bench call; ``rhs_for``
exposes the same equations as ``f(t, x)`` for scipy's solvers.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from mbst.core.filtering import angular_velocity, exponential_filter
from mbst.systems.eps import kernel as K
from mbst.systems.eps.params import (
    N_PARAMS,
    PARAM_INDEX,
    TORQUE_SENSOR_LAG,
    friction_param,
    rack_is_separate_body,
    vector_from,
)

# h·ω_max below this keeps the symplectic step stable (limit 2) and accurate
_H_OMEGA = 1.4
H_MAX_S = 5e-4

SENSOR_OFFSETS = {
    "steering_torque_nm": "offset.steering_torque_nm",
    "rack_position_m": "offset.rack_position_m",
    "tie_rod_force_left_n": "offset.tie_rod_force_left_n",
    "tie_rod_force_right_n": "offset.tie_rod_force_right_n",
    "motor_angle_rad": "offset.motor_angle_rad",
    "motor_current_a": "offset.motor_current_a",
}


def as_vector(params: np.ndarray | dict[str, float]) -> np.ndarray:
    if isinstance(params, dict):
        return vector_from(params)
    p = np.asarray(params, dtype=np.float64)
    if p.shape != (N_PARAMS,):
        raise ValueError(f"parameter vector must have length {N_PARAMS}, got {p.shape}")
    return p


def max_mode_rad_per_s(p: np.ndarray, scenario: str) -> float:
    """Fastest linear mode of the springs and explicit dampers (for the step size)."""
    g = lambda name: p[PARAM_INDEX[name]]
    r, n = g("pinion_radius_m"), g("worm_gear_ratio")
    jp, jm = g("column_inertia_kgm2"), g("motor_inertia_kgm2") * n * n
    if rack_is_separate_body(g("rack_pinion.backlash.width_rad")):
        jr = g("rack_pinion.rack_mass_kg") * r * r
        jp = max(jp - jr, 0.1 * jp)
    else:
        jr = None
    kt = g("torsion_bar.stiffness_nm_per_rad") * max(
        g("torsion_bar.stiffness_limit_stop.stiffness_ratio"), 1.0
    )
    rates = [math.sqrt(kt / jp)]
    if scenario != "blocked_column":
        kg = g("worm_gear.stiffness_nm_per_rad")
        rates.append(math.sqrt(kg * (1 / jp + 1 / jm)))
        rates.append(g("worm_gear.damping_nms_per_rad") * (1 / jp + 1 / jm))
        if jr is not None:
            krp = g("rack_pinion.mesh_stiffness_nm_per_rad")
            rates.append(math.sqrt(krp * (1 / jp + 1 / jr)))
        if scenario in ("blocked_rack", "suspended", "tires_on_ground"):
            m_rack = jr / (r * r) if jr is not None else jp / (r * r)
            ktr = g("tie_rods.stiffness_n_per_m")
            m_w = g("wheel_mass_kg") if scenario != "blocked_rack" else math.inf
            rates.append(math.sqrt(ktr * (1 / m_rack + 1 / m_w)))
            rates.append(g("tie_rods.damping_ns_per_m") * (1 / m_rack + 1 / m_w))
    return max(rates)


# dry friction between two moving bodies (tie-rods) is split Gauss–Seidel: first order in h
H_TIE_ROD_FRICTION_S = 6e-5


def _stribeck_limit_s(p: np.ndarray, scenario: str) -> float:
    """Largest h that keeps m/h above the Stribeck dip's negative slope.

    Beyond it the implicit friction equation has several roots and the stick
    -slip timing depends on h.
    """
    g = lambda name: p[PARAM_INDEX[name]]
    r = g("pinion_radius_m")
    rack_body = rack_is_separate_body(g("rack_pinion.backlash.width_rad"))
    masses = {
        "steering_column": math.inf,  # acts on the measured angle: no body
        "motor": g("motor_inertia_kgm2"),
        "rack": g("rack_pinion.rack_mass_kg") if rack_body else g("column_inertia_kgm2") / r**2,
        "tires": g("wheel_mass_kg"),
    }
    h = math.inf
    for elem, m in masses.items():
        ratio = g(friction_param(elem, "stribeck_friction.static_to_coulomb_ratio"))
        if ratio <= 1.0 or not math.isfinite(m):
            continue
        if elem == "tires" and scenario not in ("suspended", "tires_on_ground"):
            continue
        unit = "nm" if elem in ("steering_column", "motor") else "n"
        fc = g(f"{elem}.coulomb_{unit}")
        vs = g(friction_param(elem, "stribeck_friction.stribeck_velocity"))
        slope = 0.858 * fc * (ratio - 1.0) / vs  # max |d/dv| of the exponential dip
        h = min(h, 0.5 * m / slope)
    return h


def substeps(p: np.ndarray, scenario: str, dt: float) -> int:
    """Sub-steps per sample.

    h ≤ H_MAX_S, h·ω_max ≤ 1.4 (symplectic Euler is stable below 2), h below
    the Stribeck limit, and h ≤ H_TIE_ROD_FRICTION_S with tie-rod dry friction.
    """
    h = min(H_MAX_S, _H_OMEGA / max_mode_rad_per_s(p, scenario), _stribeck_limit_s(p, scenario))
    if p[PARAM_INDEX["tie_rods.coulomb_friction.level"]] > 0 and scenario in (
        "blocked_rack", "suspended", "tires_on_ground"
    ):
        h = min(h, H_TIE_ROD_FRICTION_S)
    return max(1, math.ceil(dt / h - 1e-9))


def initial_state(p: np.ndarray, scenario: str, theta0: float) -> np.ndarray:
    """Static equilibrium of the linear springs at the first measured angle.

    Friction is ignored (its state at t=0 is unknown); meshes sit centred in
    their backlash, Dahl states at zero.
    """
    g = lambda name: p[PARAM_INDEX[name]]
    x = np.zeros(K.N_STATES)
    if scenario == "blocked_column":
        return x
    r, n, kt = g("pinion_radius_m"), g("worm_gear_ratio"), g("torsion_bar.stiffness_nm_per_rad")
    ktr, kw = g("tie_rods.stiffness_n_per_m"), g("tires.centring_stiffness_n_per_m")
    if scenario == "blocked_rack":
        k_rack = ktr
    elif scenario == "tires_on_ground":
        k_rack = ktr * kw / (ktr + kw)
    else:
        k_rack = 0.0
    thp = kt * theta0 / (kt + k_rack * r * r)
    xr = r * thp
    x[K.S_THP] = thp
    x[K.S_THM] = n * thp
    x[K.S_XR] = xr
    if scenario == "tires_on_ground":
        x[K.S_XW] = ktr * xr / (ktr + kw)
    elif scenario == "suspended":
        x[K.S_XW] = xr
    return x


def scenario_codes(scenario: str, motor: str) -> tuple[int, int]:
    try:
        return K.SCENARIO_CODES[scenario], K.MOTOR_CODES[motor]
    except KeyError as exc:
        raise ValueError(f"unknown scenario or motor mode: {exc}") from None


def simulate_raw(
    scenario: str,
    motor: str,
    time_s: np.ndarray,
    angle_rad: np.ndarray,
    params: np.ndarray | dict[str, float],
    angular_velocity_rad_per_s: np.ndarray | None = None,
    n_sub: int | None = None,
) -> np.ndarray:
    """Model outputs (N, N_OUTPUTS) without sensor offsets; see ``eps_kernel.OUTPUT_NAMES``."""
    p = as_vector(params)
    t = np.ascontiguousarray(time_s, dtype=np.float64)
    th = np.ascontiguousarray(angle_rad, dtype=np.float64)
    om = (
        angular_velocity(t, th)
        if angular_velocity_rad_per_s is None
        else np.ascontiguousarray(angular_velocity_rad_per_s, dtype=np.float64)
    )
    dt = float((t[-1] - t[0]) / (len(t) - 1))
    scen, mode = scenario_codes(scenario, motor)
    ns = substeps(p, scenario, dt) if n_sub is None else int(n_sub)
    x0 = initial_state(p, scenario, float(th[0]))
    return K.simulate_dt(th, om, p, scen, mode, ns, x0, dt)


def simulate_raw_batch(
    scenario: str,
    motor: str,
    angle_rad: np.ndarray,
    angular_velocity_rad_per_s: np.ndarray,
    ps: np.ndarray,
    dt_s: float,
    n_sub: int | None = None,
) -> np.ndarray:
    """Raw outputs (B, N, N_OUTPUTS) of many parameter vectors on one input (numba prange).

    The step is the finest any of the vectors needs unless ``n_sub`` is given.
    """
    ps = np.ascontiguousarray(np.atleast_2d(ps), dtype=np.float64)
    scen, mode = scenario_codes(scenario, motor)
    ns = max(substeps(p, scenario, dt_s) for p in ps) if n_sub is None else int(n_sub)
    x0s = np.stack([initial_state(p, scenario, float(angle_rad[0])) for p in ps])
    return K.simulate_batch(np.ascontiguousarray(angle_rad, dtype=np.float64),
                            np.ascontiguousarray(angular_velocity_rad_per_s, dtype=np.float64),
                            ps, scen, mode, ns, x0s, dt_s)


def sensors_from_raw(raw: np.ndarray, p: np.ndarray, scenario: str, dt_s: float = 0.0
                     ) -> dict[str, np.ndarray]:
    """Sensor channels (with campaign-wide offsets) from raw model outputs; with the sample
    period ``dt_s``, the torque sensor's own lag where the vector sets one."""
    g = lambda name: p[PARAM_INDEX[name]]
    half_tie = 0.5 * raw[:, K.O_FTIE]
    out = {
        "steering_torque_nm": raw[:, K.O_TORQUE],
        "rack_position_m": raw[:, K.O_RACK],
        "tie_rod_force_left_n": half_tie,
        "tie_rod_force_right_n": half_tie.copy(),
        "motor_angle_rad": raw[:, K.O_THM],
        "motor_current_a": raw[:, K.O_TM] / g("motor_torque_constant_nm_per_a"),
    }
    if dt_s > 0.0 and g(TORQUE_SENSOR_LAG) > 0.0:
        out["steering_torque_nm"] = exponential_filter(out["steering_torque_nm"], dt_s,
                                                       g(TORQUE_SENSOR_LAG))
    for ch, name in SENSOR_OFFSETS.items():
        out[ch] = out[ch] + g(name)
    return out


def simulate(
    scenario: str,
    motor: str,
    time_s: np.ndarray,
    angle_rad: np.ndarray,
    params: np.ndarray | dict[str, float],
    angular_velocity_rad_per_s: np.ndarray | None = None,
    n_sub: int | None = None,
) -> dict[str, np.ndarray]:
    """Simulate one test of the EPS rig driven by the measured steering angle.

    Parameters
    ----------
    scenario, motor
        Names from eps-model.md (``free_tie_rods``…, ``passive``/``assist``).
    time_s, angle_rad
        Uniformly sampled time and measured steering-wheel angle.
    params
        Full parameter vector or a dict of named values over the defaults.
    angular_velocity_rad_per_s
        Rate of the angle; central differences of ``angle_rad`` if omitted.
    n_sub
        Sub-steps per sample; chosen from the stiffest mode if omitted.

    Returns
    -------
    dict
        Sensor channels (campaign-format names, offsets applied) plus the
        internal signals of ``eps_kernel.OUTPUT_NAMES`` under ``internal.*``.
    """
    p = as_vector(params)
    raw = simulate_raw(scenario, motor, time_s, angle_rad, p, angular_velocity_rad_per_s, n_sub)
    out = sensors_from_raw(raw, p, scenario, float(time_s[1] - time_s[0]) if len(time_s) > 1
                           else 0.0)
    for i, name in enumerate(K.OUTPUT_NAMES):
        out[f"internal.{name}"] = raw[:, i]
    return out


def rhs_for(
    scenario: str,
    motor: str,
    time_s: np.ndarray,
    angle_rad: np.ndarray,
    params: np.ndarray | dict[str, float],
    angular_velocity_rad_per_s: np.ndarray | None = None,
) -> tuple[Callable[[float, np.ndarray], np.ndarray], np.ndarray]:
    """``f(t, x)`` and ``x0`` of the same model, for ``scipy.integrate.solve_ivp``.

    The input is interpolated linearly between samples, as in ``simulate``.
    """
    p = as_vector(params)
    t = np.asarray(time_s, dtype=np.float64)
    th = np.asarray(angle_rad, dtype=np.float64)
    om = angular_velocity(t, th) if angular_velocity_rad_per_s is None else np.asarray(
        angular_velocity_rad_per_s, dtype=np.float64
    )
    scen, mode = scenario_codes(scenario, motor)

    def f(tt: float, x: np.ndarray) -> np.ndarray:
        dx = np.empty(K.N_STATES)
        K.rhs(x, np.interp(tt, t, th), np.interp(tt, t, om), p, scen, mode, dx)
        return dx

    return f, initial_state(p, scenario, float(th[0]))


def outputs_along(
    scenario: str,
    motor: str,
    time_s: np.ndarray,
    angle_rad: np.ndarray,
    states: np.ndarray,
    params: np.ndarray | dict[str, float],
    angular_velocity_rad_per_s: np.ndarray | None = None,
) -> dict[str, np.ndarray]:
    """Sensor channels along a state trajectory (N, N_STATES) from any solver."""
    p = as_vector(params)
    t = np.asarray(time_s, dtype=np.float64)
    th = np.asarray(angle_rad, dtype=np.float64)
    om = angular_velocity(t, th) if angular_velocity_rad_per_s is None else np.asarray(
        angular_velocity_rad_per_s, dtype=np.float64
    )
    scen, mode = scenario_codes(scenario, motor)
    raw = np.empty((len(t), K.N_OUTPUTS))
    force, aux, row = np.zeros(4), np.zeros(7), np.empty(K.N_OUTPUTS)
    for i in range(len(t)):
        K.outputs(np.ascontiguousarray(states[i]), th[i], om[i], p, scen, mode, force, aux, row)
        raw[i] = row
    return sensors_from_raw(raw, p, scenario, float(t[1] - t[0]) if len(t) > 1 else 0.0)
