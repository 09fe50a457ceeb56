"""Compiled right-hand side and fixed-step integrator of the EPS model.

This is the only place where the equations of eps-model.md are written down.
``rhs`` (for scipy's solvers and for discovery) and ``step`` (the fast
integrator) both call the same force functions ``_loads`` and
``_body_friction``.

Integration scheme: semi-implicit Euler with implicit friction. The
regularised friction laws are very stiff (rack: F_c/v_eps ≈ 1e7 N·s/m, so an
explicit step would need < 1 µs), but each friction element acts on one body
velocity. Per sub-step every body's velocity is solved from
``m/h·(v − v*) + F_fric(v) = 0`` (scalar, monotone: safeguarded Newton) in
Gauss–Seidel order, springs and dampers stay explicit, positions follow the
new velocities (symplectic), and Dahl states take the exact exponential step
for the frozen velocity. Stability then only needs h·ω_max ≲ 1 for the mesh
and tie-rod modes, which the front-end enforces by sub-stepping.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from mbst.systems.eps.params import (
    DAHL_BLEND_DECADES,
    FB_ASYM,
    FB_EXP,
    FB_LOAD,
    FB_SIGMA,
    FB_STATIC,
    FB_VEPS,
    FB_VSTRIB,
    PARAM_INDEX,
    RIGID_RACK_MESH_BELOW_RAD,
    dahl_stiffest,
    friction_base,
)

# ---- scenario and motor codes -------------------------------------------------------
BLOCKED_COLUMN, FREE_TIE_RODS, BLOCKED_RACK, SUSPENDED, TIRES_ON_GROUND = 0, 1, 2, 3, 4
SCENARIO_CODES = {
    "blocked_column": BLOCKED_COLUMN,
    "free_tie_rods": FREE_TIE_RODS,
    "blocked_rack": BLOCKED_RACK,
    "suspended": SUSPENDED,
    "tires_on_ground": TIRES_ON_GROUND,
}
PASSIVE, ASSIST = 0, 1
MOTOR_CODES = {"passive": PASSIVE, "assist": ASSIST}

# ---- state layout -------------------------------------------------------------------
S_THP, S_WP, S_THM, S_WM, S_XR, S_VR, S_XW, S_VW, S_ZCOL, S_ZMOT, S_ZRACK, S_ZTIRE = range(12)
N_STATES = 12
STATE_NAMES = (
    "pinion_angle_rad", "pinion_speed_rad_per_s", "motor_angle_rad", "motor_speed_rad_per_s",
    "rack_body_position_m", "rack_body_speed_m_per_s", "wheel_position_m", "wheel_speed_m_per_s",
    "column_dahl_nm", "motor_dahl_nm", "rack_dahl_n", "tires_dahl_n",
)

# ---- model outputs (before sensor offsets) ------------------------------------------
(O_TORQUE, O_RACK, O_FTIE, O_THM, O_TM, O_THP, O_XW, O_PHI, O_TTB, O_VR, O_WM,
 O_FCOL) = range(12)
N_OUTPUTS = 12
OUTPUT_NAMES = (
    "steering_torque_nm", "rack_position_m", "tie_rod_force_total_n", "motor_angle_rad",
    "motor_torque_nm", "pinion_angle_rad", "wheel_position_m", "worm_gear_mesh_angle_rad",
    "torsion_bar_torque_nm", "rack_speed_m_per_s", "motor_speed_rad_per_s",
    "column_friction_nm",
)

# ---- parameter indices (compile-time constants for numba) ---------------------------
P_RP = PARAM_INDEX["pinion_radius_m"]
P_N = PARAM_INDEX["worm_gear_ratio"]
P_JP = PARAM_INDEX["column_inertia_kgm2"]
P_JM = PARAM_INDEX["motor_inertia_kgm2"]
P_MW = PARAM_INDEX["wheel_mass_kg"]
P_KT = PARAM_INDEX["torsion_bar.stiffness_nm_per_rad"]
P_KG = PARAM_INDEX["worm_gear.stiffness_nm_per_rad"]
P_CG = PARAM_INDEX["worm_gear.damping_nms_per_rad"]
P_KTR = PARAM_INDEX["tie_rods.stiffness_n_per_m"]
P_CTR = PARAM_INDEX["tie_rods.damping_ns_per_m"]
P_KW = PARAM_INDEX["tires.centring_stiffness_n_per_m"]
P_BRG_FC = PARAM_INDEX["tires.bearing_coulomb_n"]
P_BRG_B = PARAM_INDEX["tires.bearing_viscous_ns_per_m"]
P_WGW = PARAM_INDEX["worm_gear.backlash.width_rad"]
P_RPW = PARAM_INDEX["rack_pinion.backlash.width_rad"]
P_KRP = PARAM_INDEX["rack_pinion.mesh_stiffness_nm_per_rad"]
P_MR = PARAM_INDEX["rack_pinion.rack_mass_kg"]
P_ZRP = PARAM_INDEX["rack_pinion.mesh_damping_ratio"]
P_BUMP_X = PARAM_INDEX["rack.position_dependent_friction.position_m"]
P_BUMP_A = PARAM_INDEX["rack.position_dependent_friction.amplitude"]
P_BUMP_W = PARAM_INDEX["rack.position_dependent_friction.width_m"]
P_STOP = PARAM_INDEX["torsion_bar.stiffness_limit_stop.stop_angle_rad"]
P_STOPR = PARAM_INDEX["torsion_bar.stiffness_limit_stop.stiffness_ratio"]
P_TRF = PARAM_INDEX["tie_rods.coulomb_friction.level"]
P_TRF_VEPS = PARAM_INDEX["tie_rods.regularisation_velocity_m_per_s"]
P_COG_A = PARAM_INDEX["motor.cogging_torque_nm"]
P_COG_B = PARAM_INDEX["motor.cogging_cos_torque_nm"]
P_VRATIO = PARAM_INDEX["rack_pinion.ratio_variation_per_rad2"]
P_COG_N = PARAM_INDEX["motor.cogging_periods_per_rev"]
P_AFAM = PARAM_INDEX["assist.family"]
P_C1 = PARAM_INDEX["assist.c1"]
P_C2 = PARAM_INDEX["assist.c2"]
P_C3 = PARAM_INDEX["assist.c3"]
P_CAD = PARAM_INDEX["assist.active_damping_nms_per_rad"]
B_COL = friction_base("steering_column")
B_MOT = friction_base("motor")
B_RACK = friction_base("rack")
B_TIRE = friction_base("tires")
SIGMA_TOP_COL = dahl_stiffest("steering_column")
SIGMA_TOP_MOT = dahl_stiffest("motor")
SIGMA_TOP_RACK = dahl_stiffest("rack")
SIGMA_TOP_TIRE = dahl_stiffest("tires")

# bodies in Gauss–Seidel order
BODY_PINION, BODY_MOTOR, BODY_RACK, BODY_WHEEL = 0, 1, 2, 3

_JIT = {"cache": True, "nogil": True, "error_model": "numpy"}


# ---- elementary laws ----------------------------------------------------------------
@njit(**_JIT)
def dead_zone(phi, width):
    """Mesh deflection beyond a dead zone of total width ``width``."""
    hw = 0.5 * width
    if phi > hw:
        return phi - hw
    if phi < -hw:
        return phi + hw
    return 0.0


@njit(**_JIT)
def torsion_bar_torque(theta_tb, p):
    """Torsion-bar torque with the optional bilinear limit stop (seed 001)."""
    k = p[P_KT]
    ratio = p[P_STOPR]
    stop = p[P_STOP]
    a = abs(theta_tb)
    if ratio == 1.0 or a <= stop:
        return k * theta_tb
    s = 1.0 if theta_tb > 0 else -1.0
    return s * (k * stop + k * ratio * (a - stop))


@njit(**_JIT)
def coulomb_level(p, b, fc0, v, load, pos_factor):
    """Direction-dependent Coulomb level and its velocity derivative."""
    fc = (fc0 + p[b + FB_LOAD] * load) * pos_factor
    r = p[b + FB_ASYM]
    if r != 1.0:
        fc *= (2.0 * r / (1.0 + r)) if v >= 0.0 else (2.0 / (1.0 + r))
    rs = p[b + FB_STATIC]
    if rs != 1.0:
        vs = p[b + FB_VSTRIB]
        e = math.exp(-(v / vs) ** 2)
        return fc * (1.0 + (rs - 1.0) * e), fc * (rs - 1.0) * e * (-2.0 * v / (vs * vs))
    return fc, 0.0


@njit(**_JIT)
def tanh_coulomb(p, b, fc0, v, load, pos_factor):
    """The regularised Coulomb force F_c(v)·tanh(v/v_ε) of element ``b`` and its dF/dv."""
    lvl, dlvl = coulomb_level(p, b, fc0, v, load, pos_factor)
    veps = p[b + FB_VEPS]
    th = math.tanh(v / veps)
    return th * lvl, (1.0 - th * th) / veps * lvl + th * dlvl


@njit(**_JIT)
def stiff_share(p, b):
    """Share of friction element ``b``'s force that is its stiff-end law (the base's tanh
    Coulomb): 1 without presliding (σ = 0), 0 for a Dahl state below the top
    ``DAHL_BLEND_DECADES`` of its searched stiffness, a smooth step in log σ across them.

    The Dahl state tends to that law as σ grows but lags it where the velocity crosses
    zero (its rate σ|v|/F_c vanishes there); the blend makes the stiffest presliding the
    base model exactly, so the candidate nests the base at its neutral start.
    """
    sigma = p[b + FB_SIGMA]
    if sigma <= 0.0:
        return 1.0
    if b == B_COL:
        top = SIGMA_TOP_COL
    elif b == B_MOT:
        top = SIGMA_TOP_MOT
    elif b == B_RACK:
        top = SIGMA_TOP_RACK
    else:
        top = SIGMA_TOP_TIRE
    x = 1.0 + math.log10(sigma / top) / DAHL_BLEND_DECADES
    if x <= 0.0:
        return 0.0
    if x >= 1.0:
        return 1.0
    return x * x * (3.0 - 2.0 * x)


@njit(**_JIT)
def stiff_end_blend(p, b, fc0, v, z, load, pos_factor):
    """What the stiff-end blend adds to a presliding element's force ``z`` (``friction``
    with σ > 0 gives the Dahl state alone) and its derivative, with ``z`` held."""
    w = stiff_share(p, b)
    if w <= 0.0:
        return 0.0, 0.0
    f, df = tanh_coulomb(p, b, fc0, v, load, pos_factor)
    return w * (f - z), w * df


@njit(**_JIT)
def friction(p, b, fc0, bv, v, z, load, pos_factor):
    """Force of friction element ``b`` at velocity ``v`` and its derivative.

    Smooth Coulomb (or the Dahl state ``z`` when the element has presliding
    hysteresis; ``stiff_end_blend`` adds what its stiff end blends in) plus viscous or
    power-law damping.
    """
    veps = p[b + FB_VEPS]
    if p[b + FB_SIGMA] > 0.0:
        f, df = z, 0.0
    else:
        f, df = tanh_coulomb(p, b, fc0, v, load, pos_factor)
    a = p[b + FB_EXP]
    if a == 1.0:
        return f + bv * v, df + bv
    av = abs(v)
    th = math.tanh(v / veps)
    pw = av**a
    dpw = a * av ** (a - 1.0) * abs(th) if av > 0.0 else 0.0
    return f + bv * th * pw, df + bv * ((1.0 - th * th) / veps * pw + dpw)


@njit(**_JIT)
def dahl_rate(p, b, fc0, v, z, load, pos_factor):
    """dz/dt of the Dahl model: σ·|v|·(F_c·tanh(v/v_ε) − z)/F_c.

    eps-model.md's σ·v·(1 − z/F_c·sign(v)) with sign(v) regularised as the base
    model's Coulomb term is (``friction``): outside |v| ≲ v_ε the two are equal; the
    stiff end (σ → ∞, z → F_c·tanh(v/v_ε)) is then the base model itself, so the
    presliding candidate nests the base, and a stiff state does not chatter between
    ±F_c at standstill (a sharp sign left the rack's stiffest Dahl 23 % above the base
    on a realistic bench, which no refit could undo).
    """
    sigma = p[b + FB_SIGMA]
    if sigma <= 0.0 or v == 0.0:
        return 0.0
    lvl, _ = coulomb_level(p, b, fc0, v, load, pos_factor)
    lvl = max(lvl, 1e-12)
    return sigma * abs(v) * (lvl * math.tanh(v / p[b + FB_VEPS]) - z) / lvl


@njit(**_JIT)
def dahl_step(p, b, fc0, v, z, load, pos_factor, h):
    """Exact step of the Dahl state for a velocity frozen over ``h``."""
    sigma = p[b + FB_SIGMA]
    if sigma <= 0.0 or v == 0.0:
        return z
    lvl, _ = coulomb_level(p, b, fc0, v, load, pos_factor)
    lvl = max(lvl, 1e-12)
    zs = lvl * math.tanh(v / p[b + FB_VEPS])  # the regularised target (``dahl_rate``)
    return zs + (z - zs) * math.exp(-sigma * abs(v) * h / lvl)


@njit(**_JIT)
def assist_torque(t_tb, om_sw, p):
    """Motor torque (motor side) of the power-assist law."""
    s = 1.0 if t_tb > 0 else (-1.0 if t_tb < 0 else 0.0)
    if p[P_AFAM] == 0.0:
        a = p[P_C1] * t_tb + p[P_C2] * s * abs(t_tb) ** p[P_C3]
    else:
        a = p[P_C1] * s * (math.exp(abs(t_tb)) - 1.0)
    return (a - p[P_CAD] * om_sw) / p[P_N]


@njit(**_JIT)
def cogging_torque(theta_m, p):
    """The motor's detent torque, periodic in its angle (not in the catalogue: the bench
    plants it, discovery refits it to describe a ripple it reads)."""
    a, b = p[P_COG_A], p[P_COG_B]
    if a == 0.0 and b == 0.0:
        return 0.0
    x = p[P_COG_N] * theta_m
    return a * math.sin(x) + b * math.cos(x)


@njit(**_JIT)
def column_friction_along(om_sw, load, p):
    """The column's friction F_col(ω_sw) along a record (the law without a Dahl state).

    What the measured torque carries above the torsion bar: the measured-points
    regression of the assist (``eps_boost_curve``) takes it off with this law.
    """
    out = np.empty(om_sw.shape[0])
    for i in range(om_sw.shape[0]):
        out[i] = friction(p, B_COL, p[B_COL], p[B_COL + 1], om_sw[i], 0.0, load[i], 1.0)[0]
    return out


@njit(**_JIT)
def assist_torque_along(t_tb, om_sw, p):
    """``assist_torque`` along a record (motor side)."""
    out = np.empty(t_tb.shape[0])
    for i in range(t_tb.shape[0]):
        out[i] = assist_torque(t_tb[i], om_sw[i], p)
    return out


# ---- the model ----------------------------------------------------------------------
@njit(**_JIT)
def rack_is_body(p):
    return p[P_RPW] > RIGID_RACK_MESH_BELOW_RAD


@njit(**_JIT)
def wheels_move(scen):
    return scen == SUSPENDED or scen == TIRES_ON_GROUND


@njit(**_JIT)
def tie_rods_connected(scen):
    return scen == BLOCKED_RACK or scen == SUSPENDED or scen == TIRES_ON_GROUND


@njit(**_JIT)
def body_mass(body, p):
    if body == BODY_PINION:
        if rack_is_body(p):
            r = p[P_RP]
            return max(p[P_JP] - p[P_MR] * r * r, 0.1 * p[P_JP])
        return p[P_JP]
    if body == BODY_MOTOR:
        return p[P_JM]
    if body == BODY_RACK:
        return p[P_MR]
    return p[P_MW]


@njit(**_JIT)
def pinion_ratio(theta_p, p):
    """The rack's travel per pinion radian: the pinion radius, or on a variable-ratio rack
    (bench only, not in the catalogue) r·(1 + a·θ²)."""
    a = p[P_VRATIO]
    if a == 0.0:
        return p[P_RP]
    return p[P_RP] * (1.0 + a * theta_p * theta_p)


@njit(**_JIT)
def pinion_rack_position(theta_p, p):
    """The rigid rack's position at pinion angle θ: ∫ pinion_ratio dθ."""
    a = p[P_VRATIO]
    if a == 0.0:
        return p[P_RP] * theta_p
    return p[P_RP] * (theta_p + a * theta_p ** 3 / 3.0)


@njit(**_JIT)
def rack_kinematics(x, p):
    """Rack position and speed: its own body with rack-pinion backlash, else rigid."""
    if rack_is_body(p):
        return x[S_XR], x[S_VR]
    return pinion_rack_position(x[S_THP], p), pinion_ratio(x[S_THP], p) * x[S_WP]


@njit(**_JIT)
def _loads(x, th_sw, om_sw, p, scen, mode, force, aux):
    """Non-friction generalised forces on the bodies, and auxiliary signals.

    force: [pinion torque, motor torque, rack force, wheel force]
    aux:   [T_tb, T_m, F_tie (springs/dampers), mesh angle, rack x, rack v, load]
    """
    r = p[P_RP]
    n = p[P_N]
    if scen == BLOCKED_COLUMN:
        t_tb = torsion_bar_torque(th_sw, p)
        force[0] = 0.0
        force[1] = 0.0
        force[2] = 0.0
        force[3] = 0.0
        aux[0] = t_tb
        aux[1] = 0.0
        aux[2] = 0.0
        aux[3] = 0.0
        aux[4] = 0.0
        aux[5] = 0.0
        aux[6] = abs(t_tb)
        return
    t_tb = torsion_bar_torque(th_sw - x[S_THP], p)
    # worm-gear mesh (column side), damping only while teeth are in contact
    phi = x[S_THM] / n - x[S_THP]
    dphi = x[S_WM] / n - x[S_WP]
    w = p[P_WGW]
    t_g = p[P_KG] * dead_zone(phi, w)
    if w == 0.0 or abs(phi) > 0.5 * w:
        t_g += p[P_CG] * dphi
    t_m = assist_torque(t_tb, om_sw, p) if mode == ASSIST else 0.0
    xr, vr = rack_kinematics(x, p)
    if scen == BLOCKED_RACK:
        f_tie = p[P_KTR] * xr + p[P_CTR] * vr
    elif wheels_move(scen):
        f_tie = p[P_KTR] * (xr - x[S_XW]) + p[P_CTR] * (vr - x[S_VW])
    else:
        f_tie = 0.0
    if rack_is_body(p):
        psi = x[S_THP] - xr / r
        dpsi = x[S_WP] - vr / r
        wr = p[P_RPW]
        t_rp = p[P_KRP] * dead_zone(psi, wr)
        if abs(psi) > 0.5 * wr:
            c_rp = 2.0 * p[P_ZRP] * math.sqrt(p[P_KRP] * p[P_MR] * r * r)
            t_rp += c_rp * dpsi
        force[0] = t_tb + t_g - t_rp
        force[2] = t_rp / r - f_tie
    else:
        force[0] = t_tb + t_g - pinion_ratio(x[S_THP], p) * f_tie
        force[2] = 0.0
    force[1] = t_m - t_g / n - cogging_torque(x[S_THM], p)
    k_w = p[P_KW] if scen == TIRES_ON_GROUND else 0.0
    force[3] = f_tie - k_w * x[S_XW]
    aux[0] = t_tb
    aux[1] = t_m
    aux[2] = f_tie
    aux[3] = phi
    aux[4] = xr
    aux[5] = vr
    aux[6] = abs(t_tb)


@njit(**_JIT)
def rack_pos_factor(p, xr):
    a = p[P_BUMP_A]
    if a == 0.0:
        return 1.0
    d = (xr - p[P_BUMP_X]) / p[P_BUMP_W]
    return 1.0 + a * math.exp(-d * d)


@njit(**_JIT)
def tie_rod_friction(p, dv):
    lvl = p[P_TRF]
    if lvl == 0.0:
        return 0.0, 0.0
    ve = p[P_TRF_VEPS]
    th = math.tanh(dv / ve)
    return lvl * th, lvl * (1.0 - th * th) / ve


@njit(**_JIT)
def tire_coulomb_viscous(p, scen):
    if scen == SUSPENDED:
        return p[P_BRG_FC], p[P_BRG_B]
    return p[B_TIRE], p[B_TIRE + 1]


@njit(**_JIT)
def stepped_friction(p, b, fc0, bv, v, z, load, pos_factor, h):
    """``friction`` of a body's element with its Dahl state stepped to ``v`` over ``h``.

    The velocity solve treats the presliding force implicitly, as it treats the tanh
    Coulomb term: with the state frozen at the step's start (explicit) a stiff state
    flipped between ±F_c from one step to the next, and the stiff end of the presliding
    candidate sat 2-40x the sensor noise away from the base model it should nest.
    """
    sigma = p[b + FB_SIGMA]
    if sigma <= 0.0:
        return friction(p, b, fc0, bv, v, z, load, pos_factor)
    return _stepped_presliding(p, b, fc0, bv, v, z, load, pos_factor, h)


@njit(**_JIT)
def _stepped_presliding(p, b, fc0, bv, v, z, load, pos_factor, h):
    """``stepped_friction`` of an element with presliding (σ > 0)."""
    sigma = p[b + FB_SIGMA]
    w = stiff_share(p, b)
    zn = dahl_step(p, b, fc0, v, z, load, pos_factor, h) if w < 1.0 else z
    f, df = friction(p, b, fc0, bv, v, zn, load, pos_factor)
    g, dg = stiff_end_blend(p, b, fc0, v, zn, load, pos_factor)
    f += g
    df += dg
    if v == 0.0 or w >= 1.0:
        return f, df
    # dz_n/dv with the level held (Newton is safeguarded by bisection)
    lvl, _ = coulomb_level(p, b, fc0, v, load, pos_factor)
    lvl = max(lvl, 1e-12)
    veps = p[b + FB_VEPS]
    th = math.tanh(v / veps)
    e = math.exp(-sigma * abs(v) * h / lvl)
    s = 1.0 if v > 0.0 else -1.0
    dzn = lvl * (1.0 - th * th) / veps * (1.0 - e) - (z - lvl * th) * sigma * h / lvl * e * s
    return f, df + (1.0 - w) * dzn


@njit(**_JIT)
def _body_friction(body, v, x, p, scen, aux, v_rack, v_wheel, h):
    """Friction force on ``body`` at its velocity ``v`` (others frozen) at the end of a
    step ``h``, and dF/dv."""
    r = p[P_RP]
    load_rack = aux[6] / r
    if body == BODY_MOTOR:
        return stepped_friction(p, B_MOT, p[B_MOT], p[B_MOT + 1], v, x[S_ZMOT], 0.0, 1.0, h)
    if body == BODY_PINION:
        if rack_is_body(p):
            return 0.0, 0.0
        rr = pinion_ratio(x[S_THP], p)
        pf = rack_pos_factor(p, pinion_rack_position(x[S_THP], p))
        f, df = stepped_friction(p, B_RACK, p[B_RACK], p[B_RACK + 1], rr * v, x[S_ZRACK],
                                 load_rack, pf, h)
        if tie_rods_connected(scen) and wheels_move(scen):
            g, dg = tie_rod_friction(p, rr * v - v_wheel)
            f += g
            df += dg
        elif scen == BLOCKED_RACK:
            g, dg = tie_rod_friction(p, rr * v)
            f += g
            df += dg
        return rr * f, rr * rr * df
    if body == BODY_RACK:
        pf = rack_pos_factor(p, x[S_XR])
        f, df = stepped_friction(p, B_RACK, p[B_RACK], p[B_RACK + 1], v, x[S_ZRACK], load_rack,
                                 pf, h)
        if wheels_move(scen):
            g, dg = tie_rod_friction(p, v - v_wheel)
            f += g
            df += dg
        elif scen == BLOCKED_RACK:
            g, dg = tie_rod_friction(p, v)
            f += g
            df += dg
        return f, df
    # wheel
    fc, bv = tire_coulomb_viscous(p, scen)
    f, df = stepped_friction(p, B_TIRE, fc, bv, v, x[S_ZTIRE], 0.0, 1.0, h)
    g, dg = tie_rod_friction(p, v_rack - v)
    return f - g, df + dg


@njit(**_JIT)
def _friction_bound(body, x, p, scen, aux):
    """Upper bound of the non-viscous friction magnitude on a body (for bracketing)."""
    r = p[P_RP]
    rs_mot = max(p[B_MOT + FB_STATIC], 1.0)
    if body == BODY_MOTOR:
        return 2.0 * rs_mot * p[B_MOT] + abs(x[S_ZMOT])
    if body == BODY_WHEEL:
        fc, _ = tire_coulomb_viscous(p, scen)
        return 2.0 * max(p[B_TIRE + FB_STATIC], 1.0) * fc + abs(x[S_ZTIRE]) + p[P_TRF]
    xr, _ = rack_kinematics(x, p)
    fr = 2.0 * max(p[B_RACK + FB_STATIC], 1.0) * (p[B_RACK] + p[B_RACK + FB_LOAD] * aux[6] / r)
    fr = fr * rack_pos_factor(p, xr) + abs(x[S_ZRACK]) + p[P_TRF]
    if body == BODY_PINION:
        return 0.0 if rack_is_body(p) else pinion_ratio(x[S_THP], p) * fr
    return fr


@njit(**_JIT)
def _guess_terms(body, x, p, scen, aux):
    """Coulomb level, regularisation velocity and viscous slope of a body's own element."""
    r = p[P_RP]
    if body == BODY_MOTOR:
        b = B_MOT
        lvl, sc = p[B_MOT], 1.0
        bv = p[B_MOT + 1]
    elif body == BODY_WHEEL:
        b = B_TIRE
        lvl, bv = tire_coulomb_viscous(p, scen)
        sc = 1.0
    else:
        b = B_RACK
        xr, _ = rack_kinematics(x, p)
        lvl = (p[B_RACK] + p[B_RACK + FB_LOAD] * aux[6] / r) * rack_pos_factor(p, xr)
        bv = p[B_RACK + 1]
        sc = pinion_ratio(x[S_THP], p) if body == BODY_PINION else 1.0
    if p[b + FB_SIGMA] > 0.0 and stiff_share(p, b) < 1.0:
        lvl = 0.0
    return lvl * sc, p[b + FB_VEPS] / sc, bv * sc * sc


@njit(**_JIT)
def _solve_velocity(body, m_h, v_star, v_guess, x, p, scen, aux, v_rack, v_wheel, h):
    """Solve m/h·(v − v*) + F_fric(v) = 0 by safeguarded Newton.

    The start is the sliding solution, or the creep velocity v_eps·atanh(·)
    when the load is below the Coulomb level, so Newton needs a few steps.
    """
    if body == BODY_PINION and rack_is_body(p):
        # the rack is its own body: no friction acts on the pinion, the update is exact
        return v_star
    fb = _friction_bound(body, x, p, scen, aux)
    lo = min(v_star, 0.0) - fb / m_h - 1e-12
    hi = max(v_star, 0.0) + fb / m_h + 1e-12
    tol = 1e-11 * (hi - lo) + 1e-300
    lvl, ve, bv = _guess_terms(body, x, p, scen, aux)
    z = m_h * v_star
    if lvl <= 0.0:
        v = z / (m_h + bv)
    elif abs(z) > lvl:
        v = (z - lvl) / (m_h + bv) if z > 0 else (z + lvl) / (m_h + bv)
    else:
        v = ve * math.atanh(max(min(z / lvl, 0.999999999), -0.999999999))
    v = min(max(v, lo), hi)
    for _ in range(100):
        f, df = _body_friction(body, v, x, p, scen, aux, v_rack, v_wheel, h)
        g = m_h * (v - v_star) + f
        if g > 0.0:
            hi = v
        else:
            lo = v
        dg = m_h + df
        vn = v - g / dg if dg > 0.0 else 0.5 * (lo + hi)
        if abs(vn - v) <= tol:
            return vn
        if not (lo < vn < hi):
            vn = 0.5 * (lo + hi)
        v = vn
    return v


@njit(**_JIT)
def step(x, th_sw, om_sw, om_end, p, scen, mode, h, force, aux):
    """Advance the state ``x`` in place by one sub-step ``h`` (input rate ``om_sw`` at its
    start, ``om_end`` at its end)."""
    if scen != BLOCKED_COLUMN:
        _loads(x, th_sw, om_sw, p, scen, mode, force, aux)
        sep = rack_is_body(p)
        v_wheel = x[S_VW] if wheels_move(scen) else 0.0
        # pinion
        m = body_mass(BODY_PINION, p)
        x[S_WP] = _solve_velocity(BODY_PINION, m / h, x[S_WP] + h / m * force[0], x[S_WP],
                                  x, p, scen, aux, 0.0, v_wheel, h)
        # motor
        m = body_mass(BODY_MOTOR, p)
        x[S_WM] = _solve_velocity(BODY_MOTOR, m / h, x[S_WM] + h / m * force[1], x[S_WM],
                                  x, p, scen, aux, 0.0, v_wheel, h)
        if sep:
            m = body_mass(BODY_RACK, p)
            x[S_VR] = _solve_velocity(BODY_RACK, m / h, x[S_VR] + h / m * force[2], x[S_VR],
                                      x, p, scen, aux, 0.0, v_wheel, h)
        if wheels_move(scen):
            v_rack = x[S_VR] if sep else pinion_ratio(x[S_THP], p) * x[S_WP]
            m = body_mass(BODY_WHEEL, p)
            x[S_VW] = _solve_velocity(BODY_WHEEL, m / h, x[S_VW] + h / m * force[3], x[S_VW],
                                      x, p, scen, aux, v_rack, 0.0, h)
        # positions and Dahl states follow the new velocities
        x[S_THP] += h * x[S_WP]
        x[S_THM] += h * x[S_WM]
        if sep:
            x[S_XR] += h * x[S_VR]
        if wheels_move(scen):
            x[S_XW] += h * x[S_VW]
        r = p[P_RP]
        xr, vr = rack_kinematics(x, p)
        x[S_ZMOT] = dahl_step(p, B_MOT, p[B_MOT], x[S_WM], x[S_ZMOT], 0.0, 1.0, h)
        x[S_ZRACK] = dahl_step(p, B_RACK, p[B_RACK], vr, x[S_ZRACK], aux[6] / r,
                               rack_pos_factor(p, xr), h)
        if wheels_move(scen):
            fc, _ = tire_coulomb_viscous(p, scen)
            x[S_ZTIRE] = dahl_step(p, B_TIRE, fc, x[S_VW], x[S_ZTIRE], 0.0, 1.0, h)
        load_col = aux[6]
    else:
        load_col = abs(torsion_bar_torque(th_sw, p))
    # the column's Dahl state is driven by the measured input alone: stepped with the rate at
    # the sub-step's end it is what the output reads there, so its stiff end is the base
    # model's tanh Coulomb at that sample (with the start's rate it lagged one sample)
    x[S_ZCOL] = dahl_step(p, B_COL, p[B_COL], om_end, x[S_ZCOL], load_col, 1.0, h)


@njit(**_JIT)
def rhs(x, th_sw, om_sw, p, scen, mode, dx):
    """Right-hand side dx/dt = f(x, u, p) with u = (angle, angular speed)."""
    force = np.zeros(4)
    aux = np.zeros(7)
    for i in range(N_STATES):
        dx[i] = 0.0
    if scen != BLOCKED_COLUMN:
        _loads(x, th_sw, om_sw, p, scen, mode, force, aux)
        sep = rack_is_body(p)
        v_wheel = x[S_VW] if wheels_move(scen) else 0.0
        xr, vr = rack_kinematics(x, p)
        f, _ = _body_friction(BODY_PINION, x[S_WP], x, p, scen, aux, 0.0, v_wheel, 0.0)
        dx[S_THP] = x[S_WP]
        dx[S_WP] = (force[0] - f) / body_mass(BODY_PINION, p)
        f, _ = _body_friction(BODY_MOTOR, x[S_WM], x, p, scen, aux, 0.0, v_wheel, 0.0)
        dx[S_THM] = x[S_WM]
        dx[S_WM] = (force[1] - f) / body_mass(BODY_MOTOR, p)
        if sep:
            f, _ = _body_friction(BODY_RACK, x[S_VR], x, p, scen, aux, 0.0, v_wheel, 0.0)
            dx[S_XR] = x[S_VR]
            dx[S_VR] = (force[2] - f) / body_mass(BODY_RACK, p)
        if wheels_move(scen):
            f, _ = _body_friction(BODY_WHEEL, x[S_VW], x, p, scen, aux, vr, 0.0, 0.0)
            dx[S_XW] = x[S_VW]
            dx[S_VW] = (force[3] - f) / body_mass(BODY_WHEEL, p)
            fc, _ = tire_coulomb_viscous(p, scen)
            dx[S_ZTIRE] = dahl_rate(p, B_TIRE, fc, x[S_VW], x[S_ZTIRE], 0.0, 1.0)
        r = p[P_RP]
        dx[S_ZMOT] = dahl_rate(p, B_MOT, p[B_MOT], x[S_WM], x[S_ZMOT], 0.0, 1.0)
        dx[S_ZRACK] = dahl_rate(p, B_RACK, p[B_RACK], vr, x[S_ZRACK], aux[6] / r,
                                rack_pos_factor(p, xr))
        load_col = aux[6]
    else:
        load_col = abs(torsion_bar_torque(th_sw, p))
    dx[S_ZCOL] = dahl_rate(p, B_COL, p[B_COL], om_sw, x[S_ZCOL], load_col, 1.0)


@njit(**_JIT)
def outputs(x, th_sw, om_sw, p, scen, mode, force, aux, out):
    """Model outputs at the current state (sensor offsets are added outside)."""
    _loads(x, th_sw, om_sw, p, scen, mode, force, aux)
    f_col, _ = friction(p, B_COL, p[B_COL], p[B_COL + 1], om_sw, x[S_ZCOL], aux[6], 1.0)
    if p[B_COL + FB_SIGMA] > 0.0:
        f_col += stiff_end_blend(p, B_COL, p[B_COL], om_sw, x[S_ZCOL], aux[6], 1.0)[0]
    xr, vr = rack_kinematics(x, p)
    f_tie = aux[2]
    if wheels_move(scen):
        g, _ = tie_rod_friction(p, vr - x[S_VW])
        f_tie += g
    elif scen == BLOCKED_RACK:
        g, _ = tie_rod_friction(p, vr)
        f_tie += g
    out[O_TORQUE] = aux[0] + f_col
    out[O_RACK] = xr
    out[O_FTIE] = f_tie
    out[O_THM] = x[S_THM]
    out[O_TM] = aux[1]
    out[O_THP] = x[S_THP]
    out[O_XW] = x[S_XW]
    out[O_PHI] = aux[3]
    out[O_TTB] = aux[0]
    out[O_VR] = vr
    out[O_WM] = x[S_WM]
    out[O_FCOL] = f_col


@njit(**_JIT)
def simulate_dt(theta_sw, omega_sw, p, scen, mode, n_sub, x0, dt):
    """Simulate one test sampled at uniform ``dt`` with ``n_sub`` sub-steps per sample.

    ``theta_sw``/``omega_sw`` are the measured angle and its rate at the sample
    times, held linear between samples. Returns (n_samples, N_OUTPUTS).
    """
    n = theta_sw.shape[0]
    out = np.empty((n, N_OUTPUTS))
    x = x0.copy()
    force = np.zeros(4)
    aux = np.zeros(7)
    row = np.empty(N_OUTPUTS)
    outputs(x, theta_sw[0], omega_sw[0], p, scen, mode, force, aux, row)
    out[0, :] = row
    h = dt / n_sub
    for i in range(1, n):
        a0 = theta_sw[i - 1]
        a1 = theta_sw[i]
        w0 = omega_sw[i - 1]
        w1 = omega_sw[i]
        for s in range(n_sub):
            # the kick uses the state at the start of the sub-step, so the input too
            tau = s / n_sub
            step(x, a0 + tau * (a1 - a0), w0 + tau * (w1 - w0),
                 w0 + (s + 1) / n_sub * (w1 - w0), p, scen, mode, h, force, aux)
        outputs(x, a1, w1, p, scen, mode, force, aux, row)
        out[i, :] = row
    return out


@njit(parallel=True, cache=True)
def simulate_batch(theta_sw, omega_sw, params, scen, mode, n_sub, x0s, dt):
    """Many parameter vectors on one test, in parallel (identification Jacobians)."""
    b = params.shape[0]
    out = np.empty((b, theta_sw.shape[0], N_OUTPUTS))
    for k in prange(b):
        out[k] = simulate_dt(theta_sw, omega_sw, params[k], scen, mode, n_sub, x0s[k], dt)
    return out
