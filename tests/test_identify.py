"""Cascaded identification on seeded bench campaigns (issue 3 targets)."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pandas as pd
import pytest

from mbst.cli import main
from mbst.identify.cascade import IdentifySettings, correlate, identify
from mbst.identify.fitting import channel_scales, hac_meat, residual_memory
from mbst.identify.record import base_from_record
from mbst.io.campaign import CampaignError, read_campaign
from mbst.report.plots import motion_reversals
from mbst.systems.eps.bench import BenchRecipe, PlannedTest, run_bench
from mbst.systems.eps.model import rate_noise, smooth_input, standstill
from mbst.systems.eps.params import PARAM_INDEX, vector_from

# The fit's own verdict must cover these (a guard against an empty "identifiable" set).
WELL_DETERMINED = (
    "torsion_bar.stiffness_nm_per_rad",
    "steering_column.coulomb_nm",
    "tie_rods.stiffness_n_per_m",
    "tires.centring_stiffness_n_per_m",
    "tires.coulomb_n",
    "tires.viscous_ns_per_m",
    "offset.rack_position_m",
    "offset.tie_rod_force_left_n",
    "offset.tie_rod_force_right_n",
)


@pytest.fixture(scope="module")
def clean(demo_clean_bench, demo_clean_identified):
    camp, result = demo_clean_identified
    truth = json.loads((demo_clean_bench / "truth.json").read_text())["params"]
    return camp, vector_from(truth), result


@pytest.fixture(scope="module")
def backlash(demo_backlash_identified):
    return demo_backlash_identified


def test_clean_campaign_recovers_every_identifiable_parameter(clean):
    """Issue #3: what the fit calls identifiable comes back within 5 % of truth.

    The torque offset (0.04 N·m) comes back ~0.005 N·m high, a quarter of the
    sensor noise: it gets an absolute bound instead, 0.5 % of the channel's spread. The split of rack and motor
    friction, the column's
    viscous term and the worm-gear mesh are not identifiable from the demo's
    three sensors; the fit must say so rather than pass them off as found.
    """
    camp, truth, res = clean
    scales = channel_scales([res.prepared[s.id] for s in camp.identification_tests()])
    identified = [n for st in res.stages for n in st.free if st.identifiable[n]]
    assert set(WELL_DETERMINED) <= set(identified)
    for name in identified:
        i = PARAM_INDEX[name]
        if name == "offset.steering_torque_nm":
            assert abs(res.params[i] - truth[i]) < 0.005 * scales["steering_torque_nm"], name
        else:
            assert res.params[i] == pytest.approx(truth[i], rel=0.05), name
    for name in ("motor.coulomb_nm", "steering_column.viscous_nms_per_rad"):
        assert name not in identified, name


def test_standard_errors_widen_with_residual_memory():
    """The Newey–West meat equals s²·JᵀJ for white residuals and grows for correlated ones."""
    rng = np.random.default_rng(0)
    n = 4000
    jac = np.column_stack([np.ones(n), np.linspace(-1, 1, n)])
    white = rng.standard_normal(n)
    classical = white @ white / (n - 2) * jac.T @ jac
    assert np.allclose(np.diag(hac_meat(jac, white, [n], 2)), np.diag(classical), rtol=0.1)
    slow = np.convolve(rng.standard_normal(n + 49), np.ones(50) / np.sqrt(50), "valid")
    assert residual_memory(slow) > 30
    widened = hac_meat(jac, slow, [n], 2)
    assert widened[0, 0] > 10 * (slow @ slow / (n - 2)) * n


def test_clean_fit_reaches_the_noise_floor_on_controls(clean):
    camp, truth, res = clean
    controls = [res.prepared[s.id] for s in camp.control_tests()]
    floor, _ = correlate(controls, truth)
    merged = res.correlation.merge(floor, on=["test", "channel"], suffixes=("", "_true"))
    assert len(merged) >= 4
    gap = merged.fit_percent_true - merged.fit_percent
    assert gap.max() < 0.5, merged[["test", "channel", "fit_percent", "fit_percent_true"]]


def test_clean_fit_raises_no_bound_alarm(clean):
    _, _, res = clean
    assert not [w for w in res.warnings if w.startswith("LOUD")]


def test_hidden_backlash_drops_control_fit_at_reversals(clean, backlash):
    _, _, res_clean = clean
    camp, res = backlash
    key = ["test", "channel"]
    both = res.correlation.merge(res_clean.correlation, on=key, suffixes=("", "_clean"))
    torque = both[both.channel == "steering_torque_nm"]
    # the free tie-rods control shows the shelf at every reversal
    drop = (torque.fit_percent_clean - torque.fit_percent).max()
    assert drop > 5.0, torque
    # and the residual lives just after the motion reversals: the mesh crosses its gap
    # when the motor's load reverses, within ~0.2 s of the steering reversal at 0.8 Hz
    ctrl = res.prepared["s2_sine_0p8hz_ctrl"]
    err2 = (ctrl.measured["steering_torque_nm"] - res.twins[ctrl.id]["steering_torque_nm"]) ** 2
    after = np.zeros(len(err2), bool)
    win = int(0.2 / ctrl.dt_s)
    for r in motion_reversals(ctrl.omega_rad_per_s):
        after[r: r + win] = True
    assert after.mean() < 0.35
    assert err2[after].sum() / err2.sum() > 0.6


def test_missing_effect_shows_as_a_loud_bound_warning(backlash):
    _, res = backlash
    loud = [w for w in res.warnings if w.startswith("LOUD")]
    assert any("worm_gear.stiffness" in w for w in loud), res.warnings


def _small_blocked_column(tmp_path):
    sine = {"kind": "sine", "amplitude_deg": 5, "frequency_hz": 0.5, "cycles": 2}
    plan = [PlannedTest("a", "blocked_column", sine), PlannedTest("b", "blocked_column", sine),
            PlannedTest("c", "blocked_column", sine, role="control")]
    return run_bench(tmp_path / "small", BenchRecipe(effects=[], plan=plan, name="small"))


def test_flat_lined_channel_is_named_and_not_used(tmp_path):
    camp_dir = _small_blocked_column(tmp_path)
    f = camp_dir / "tests" / "b.csv"
    df = pd.read_csv(f)
    df["steering_torque_nm"] = 0.5
    df.to_csv(f, index=False)
    res = identify(read_campaign(camp_dir), IdentifySettings(multistart=1))
    assert any("'b'" in w and "steering_torque_nm" in w and "flat" in w for w in res.warnings)


def test_no_identification_test_is_an_error(tmp_path):
    camp_dir = _small_blocked_column(tmp_path)
    y = (camp_dir / "campaign.yaml").read_text().replace("role: identification", "role: control")
    (camp_dir / "campaign.yaml").write_text(y)
    with pytest.raises(CampaignError, match="identification"):
        identify(read_campaign(camp_dir))


def test_cli_identify_bad_campaign_writes_nothing(tmp_path, capsys):
    camp_dir = _small_blocked_column(tmp_path)
    f = camp_dir / "tests" / "a.csv"
    df = pd.read_csv(f)
    df.loc[41, "steering_torque_nm"] = np.nan
    df.to_csv(f, index=False)
    out = tmp_path / "out"
    assert main(["identify", str(camp_dir), "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    assert "'a'" in err and "steering_torque_nm" in err and "row 42" in err
    assert not out.exists()


def test_cli_identify_writes_params_and_correlation(tmp_path):
    camp_dir = _small_blocked_column(tmp_path)
    out = tmp_path / "out"
    assert main(["identify", str(camp_dir), "--out", str(out), "--quiet"]) == 0
    params = json.loads((out / "params.json").read_text())["params"]
    kt = params["torsion_bar.stiffness_nm_per_rad"]
    assert kt["stage"] == "blocked_column" and kt["std_error"] > 0
    assert kt["value"] == pytest.approx(92.0, rel=0.02)
    corr = pd.read_csv(out / "correlation.csv")
    assert list(corr.columns) == ["test", "channel", "fit_percent", "nrmse", "pearson_r", "r2",
                                  "max_abs_error"]
    assert set(corr.test) == {"c"} and corr.fit_percent.min() > 95
    for fig in ("hysteresis.png", "time_histories.png", "residuals.png"):
        assert (out / "figures" / fig).stat().st_size > 10_000
    leftovers = [p for p in tmp_path.iterdir() if p.name.startswith(".out")]
    assert not leftovers
    shutil.rmtree(out)


def test_base_fit_record_rebuilds_discoverys_own_cascade_and_only_for_its_campaign(tmp_path):
    """The identify step's cascade is what discovery would fit itself (bitwise), and a
    record of other data or other settings is refused with the reason."""
    camp_dir = _small_blocked_column(tmp_path)
    out = tmp_path / "out"
    assert main(["identify", str(camp_dir), "--out", str(out), "--quiet"]) == 0
    record = json.loads((out / "base_fit.json").read_text())
    camp = read_campaign(camp_dir)
    own = identify(camp, IdentifySettings(), controls=False, check_known=False)
    rebuilt = base_from_record(camp, IdentifySettings(), record)
    assert rebuilt.result is not None, rebuilt.reason
    assert np.array_equal(rebuilt.result.params, own.params)
    assert [st.free for st in rebuilt.result.stages] == [st.free for st in own.stages]
    assert rebuilt.result.preid["upper"] == own.preid["upper"]
    for tid, tw in own.twins.items():
        for ch, y in tw.items():
            assert np.array_equal(rebuilt.result.twins[tid][ch], y), (tid, ch)
    assert "settings" in base_from_record(camp, IdentifySettings(seed=1), record).reason
    f = camp_dir / "tests" / "a.csv"
    df = pd.read_csv(f)
    df.loc[10, "steering_torque_nm"] += 0.01
    df.to_csv(f, index=False)
    assert "campaign data" in base_from_record(read_campaign(camp_dir), IdentifySettings(),
                                               record).reason


def test_rate_noise_and_standstill_are_read_from_the_angle():
    dt = 0.002
    t = np.arange(0.0, 6.0, dt)
    clean = np.radians(5) * np.sin(2 * np.pi * 0.5 * t) * (t > 1.0)
    noisy = clean + np.radians(0.05) * np.random.default_rng(0).standard_normal(len(t))
    _, rate_clean = smooth_input(clean, dt)
    _, rate_noisy = smooth_input(noisy, dt)
    true_noise = np.std(rate_noisy - rate_clean)
    assert rate_noise(clean, dt) < 1e-3 * true_noise
    assert rate_noise(noisy, dt) == pytest.approx(true_noise, rel=0.1)
    still = standstill(smooth_input(noisy, dt)[0], 2e-4, dt)
    assert still[t < 0.9].mean() > 0.9 and still[t > 1.2].mean() < 0.05


def test_fast_inputs_get_a_shorter_input_smoothing_window(tmp_path):
    """A 0.1 s impact on tires on ground: the default 0.1 s cubic rounded the pulses off
    and the *true* model's twin reached only ~72 % torque FIT; slow tests keep 0.1 s."""
    from mbst.core.metrics import fit_percent
    from mbst.identify.fitting import prepare_test, simulate_twin
    from mbst.io.campaign import TestSpec, write_campaign
    from mbst.plan.inputs import profile
    from mbst.systems.eps import simulate as eps
    from mbst.systems.eps.model import INPUT_WINDOW_S, input_window

    recipe = BenchRecipe(effects=[], seed=0)
    truth = recipe.true_params()
    noise = {"steering_angle_rad": np.radians(0.05), "steering_torque_nm": 0.02,
             "rack_position_m": 2e-5, "tie_rod_force_left_n": 5.0}
    tests = []
    for i, spec in enumerate([
            {"kind": "impact", "amplitude_deg": 24.0, "width_s": 0.1, "count": 4,
             "spacing_s": 1.0},
            {"kind": "sine", "amplitude_deg": 120.0, "frequency_hz": 0.5, "cycles": 2}]):
        t, ang = profile(spec, 500.0)
        raw = eps.simulate_raw("tires_on_ground", "passive", t, ang, truth)
        sig = eps.sensors_from_raw(raw, truth, "tires_on_ground")
        rng = np.random.default_rng([0, i])
        cols = {"time_s": t, "steering_angle_rad": ang}
        cols.update({ch: sig[ch] for ch in noise if ch != "steering_angle_rad"})
        for ch, sd in noise.items():
            cols[ch] = cols[ch] + sd * rng.standard_normal(len(t))
        tid = f"t{i}_{spec['kind']}"
        tests.append((TestSpec(id=tid, file=f"tests/{tid}.csv", scenario="tires_on_ground",
                               input=spec, motor="passive", role="identification"),
                      pd.DataFrame(cols)))
    camp = read_campaign(write_campaign(tmp_path / "c", name="fast", system="eps-column-assist",
                                        known={}, tests=tests))
    impact, sine = (prepare_test(camp, spec, 0.005) for spec in camp.tests)
    assert float(sine.inputs["input_window_s"]) == INPUT_WINDOW_S
    assert float(impact.inputs["input_window_s"]) <= 0.05
    fit = fit_percent(impact.measured["steering_torque_nm"],
                      simulate_twin(impact, truth)["steering_torque_nm"])
    assert fit > 95.0, fit
    # the same angle without noise is left alone (nothing to compare the leftovers with)
    assert input_window(profile(camp.tests[0].input, 500.0)[1], 0.002) == INPUT_WINDOW_S


def test_angle_noise_does_not_bias_the_column_friction(tmp_path):
    """The blocked column alone, with the bench's 0.05° of angle noise: a twin that
    switched its column friction on the noisy rate gave −19 % here."""
    from mbst.identify.cascade import run_cascade
    from mbst.systems.eps.bench import compact_plan

    recipe = BenchRecipe(effects=[], plan=compact_plan()[:2], seed=0)
    camp = read_campaign(run_bench(tmp_path, recipe))
    truth = recipe.true_params()
    only = {"torsion_bar.stiffness_nm_per_rad", "steering_column.coulomb_nm",
            "steering_column.viscous_nms_per_rad"}
    p = run_cascade(camp, IdentifySettings(), base=truth, only=only).params
    i = PARAM_INDEX["steering_column.coulomb_nm"]
    assert p[i] == pytest.approx(truth[i], rel=0.05)


def test_a_fragment_that_never_turns_back_is_not_read_as_the_friction_loop(tmp_path):
    """An independent campaign held a 0.24-s start of a free tie-rods sine (0.2° of motion
    under a 13-bit encoder): as the slowest test its "loop", read from the noise, set the
    rack's Coulomb bound to 3 N and the control torque FIT fell from 96 to 36 %. The loop
    now comes from the slowest test that goes both ways through its range."""
    from mbst.identify.fitting import prepare_test
    from mbst.io.campaign import write_campaign
    from mbst.systems.eps.bench import compact_plan
    from mbst.systems.eps.model import pre_identify, reversals
    from mbst.systems.eps.realism import BenchRealism

    recipe = BenchRecipe(effects=[], plan=compact_plan(), seed=700,
                         realism=BenchRealism.realistic())
    camp = read_campaign(run_bench(tmp_path / "bench", recipe))
    tests = [(s, camp.frame(s.id)) for s in camp.tests]
    spec, frame = next((s, f) for s, f in tests if s.scenario == "free_tie_rods")
    fragment = spec.__class__(**{**spec.__dict__, "id": "fragment",
                                 "file": "tests/fragment.csv"})
    tests.append((fragment, frame.iloc[:120].reset_index(drop=True)))
    both = read_campaign(write_campaign(tmp_path / "with", name="fragment",
                                        system="eps-column-assist", known=camp.known,
                                        tests=tests))
    p0 = recipe.true_params()

    def preid(c):
        return pre_identify(c, [prepare_test(c, s, 0.005) for s in c.tests
                                if s.role == "identification"], p0.copy())

    alone, with_fragment = preid(camp), preid(both)
    assert with_fragment["hysteresis_free_tie_rods"]["test"] != "fragment"
    assert with_fragment["upper"] == pytest.approx(alone["upper"])
    assert with_fragment["values"] == pytest.approx(alone["values"])
    # the counter itself: a noisy, quantised sine turns back at each peak, a still
    # angle under the same sensor never
    rng = np.random.default_rng(0)
    t = np.arange(0.0, 4.0, 0.002)
    q = 2 * np.pi / 2**13
    noisy = lambda x: np.round((x + 8.7e-4 * rng.standard_normal(len(t))) / q) * q  # noqa: E731
    assert reversals(noisy(0.5 * np.sin(2 * np.pi * 1.0 * t)), 8 * 8.7e-4) == 8  # 4 cycles
    assert reversals(noisy(np.zeros_like(t)), 8 * 8.7e-4) == 0
