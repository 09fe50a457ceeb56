"""Tests of the virtual test bench: determinism, hidden truth, noise, the ``mbst bench`` CLI."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from mbst.cli import main
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
