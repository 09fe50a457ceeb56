"""Tests of the virtual test bench: determinism, hidden truth, noise, the ``mbst bench`` CLI."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from mbst.cli import main
from mbst.core.sensors import SensorRealities, coloured_noise, measure
from mbst.io.campaign import read_campaign
from mbst.systems.eps import bench
from mbst.systems.eps import simulate as eps
from mbst.systems.eps.bench import (
    DEFAULT_SENSORS,
    DEMO_OFFSETS,
    KNOWN,
    NOISE_RMS,
    BenchRecipe,
    PlannedTest,
    run_bench,
    simulate_plan,
)
from mbst.systems.eps.model import EPS_MODEL
from mbst.systems.eps.params import EFFECTS
from mbst.systems.eps.realism import RIG_RANGES, SENSOR_QUANTUM, BenchRealism

LEAD_S = 0.5  # input_profile holds the angle at 0 this long before the motion


def small_plan() -> list[PlannedTest]:
    """Three short tests over three scenarios (one control) to keep the bench fast."""
    return [
        PlannedTest("bc_sine", "blocked_column",
                    {"kind": "sine", "amplitude_deg": 5, "frequency_hz": 1.0, "cycles": 2}),
        PlannedTest("ft_ramp", "free_tie_rods",
                    {"kind": "ramp", "amplitude_deg": 10, "rate_deg_per_s": 20}),
        PlannedTest("tg_sine", "tires_on_ground",
                    {"kind": "sine", "amplitude_deg": 100, "frequency_hz": 1.0, "cycles": 2},
                    role="control"),
    ]


def recipe(seed: int = 7, **kw) -> BenchRecipe:
    return BenchRecipe(seed=seed, plan=small_plan(), name="bench-test", **kw)


def campaign_files(camp: Path) -> dict[str, bytes]:
    files = sorted(f for f in camp.rglob("*") if f.is_file())
    return {str(f.relative_to(camp)): f.read_bytes() for f in files}


@pytest.fixture(scope="module")
def bench_dir(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("bench")
    run_bench(out, recipe())
    return out


# --------------------------------------------------------------------------------------
# Determinism
# --------------------------------------------------------------------------------------


def test_same_seed_gives_identical_bytes(bench_dir, tmp_path):
    run_bench(tmp_path, recipe())
    a = campaign_files(bench_dir / "campaign")
    b = campaign_files(tmp_path / "campaign")
    assert set(a) == set(b)
    assert len([k for k in a if k.endswith(".csv")]) == len(small_plan())
    for name in a:
        assert a[name] == b[name], name
    assert (bench_dir / "truth.json").read_bytes() == (tmp_path / "truth.json").read_bytes()


def test_same_seed_gives_identical_frames():
    for (s1, f1), (s2, f2) in zip(simulate_plan(recipe()), simulate_plan(recipe()), strict=True):
        assert s1 == s2
        pd.testing.assert_frame_equal(f1, f2, check_exact=True)


def test_different_seed_changes_only_the_noise():
    for (_, f1), (_, f2) in zip(simulate_plan(recipe(seed=7)), simulate_plan(recipe(seed=8)),
                                strict=True):
        assert list(f1.columns) == list(f2.columns)
        np.testing.assert_array_equal(f1["time_s"], f2["time_s"])
        for ch in f1.columns.drop("time_s"):
            d = (f1[ch] - f2[ch]).to_numpy()
            # two independent draws of the same noise: the difference has std √2·σ
            assert np.std(d) == pytest.approx(np.sqrt(2.0) * NOISE_RMS[ch], rel=0.15), ch


def test_noise_free_bench_is_the_model():
    p = recipe().true_params()
    for spec, frame in simulate_plan(recipe(noise_scale=0.0)):
        t = frame["time_s"].to_numpy()
        angle = frame["steering_angle_rad"].to_numpy()
        sim = eps.simulate(spec.scenario, spec.motor, t, angle, p)
        for ch in frame.columns.drop(["time_s", "steering_angle_rad"]):
            np.testing.assert_array_equal(frame[ch].to_numpy(), sim[ch], err_msg=ch)


# --------------------------------------------------------------------------------------
# What is written: a valid campaign, the truth beside it
# --------------------------------------------------------------------------------------


def test_truth_lies_outside_the_campaign(bench_dir):
    camp = (bench_dir / "campaign").resolve()
    truth = (bench_dir / "truth.json").resolve()
    assert truth.is_file()
    assert camp not in truth.parents
    assert not [f for f in camp.rglob("*") if "truth" in f.name.lower()]
    yaml_text = (camp / "campaign.yaml").read_text(encoding="utf-8")
    assert "truth" not in yaml_text.lower()
    record = json.loads(truth.read_text(encoding="utf-8"))
    hidden = [e["effect"] for e in record["effects"]]
    assert hidden == ["backlash"]  # the demo's worm-gear backlash, and nothing of it leaks
    for name in hidden:
        assert name not in yaml_text
    assert record["seed"] == 7


def test_written_campaign_reads_back(bench_dir):
    camp = read_campaign(bench_dir / "campaign")
    assert camp.name == "bench-test"
    assert [t.id for t in camp.tests] == [t.id for t in small_plan()]
    assert [t.scenario for t in camp.tests] == [t.scenario for t in small_plan()]
    assert [t.id for t in camp.control_tests()] == ["tg_sine"]
    assert camp.known == pytest.approx(KNOWN)
    allowed = set(NOISE_RMS) | {"time_s"}
    for spec in camp.tests:
        frame = camp.frame(spec.id)
        assert set(frame.columns) <= allowed
        assert camp.sample_time_s(spec.id) == pytest.approx(1.0 / 500.0)
    assert "rack_position_m" not in camp.frame("bc_sine").columns
    assert "tie_rod_force_left_n" in camp.frame("tg_sine").columns


def test_noise_level_and_offsets_on_flat_segment():
    """Before the motion every channel is flat: its std is the noise, its mean the offset."""
    tests = simulate_plan(recipe(sample_rate_hz=1000.0))
    pooled: dict[str, list[np.ndarray]] = {}
    for _, frame in tests:
        flat = frame[frame["time_s"] < LEAD_S - 0.05]
        for ch in frame.columns.drop("time_s"):
            pooled.setdefault(ch, []).append(flat[ch].to_numpy() - flat[ch].mean())
            offset = DEMO_OFFSETS.get(f"offset.{ch}", 0.0)
            # a campaign-wide offset: the same in every test (within 5 σ of the mean)
            assert flat[ch].mean() == pytest.approx(
                offset, abs=5 * NOISE_RMS[ch] / np.sqrt(len(flat))), ch
    assert {"steering_angle_rad", "steering_torque_nm", "rack_position_m",
            "tie_rod_force_left_n"} <= set(pooled)
    for ch, parts in pooled.items():
        std = np.std(np.concatenate(parts), ddof=len(parts))
        assert std == pytest.approx(NOISE_RMS[ch], rel=0.2), ch


def test_noise_scale_scales_the_noise():
    _, f1 = simulate_plan(recipe())[0]
    _, f0 = simulate_plan(recipe(noise_scale=0.0))[0]
    _, f3 = simulate_plan(recipe(noise_scale=3.0))[0]
    d1 = (f1["steering_torque_nm"] - f0["steering_torque_nm"]).to_numpy()
    d3 = (f3["steering_torque_nm"] - f0["steering_torque_nm"]).to_numpy()
    np.testing.assert_allclose(d3, 3.0 * d1, rtol=1e-9, atol=1e-12)


# --------------------------------------------------------------------------------------
# The CLI
# --------------------------------------------------------------------------------------


@pytest.fixture
def fast_demo(monkeypatch):
    """The CLI always runs the demo plan; a short one keeps these tests fast."""
    monkeypatch.setattr(bench, "demo_plan", small_plan)


def test_cli_sensors_adds_motor_angle(fast_demo, tmp_path, capsys):
    sensors = ",".join(DEFAULT_SENSORS + ("motor_angle_rad",))
    assert main(["bench", "--out", str(tmp_path / "with"), "--sensors", sensors, "-q"]) == 0
    assert main(["bench", "--out", str(tmp_path / "without"), "-q"]) == 0
    assert capsys.readouterr().out == ""
    with_motor = read_campaign(tmp_path / "with" / "campaign")
    without = read_campaign(tmp_path / "without" / "campaign")
    for spec in with_motor.tests:
        cols_with = set(with_motor.frame(spec.id).columns)
        cols_without = set(without.frame(spec.id).columns)
        assert "motor_angle_rad" not in cols_without
        if spec.scenario == "blocked_column":
            assert cols_with == cols_without  # no motor on a blocked column
        else:
            assert cols_with == cols_without | {"motor_angle_rad"}


def test_cli_reduced_sensors_never_write_an_invalid_campaign(fast_demo, tmp_path):
    rc = main(["bench", "--out", str(tmp_path), "--sensors",
               "steering_angle_rad,steering_torque_nm", "-q"])
    if rc == 0:
        read_campaign(tmp_path / "campaign")
    else:
        assert rc == 2


@pytest.mark.parametrize(
    "bad",
    [
        "nonsense:worm_gear",
        "backlash:tires",
        "backlash",
        "backlash:worm_gear:width=0.01",
        "backlash:worm_gear:width_rad=wide",
    ],
)
def test_cli_rejects_bad_effect(fast_demo, tmp_path, capsys, bad):
    out = tmp_path / "out"
    assert main(["bench", "--out", str(out), "--effect", bad]) == 2
    captured = capsys.readouterr()
    assert captured.out == ""
    err = captured.err.strip()
    assert err.startswith("mbst bench: error:")
    assert "\n" not in err
    assert "Traceback" not in err
    assert not out.exists()  # validated before anything is written


@pytest.mark.parametrize(("flags", "named"), [
    (["--plan-jitter", "2"], "--plan-jitter must be in [0, 1)"),  # was a bare IndexError
    (["--cogging-nm", "15"], "--cogging-nm must be in [-0.5, 0.5]"),  # N·m, not mN·m
    (["--friction-drift", "1.5"], "--friction-drift must be in [0, 1)"),
    (["--oversample", "0"], "--oversample must be in [1, 1000]"),
    (["--realistic", "--torque-lag-s", "-0.003"], "--torque-lag-s must be in [0, 1)"),
    # a bare ZeroDivisionError; a campaign of NaN noise
    (["--sample-rate-hz", "0"], "--sample-rate-hz must be a finite rate > 0 Hz"),
    (["--noise-scale", "nan"], "--noise-scale must be a finite factor ≥ 0"),
])
def test_a_realism_flag_outside_what_it_means_is_refused_by_name(tmp_path, capsys, flags,
                                                                 named):
    """Each flag was taken as given: a 15 N·m cogging ran a 50-minute discovery on a rig
    whose base model scored −4751 % control FIT, a plan jitter of 2 died in numpy."""
    out = tmp_path / "out"
    assert main(["bench", "--out", str(out), "--plan", "compact", *flags]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"mbst bench: error: {named}") and "Traceback" not in err
    assert not out.exists()


def test_a_random_input_is_band_limited_seeded_and_a_campaign(tmp_path):
    """campaign-format.md lists ``random`` among the input kinds and the bench refused it,
    so a campaign with such tests could not be re-run (``--tests-from``). A band-limited
    random input: the same entry gives the same angle, its peak is the amplitude, its power
    lies in the band, and a campaign of it reads back."""
    spec = {"kind": "random", "amplitude_deg": 30, "f0_hz": 0.05, "f1_hz": 0.6,
            "duration_s": 20, "seed": 3}
    t, ang = bench.input_profile(spec, 1000.0)
    assert np.array_equal(ang, bench.input_profile(dict(spec), 1000.0)[1])
    assert not np.array_equal(ang, bench.input_profile({**spec, "seed": 4}, 1000.0)[1])
    assert np.degrees(np.abs(ang).max()) == pytest.approx(30.0)
    assert ang[0] == 0.0 and ang[-1] == 0.0 and t[-1] == pytest.approx(21.0, abs=2e-3)
    power = np.abs(np.fft.rfft(ang)) ** 2
    freq = np.fft.rfftfreq(len(ang), 1e-3)
    assert power[freq > 0.7].sum() < 1e-3 * power.sum()
    with pytest.raises(ValueError, match="f0_hz <= f1_hz"):
        bench.input_profile({**spec, "f0_hz": 1.0}, 1000.0)
    plan = [PlannedTest("ft_random", "free_tie_rods", spec),
            PlannedTest("bc_sine", "blocked_column",
                        {"kind": "sine", "amplitude_deg": 5, "frequency_hz": 1.0, "cycles": 2})]
    camp = read_campaign(run_bench(tmp_path, BenchRecipe(effects=[], plan=plan)))
    assert camp.tests[0].input["kind"] == "random"
    measured = camp.frame("ft_random")["steering_angle_rad"].to_numpy()
    assert np.degrees(np.abs(measured).max()) == pytest.approx(30.0, abs=0.5)


def test_a_rig_that_diverges_writes_no_campaign_and_says_where(tmp_path, capsys):
    """An HPS curve (gain c1·e^|T|) past a torsion-bar stop makes the powered loop unstable
    and the model has no motor torque limit: the bench wrote a campaign of NaNs, which
    discovery then refused row by row. Now it refuses, naming the test and the instant."""
    plan = [t for t in bench.compact_assist_plan() if t.id == "on_loaded_1hz_normal_60kph"]
    recipe = BenchRecipe(effects=["stiffness_limit_stop:torsion_bar"], plan=plan,
                         assist_characteristic="hps")
    with pytest.raises(ValueError, match=r"test 'on_loaded_1hz_normal_60kph' "
                       r"\(tires_on_ground\): the simulated rig diverged at t = 1\.1\d\d s"):
        run_bench(tmp_path / "run", recipe)
    assert not (tmp_path / "run").exists()
    # ... the same through the command: one line, exit 2, nothing written
    out = tmp_path / "cli"
    assert main(["bench", "--out", str(out), "--plan", "compact-assist",
                 "--assist-characteristic", "hps", "--effect", "stiffness_limit_stop:torsion_bar",
                 "-q"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("mbst bench: error: test 'on_loaded_") and "\n" not in err, err
    assert "assist" in err and not out.exists()
    # the same plan with the eps curve is a campaign
    recipe = BenchRecipe(effects=["stiffness_limit_stop:torsion_bar"], plan=plan)
    assert read_campaign(run_bench(tmp_path / "eps", recipe)).tests


# --------------------------------------------------------------------------------------
# A bench that is not the model (issue #30): drawn rigs, off-grid sizes, real sensors
# --------------------------------------------------------------------------------------


def test_coloured_noise_keeps_its_rms_and_wanders():
    rng = np.random.default_rng(0)
    e = coloured_noise(200_000, 0.3, 0.9, rng)
    assert np.std(e) == pytest.approx(0.3, rel=0.03)
    assert np.corrcoef(e[:-1], e[1:])[0, 1] == pytest.approx(0.9, abs=0.01)
    white = coloured_noise(200_000, 0.3, 0.0, rng)
    assert abs(np.corrcoef(white[:-1], white[1:])[0, 1]) < 0.01


def test_sensor_lags_counts_in_steps_and_drifts():
    t = np.arange(0.0, 2.0, 1e-3)
    step = (t > 0.5).astype(float)
    rng = np.random.default_rng(0)
    lagged = measure(step, t, 0.0, rng, SensorRealities(lag_s=0.01))
    k = np.searchsorted(t, 0.51)  # one time constant after the step: 1 − e⁻¹ of the way
    assert lagged[k] == pytest.approx(1 - np.exp(-1), abs=0.05)
    counted = measure(np.sin(t), t, 0.01, rng, SensorRealities(quantum=0.05))
    np.testing.assert_allclose(counted / 0.05, np.round(counted / 0.05), atol=1e-9)
    drifted = measure(np.zeros_like(t), t, 0.1, rng,
                      SensorRealities(drift=2.0, drift_tau_s=1.0), campaign_time_s=100.0)
    assert np.mean(drifted) == pytest.approx(0.2, abs=0.02)  # long warmed up: 2 rms


def test_plain_bench_realism_is_off():
    """The default recipe is the plain bench: seed 000's rig and the catalogue sizes."""
    r = recipe(effects=["backlash:worm_gear"])
    assert r.rig_values() == {**bench.DEMO_RIG, **DEMO_OFFSETS}
    assert r.known() == KNOWN
    assert r.effect_values()[0][1] == EFFECTS["backlash:worm_gear"].default_size


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_drawn_rig_lies_in_the_typical_ranges_and_differs_per_seed(seed):
    rig = recipe(seed, realism=BenchRealism.realistic()).rig_values()
    other = recipe(seed + 10, realism=BenchRealism.realistic()).rig_values()
    for name, (lo, hi, _) in RIG_RANGES.items():
        assert lo <= rig[name] <= hi, name
        assert rig[name] != other[name], name
    # friction regularisation of the bench is not identification's
    veps = "rack.regularisation_velocity_m_per_s"
    assert rig[veps] == pytest.approx(0.5 * EPS_MODEL.vector_from({})[EPS_MODEL.param_index[veps]])


def test_known_values_are_written_off_by_at_most_the_error():
    r = recipe(3, realism=BenchRealism.realistic(known_error=0.15))
    true = {k: r.rig_values()[k] for k in KNOWN}
    written = r.known()
    rel = {k: written[k] / true[k] - 1 for k in KNOWN}
    assert all(abs(v) <= 0.15 for v in rel.values())
    assert max(abs(rel[k]) for k in ("column_inertia_kgm2", "motor_inertia_kgm2",
                                     "wheel_mass_kg")) > 0.01
    assert abs(rel["worm_gear_ratio"]) <= 0.015  # geometry comes from drawings


def test_drawn_effect_sizes_are_off_the_catalogue_default_and_keep_what_is_given():
    widths = []
    for seed in range(8):
        r = recipe(seed, effects=["backlash:worm_gear", "stribeck_friction:rack:"
                                  "static_to_coulomb_ratio=1.3"],
                   realism=BenchRealism(draw_sizes=True))
        (_, backlash), (_, stribeck) = r.effect_values()
        widths.append(backlash["worm_gear.backlash.width_rad"])
        assert stribeck["rack.stribeck_friction.static_to_coulomb_ratio"] == 1.3
    assert all(0.005 <= w <= 0.035 for w in widths)
    assert len(set(widths)) == len(widths)
    assert EFFECTS["backlash:worm_gear"].default_size["worm_gear.backlash.width_rad"] not in widths


def test_realistic_channels_are_quantised_lagged_and_written_to_truth(tmp_path):
    r = recipe(2, effects=[], realism=BenchRealism.realistic())
    camp = read_campaign(run_bench(tmp_path, r))
    truth = json.loads((tmp_path / "truth.json").read_text())
    assert truth["realism"]["quantise"] and truth["realism"]["torque_lag_s"] > 0
    assert camp.known == pytest.approx(truth["known_written"])
    frame = pd.read_csv(tmp_path / "campaign" / "tests" / "bc_sine.csv")
    q = SENSOR_QUANTUM["steering_torque_nm"]
    np.testing.assert_allclose(frame["steering_torque_nm"] / q,
                               np.round(frame["steering_torque_nm"] / q), atol=1e-6)
    # the bench integrates on its own grid: without noise it is not identification's twin
    quiet = recipe(2, effects=[], noise_scale=0.0,
                   realism=BenchRealism(oversample=3, smoothing=0.5))
    spec, frame = simulate_plan(quiet)[1]
    sim = eps.simulate(spec.scenario, spec.motor, frame["time_s"].to_numpy(),
                       frame["steering_angle_rad"].to_numpy(), quiet.true_params())
    assert not np.allclose(sim["steering_torque_nm"], frame["steering_torque_nm"], atol=1e-9)
