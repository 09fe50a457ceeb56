"""`mbst preprocess`: the written data is what the fit compares, and cannot be filtered twice."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from mbst.cli import main
from mbst.core.filtering import exponential_filter
from mbst.identify.fitting import prepare_test
from mbst.io.campaign import CampaignError, read_campaign
from mbst.systems.eps.bench import NOISE_RMS, BenchRecipe, PlannedTest, run_bench

TAU_S = 0.005


@pytest.fixture(scope="module")
def raw_campaign(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("raw")
    plan = [
        PlannedTest("bc_sine", "blocked_column",
                    {"kind": "sine", "amplitude_deg": 5, "frequency_hz": 1.0, "cycles": 2}),
        PlannedTest("tg_sine", "tires_on_ground",
                    {"kind": "sine", "amplitude_deg": 100, "frequency_hz": 1.0, "cycles": 2},
                    role="control"),
    ]
    run_bench(out, BenchRecipe(effects=[], seed=3, plan=plan, name="pre-test"))
    return out / "campaign"


@pytest.fixture(scope="module")
def preprocessed(raw_campaign, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("pre") / "preprocess"
    assert main(["preprocess", str(raw_campaign), "--out", str(out), "--tau", str(TAU_S),
                 "-q"]) == 0
    return out


def test_written_channels_are_what_the_fit_compares(raw_campaign, preprocessed):
    raw = read_campaign(raw_campaign)
    done = read_campaign(preprocessed / "campaign")
    assert [t.id for t in done.tests] == [t.id for t in raw.tests]
    assert [t.role for t in done.tests] == [t.role for t in raw.tests]
    for spec in raw.tests:
        pt = prepare_test(raw, spec, TAU_S)
        frame = done.frame(spec.id)
        for ch, y in pt.measured.items():
            np.testing.assert_allclose(frame[ch].to_numpy(), y, rtol=0, atol=1e-12)
        np.testing.assert_allclose(frame["model_input"].to_numpy(), pt.input_signal, atol=1e-15)
        # the input channel gets the very same filter as every other channel
        angle = raw.frame(spec.id)["steering_angle_rad"].to_numpy()
        dt = pt.dt_s
        np.testing.assert_allclose(frame["steering_angle_rad"].to_numpy(),
                                   exponential_filter(angle, dt, TAU_S), atol=1e-15)
    # the filter really smoothed: on the slow blocked-column sine the sample-to-sample
    # jitter of the torque is sensor noise, and it drops
    torque_raw = raw.frame("bc_sine")["steering_torque_nm"].to_numpy()
    torque = done.frame("bc_sine")["steering_torque_nm"].to_numpy()
    assert np.std(np.diff(torque, 2)) < 0.3 * np.std(np.diff(torque_raw, 2))


def test_noise_table_recovers_the_bench_sensor_noise(preprocessed):
    table = pd.read_csv(preprocessed / "noise.csv")
    assert set(table["test"]) == {"bc_sine", "tg_sine"}
    for row in table.itertuples():
        assert row.noise_std_filtered < 0.6 * row.noise_std_raw
    # On a slow test the estimate is the sensor noise; on the fast 1 Hz, 100° control
    # test a 0.1 s local cubic also leaves out real fast dynamics, so it reads high.
    slow = table[table["test"] == "bc_sine"].set_index("channel")
    assert slow.loc["steering_torque_nm", "noise_std_raw"] == pytest.approx(
        NOISE_RMS["steering_torque_nm"], rel=0.2)
    text = (preprocessed / "preprocess.md").read_text()
    assert "| tg_sine | control | tie_rod_force_left_n |" in text
    # the report shows the HTML rendering of the same table inline
    html = (preprocessed / "preprocess.html").read_text()
    assert html.count("<tr>") == len(table) + 1
    assert "<td>tg_sine</td>\n<td>control</td>\n<td>tie_rod_force_left_n</td>" in html
    assert (preprocessed / "figures" / "filter.png").stat().st_size > 10_000


def test_fitting_a_preprocessed_campaign_again_is_refused(preprocessed, capsys):
    done = read_campaign(preprocessed / "campaign")
    with pytest.raises(CampaignError, match="already filtered"):
        prepare_test(done, done.tests[0], TAU_S)
    prepare_test(done, done.tests[0], 0.0)  # τ = 0: no second filter, allowed
    assert main(["identify", str(preprocessed / "campaign"), "--out",
                 str(preprocessed.parent / "ident"), "-q"]) == 2
    err = capsys.readouterr().err
    assert "campaign.yaml" in err and "already filtered" in err and "--tau 0" in err
    assert not (preprocessed.parent / "ident").exists()


def test_bad_campaign_leaves_nothing_behind(tmp_path, capsys):
    out = tmp_path / "pre"
    assert main(["preprocess", str(tmp_path / "missing"), "--out", str(out), "-q"]) == 2
    assert "mbst preprocess: error:" in capsys.readouterr().err
    assert not out.exists()
