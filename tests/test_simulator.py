"""Tests of the EPS simulator against closed forms, a reference solver and the noise floor.

The fixed-step integrator (``eps.simulate``) is checked three ways: on a
configuration that reduces to a linear spring-mass-damper with a closed-form
step response, on the stick/slip threshold of Coulomb friction, and against
``scipy.integrate.solve_ivp`` on the same right-hand side. The effect
catalogue is checked for visibility: every effect at its default size must
move some sensor by well more than its noise.
"""

from __future__ import annotations

import functools
import math

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from mbst.core.filtering import exponential_filter, filter_alpha
from mbst.systems.eps import simulate as eps
from mbst.systems.eps.bench import (
    DEFAULT_SENSORS,
    NOISE_RMS,
    BenchRecipe,
    _channels_for,
    compact_plan,
    demo_plan,
    input_profile,
    run_bench,
)
from mbst.systems.eps.params import EFFECTS, PARAM_INDEX, vector_from


def fit_percent(y: np.ndarray, y_hat: np.ndarray) -> float:
    """FIT % = 100·(1 − ‖y − ŷ‖ / ‖y − mean y‖)."""
    return 100.0 * (1.0 - np.linalg.norm(y - y_hat) / np.linalg.norm(y - np.mean(y)))


def _g(p: np.ndarray, name: str) -> float:
    return float(p[PARAM_INDEX[name]])


# No friction anywhere except what a test switches on. The column friction acts on the
# measured rate only, so zeroing it makes the torque channel k_t·(θ_sw − θ_p) exactly.
FRICTIONLESS = {
    "steering_column.coulomb_nm": 0.0,
    "steering_column.viscous_nms_per_rad": 0.0,
    "motor.coulomb_nm": 0.0,
    "motor.viscous_nms_per_rad": 0.0,
    "rack.coulomb_n": 0.0,
    "rack.viscous_ns_per_m": 0.0,
}


# --------------------------------------------------------------------------------------
# Analytic linear case: a spring-mass-damper step response
# --------------------------------------------------------------------------------------


def _unit_ramp_response(t: np.ndarray, wn: float, zeta: float) -> np.ndarray:
    """Response of ω²/(s² + 2ζωs + ω²) to a unit-slope ramp starting at t = 0 (underdamped)."""
    t = np.maximum(t, 0.0)
    wd = wn * math.sqrt(1.0 - zeta**2)
    decay = np.exp(-zeta * wn * t)
    return t - 2 * zeta / wn + decay * (
        2 * zeta / wn * np.cos(wd * t) + (2 * zeta**2 - 1) / wd * np.sin(wd * t)
    )


@pytest.mark.parametrize(
    "rack_coulomb_n",
    [
        pytest.param(1e-9, id="rack_coulomb_1e-9"),
        pytest.param(0.0, id="rack_coulomb_0"),
    ],
)
def test_step_response_matches_spring_mass_damper(rack_coulomb_n):
    """free_tie_rods, passive motor, stiff worm gear, rack viscous friction only.

    With θ_m = N·θ_p (k_g → ∞) the pinion and motor are one inertia
    J = J_p + J_m·N² on the torsion bar k_t, damped by the rack's b·r_p²:
    J·θ̈_p + b·r_p²·θ̇_p + k_t·θ_p = k_t·θ_sw.
    """
    p = vector_from({
        **FRICTIONLESS,
        "rack.coulomb_n": rack_coulomb_n,
        "rack.viscous_ns_per_m": 4500.0,
        # mesh mode ~300x the main mode; damped so the step does not ring it
        "worm_gear.stiffness_nm_per_rad": 1e6,
        "worm_gear.damping_nms_per_rad": 25.0,
    })
    n = _g(p, "worm_gear_ratio")
    j = _g(p, "column_inertia_kgm2") + _g(p, "motor_inertia_kgm2") * n**2
    k = _g(p, "torsion_bar.stiffness_nm_per_rad")
    c = _g(p, "rack.viscous_ns_per_m") * _g(p, "pinion_radius_m") ** 2
    wn = math.sqrt(k / j)
    zeta = c / (2.0 * math.sqrt(k * j))
    assert 0.05 < zeta < 0.3  # underdamped: the closed form below applies

    dt, step = 1e-3, 0.05
    t = np.arange(0.0, 1.0 + dt / 2, dt)
    angle = np.full_like(t, step)
    angle[0] = 0.0
    out = eps.simulate("free_tie_rods", "passive", t, angle, p,
                       angular_velocity_rad_per_s=np.zeros_like(t))

    # the input is linear between samples: the step rises over the first dt, so the exact
    # response is the step response averaged over that window
    theta_exact = step * (_unit_ramp_response(t, wn, zeta)
                          - _unit_ramp_response(t - dt, wn, zeta)) / dt
    theta = out["internal.pinion_angle_rad"]
    assert np.max(np.abs(theta - theta_exact)) < 0.005 * step
    torque_exact = k * (angle - theta_exact)
    assert np.max(np.abs(out["steering_torque_nm"] - torque_exact)) < 0.005 * k * step
    # it did ring and settle, so the comparison is not trivially passed by a lazy solution
    assert theta.max() > 1.2 * step
    assert abs(theta[-1] - step) < 0.01 * step


# --------------------------------------------------------------------------------------
# Coulomb friction: stick below r_p·F_c, slip above
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "scenario, coulomb_n",
    [
        ("free_tie_rods", 150.0),
        ("free_tie_rods", 270.0),
        ("free_tie_rods", 500.0),
        ("blocked_rack", 270.0),
    ],
)
def test_rack_coulomb_breakaway_torque(scenario, coulomb_n):
    """A slow ramp of the angle: the rack sticks until k_t·(θ_sw − θ_p) reaches r_p·F_c."""
    p = vector_from({**FRICTIONLESS, "rack.coulomb_n": coulomb_n})
    dt = 1e-3
    t = np.arange(0.0, 3.0, dt)
    rate = math.radians(5.0)
    angle = rate * np.clip(t - 0.5, 0.0, 2.5)
    out = eps.simulate(scenario, "passive", t, angle, p)
    torque = out["steering_torque_nm"]
    x = out["internal.rack_position_m"]
    v = out["internal.rack_speed_m_per_s"]
    v_eps = _g(p, "rack.regularisation_velocity_m_per_s")
    t_break = _g(p, "pinion_radius_m") * coulomb_n

    # stuck: below 95 % of the threshold only the creep of the tanh law (v ≲ v_eps)
    i_95 = int(np.argmax(torque >= 0.95 * t_break))
    assert i_95 > 0
    assert np.max(np.abs(x[:i_95])) < 10e-6
    # breakaway: the rack speed leaves the creep band (tanh(3) ≈ 0.995 of F_c)
    moving = np.abs(v) > 3.0 * v_eps
    assert moving.any()
    i_slip = int(np.argmax(moving))
    assert torque[i_slip] == pytest.approx(t_break, rel=0.03)
    # and it really slides once past the threshold
    assert abs(x[-1]) > 0.5e-3
    if scenario == "free_tie_rods":
        # nothing else loads the rack: sliding torque is the friction torque
        sliding = slice(i_slip + 200, int(2.5 / dt))
        assert np.mean(torque[sliding]) == pytest.approx(t_break, rel=0.02)


# --------------------------------------------------------------------------------------
# Agreement with a reference solver on the same right-hand side
# --------------------------------------------------------------------------------------

# (scenario, motor, hidden effects, amplitude in degrees): amplitudes where each scenario's
# own physics acts (tires slide on the ground beyond ~90°)
IVP_CASES = {
    "blocked_column": ("blocked_column", "passive", [], 5.0),
    "free_tie_rods": ("free_tie_rods", "passive", [], 30.0),
    "blocked_rack": ("blocked_rack", "passive", [], 30.0),
    "suspended": ("suspended", "passive", [], 60.0),
    "tires_on_ground": ("tires_on_ground", "passive", [], 100.0),
    "free_tie_rods-worm_gear_backlash": ("free_tie_rods", "passive", ["backlash:worm_gear"], 30.0),
    "blocked_rack-worm_gear_backlash": ("blocked_rack", "passive", ["backlash:worm_gear"], 30.0),
    "free_tie_rods-assist": ("free_tie_rods", "assist", [], 30.0),
}


@pytest.mark.parametrize("case", list(IVP_CASES))
def test_simulate_agrees_with_solve_ivp(case):
    scenario, motor, effects, amp = IVP_CASES[case]
    p = BenchRecipe(effects=effects).true_params()
    spec = {"kind": "sine", "amplitude_deg": amp, "frequency_hz": 0.8, "cycles": 2}
    t, angle = input_profile(spec, 500.0)
    assert 3.0 <= t[-1] <= 4.0

    fast = eps.simulate(scenario, motor, t, angle, p)
    f, x0 = eps.rhs_for(scenario, motor, t, angle, p)
    sol = solve_ivp(f, (t[0], t[-1]), x0, method="LSODA", t_eval=t,
                    rtol=1e-7, atol=1e-10, max_step=1e-3)
    assert sol.success, sol.message
    ref = eps.outputs_along(scenario, motor, t, angle, sol.y.T, p)

    channels = ["steering_torque_nm"]
    if scenario != "blocked_column":  # the rack does not move there
        channels.append("rack_position_m")
    for ch in channels:
        assert fit_percent(ref[ch], fast[ch]) >= 99.0, ch


# --------------------------------------------------------------------------------------
# Every catalogue effect is visible at its default size
# --------------------------------------------------------------------------------------

# The demo campaign's test (seed 000's plan) on which each effect shows most; the effect
# must act in that scenario (tires only touch the ground in tires_on_ground, tie-rods are
# disconnected in free_tie_rods, the column friction shows in every torque).
EFFECT_TEST = {
    "backlash:worm_gear": "s2_sine_0p8hz",
    "backlash:rack_pinion": "s2_sine_0p8hz",
    "stribeck_friction:steering_column": "s1_sine_0p2hz",
    "presliding_hysteresis:steering_column": "s1_sine_0p8hz",
    "power_law_damping:steering_column": "s3_sine_0p8hz",
    "asymmetric_friction:steering_column": "s1_sine_0p2hz",
    "load_dependent_friction:steering_column": "s1_sine_0p8hz",
    "stribeck_friction:motor": "s2_sine_0p2hz",
    "presliding_hysteresis:motor": "s2_sine_0p8hz",
    "power_law_damping:motor": "s3_sine_0p8hz",
    "asymmetric_friction:motor": "s2_sine_0p2hz",
    "stribeck_friction:rack": "s2_ramp",
    "presliding_hysteresis:rack": "s2_sine_0p8hz",
    "power_law_damping:rack": "s2_sine_0p8hz",
    "asymmetric_friction:rack": "s2_ramp",
    "load_dependent_friction:rack": "s3_sine_0p8hz",
    "stribeck_friction:tires": "s3_ramp",
    "presliding_hysteresis:tires": "s3_sine_0p8hz",
    "power_law_damping:tires": "s3_sine_0p8hz",
    "asymmetric_friction:tires": "s3_ramp",
    "position_dependent_friction:rack": "s2_sine_0p8hz",
    "stiffness_limit_stop:torsion_bar": "s1_sine_0p8hz",
    "coulomb_friction:tie_rods": "s3_sine_0p8hz",
}

# Effects whose catalogue default size stays below 3x the noise on every default sensor
# of every demo test (ratio measured on the test above). The column friction is only
# 0.07 N·m = 3.5x the torque noise, so a change of a fraction of it cannot reach 3x.
TOO_SMALL = {
    "stribeck_friction:steering_column": 1.2,
    "presliding_hysteresis:steering_column": 1.6,
    "power_law_damping:steering_column": 1.9,
    "asymmetric_friction:steering_column": 0.7,
    "presliding_hysteresis:motor": 2.7,
}


def _effect_params(key: str):
    if key in TOO_SMALL:
        return pytest.param(key, marks=pytest.mark.xfail(
            strict=True,
            reason=f"catalogue default size too small: rms change {TOO_SMALL[key]}x noise < 3x",
        ))
    return key


@functools.cache
def _demo_run(test_id: str, effect_key: str | None):
    pt = {p.id: p for p in demo_plan()}[test_id]
    p = BenchRecipe(effects=[]).true_params()
    if effect_key is not None:
        p = vector_from(EFFECTS[effect_key].default_size, base=p)
    t, angle = input_profile(pt.input, 500.0)
    return pt.scenario, eps.simulate(pt.scenario, pt.motor, t, angle, p)


def test_every_effect_has_a_visibility_case():
    assert set(EFFECT_TEST) == set(EFFECTS)
    assert set(TOO_SMALL) <= set(EFFECTS)


@pytest.mark.parametrize("key", [_effect_params(k) for k in EFFECTS])
def test_effect_visible_at_default_size(key):
    test_id = EFFECT_TEST[key]
    scenario, base = _demo_run(test_id, None)
    _, with_effect = _demo_run(test_id, key)
    channels = [c for c in _channels_for(scenario, DEFAULT_SENSORS) if c != "steering_angle_rad"]
    ratios = {
        ch: float(np.sqrt(np.mean((with_effect[ch] - base[ch]) ** 2)) / NOISE_RMS[ch])
        for ch in channels
    }
    assert max(ratios.values()) > 3.0, ratios


# --------------------------------------------------------------------------------------
# Exponential filter
# --------------------------------------------------------------------------------------


def test_filter_alpha():
    dt, tau = 2e-3, 5e-3
    assert filter_alpha(dt, tau) == pytest.approx(1.0 - math.exp(-dt / tau), rel=1e-15)
    assert filter_alpha(dt, 0.0) == 1.0


def test_exponential_filter_matches_recursion():
    rng = np.random.default_rng(3)
    x = np.cumsum(rng.standard_normal(500))
    dt, tau = 1e-3, 7e-3
    a = 1.0 - math.exp(-dt / tau)
    y_ref = np.empty_like(x)
    y_ref[0] = x[0]  # started at the first sample: no start-up transient
    for i in range(1, len(x)):
        y_ref[i] = y_ref[i - 1] + a * (x[i] - y_ref[i - 1])
    y = exponential_filter(x, dt, tau)
    np.testing.assert_allclose(y, y_ref, rtol=1e-12, atol=1e-12)


def test_exponential_filter_step_gives_alpha():
    dt, tau = 1e-3, 4e-3
    x = np.ones(50)
    x[0] = 0.0
    y = exponential_filter(x, dt, tau)
    a = 1.0 - math.exp(-dt / tau)
    n = np.arange(50)
    np.testing.assert_allclose(y[1:], 1.0 - (1.0 - a) ** n[1:], rtol=1e-12)


def test_exponential_filter_same_on_every_channel():
    rng = np.random.default_rng(4)
    x = rng.standard_normal(300)
    two = np.column_stack([x, x, 10.0 * x])
    y2 = exponential_filter(two, 1e-3, 5e-3)
    y1 = exponential_filter(x, 1e-3, 5e-3)
    assert y2.shape == two.shape
    np.testing.assert_array_equal(y2[:, 0], y2[:, 1])
    np.testing.assert_allclose(y2[:, 0], y1, rtol=1e-14, atol=1e-14)
    np.testing.assert_allclose(y2[:, 2], 10.0 * y1, rtol=1e-12, atol=1e-12)


def test_exponential_filter_tau_zero_is_identity():
    x = np.arange(10.0)
    y = exponential_filter(x, 1e-3, 0.0)
    np.testing.assert_array_equal(y, x)
    assert y is not x


# --------------------------------------------------------------------------------------
# The presliding candidate nests the base model (issue #34)
# --------------------------------------------------------------------------------------

PRESLIDING = [k for k in EFFECTS if k.startswith("presliding_hysteresis:")]


def _worst_noise_ratio(test_id: str, values: dict[str, float]) -> float:
    """Largest RMS difference (in noise RMS) over a demo test's channels between the clean
    rig with ``values`` set and the clean rig."""
    scenario, base = _demo_run(test_id, None)
    pt = {p.id: p for p in demo_plan()}[test_id]
    t, angle = input_profile(pt.input, 500.0)
    p = vector_from(values, base=BenchRecipe(effects=[]).true_params())
    sim = eps.simulate(pt.scenario, pt.motor, t, angle, p)
    channels = [c for c in _channels_for(scenario, DEFAULT_SENSORS) if c != "steering_angle_rad"]
    return max(float(np.sqrt(np.mean((sim[ch] - base[ch]) ** 2))) / NOISE_RMS[ch]
               for ch in channels)


@pytest.mark.parametrize("key", PRESLIDING)
def test_stiffest_presliding_is_the_base_model(key):
    """At the stiff end of its search range the Dahl state follows the base model's own
    regularised Coulomb force (blended into it over the top of the range, ``stiff_share``),
    so the candidate is the base there and a refit that starts there starts at the base's
    cost; the softest end is far from it (so the test can fail: with eps-model.md's
    unregularised sign the rack's stiff end sat 23 % above the base, and without the blend
    the Dahl state's lag at velocity reversals left 0.03x noise)."""
    from mbst.systems.eps.params import DAHL_BLEND_DECADES, PARAM_SPECS

    test_id = EFFECT_TEST[key]
    sigma = next(iter(EFFECTS[key].free))
    spec = PARAM_SPECS[PARAM_INDEX[sigma]]

    def worst_ratio(value: float) -> float:
        return _worst_noise_ratio(test_id, {sigma: value})

    stiff, soft = worst_ratio(spec.upper), worst_ratio(spec.lower)
    # where the blend into the stiff end begins, the Dahl state alone is already close
    foot = worst_ratio(spec.upper / 10**DAHL_BLEND_DECADES)
    print(f"{key}: stiff end {stiff:.2e}x noise, blend foot {foot:.3f}x, soft end {soft:.3f}x")
    assert stiff < 1e-9
    assert foot < 0.3
    assert soft > 0.3


def test_a_rack_pinion_gap_at_its_neutral_start_is_the_rigid_base_model():
    """The rack-pinion backlash candidate adds a gap and the mesh's compliance; off, it is
    the base's rigid rack. least_squares starts a bound parameter 1e-10 of its range inside
    (width 1e-11 rad): that must still be the base model, or the candidate's neutral refit
    starts above the base (it did: 0.06 % on a realistic bench, and fell back)."""
    key = "backlash:rack_pinion"
    test_id = EFFECT_TEST[key]
    width = next(iter(EFFECTS[key].free))

    def worst_ratio(value: float) -> float:
        return _worst_noise_ratio(test_id, {width: value})

    assert worst_ratio(1e-11) == 0.0
    assert worst_ratio(1e-4) > 0.0  # a gap of 0.006° is a compliant rack body


def test_the_torque_sensors_own_lag_filters_the_torque_channel_alone():
    """The torque sensor's lag (``torque_sensor.lag_s``, held at 0 by identification and
    refitted by discovery as a rival of each winner) is a first-order lag of the torque
    channel as the sensor logs it; at 0 the twin is the base model's."""
    t = np.arange(0.0, 2.0, 1e-3)
    angle = 0.3 * np.sin(2 * np.pi * 1.0 * t)
    base = vector_from({})
    lagged = vector_from({"torque_sensor.lag_s": 0.004})
    a = eps.simulate("free_tie_rods", "passive", t, angle, base)
    b = eps.simulate("free_tie_rods", "passive", t, angle, lagged)
    offset = base[PARAM_INDEX["offset.steering_torque_nm"]]
    np.testing.assert_allclose(
        b["steering_torque_nm"] - offset,
        exponential_filter(a["steering_torque_nm"] - offset, 1e-3, 0.004), atol=1e-12)
    assert np.max(np.abs(b["steering_torque_nm"] - a["steering_torque_nm"])) > 0.01
    for ch in ("rack_position_m", "tie_rod_force_left_n"):
        np.testing.assert_array_equal(a[ch], b[ch])


def test_a_drift_over_the_campaign_runs_each_test_at_its_own_friction_levels(tmp_path):
    """``friction.campaign_drift`` (held at 0 by identification, refitted by discovery as a
    rival of each winner): a test at place x of the running order (−½ first … ½ last) runs
    with every Coulomb level × (1 + drift·x), through the one simulate path."""
    from mbst.identify.fitting import prepare_test, simulate_twin
    from mbst.io.campaign import read_campaign

    camp = read_campaign(run_bench(tmp_path, BenchRecipe(effects=[], seed=0,
                                                         plan=compact_plan())))
    pts = [prepare_test(camp, s, 0.005) for s in camp.tests]
    assert [pt.place for pt in pts] == pytest.approx(np.linspace(-0.5, 0.5, len(pts)))
    model = pts[0].model
    drift, levels = model.campaign_drift
    assert "rack.coulomb_n" in levels and "motor.coulomb_nm" in levels
    p = model.vector_from({drift: -0.2})
    for pt, factor in ((pts[0], 1.1), (pts[-1], 0.9)):
        by_hand = model.vector_from({n: factor * p[model.param_index[n]] for n in levels})
        a, b = simulate_twin(pt, p), simulate_twin(pt, by_hand)
        for ch in pt.measured:
            np.testing.assert_array_equal(a[ch], b[ch])
        still = simulate_twin(pt, model.vector_from({}))
        assert np.max(np.abs(still["steering_torque_nm"] - a["steering_torque_nm"])) > 1e-3
