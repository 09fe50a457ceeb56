"""Tests for mbst.io.campaign: reading, validation, writing and the summary."""

from __future__ import annotations

import pickle
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml

from mbst.core.family import get_system, known_systems
from mbst.io.campaign import (
    Campaign,
    CampaignError,
    TestSpec,
    read_campaign,
    summarize_campaign,
    write_campaign,
)

SYSTEM = "eps-column-assist"
NAME = "demo-eps"
N = 200
DT = 1e-3


def make_frame(scenario: str, n: int = N, seed: int = 0) -> pd.DataFrame:
    """Made-up data with every channel the family requires for ``scenario``.

    Channel names come from the family, so the tests follow its table.
    """
    rng = np.random.default_rng(seed)
    family = get_system(SYSTEM)
    t = np.arange(n) * DT
    cols: dict[str, np.ndarray] = {family.time_channel: t}
    angle = 0.5 * np.sin(2 * np.pi * 2.0 * t)
    for name in family.required_channels(scenario):
        if name == family.time_channel:
            continue
        if name == family.input_channel:
            cols[name] = angle
        else:
            cols[name] = 3.0 * angle + 0.01 * rng.standard_normal(n)
    return pd.DataFrame(cols)


def make_specs() -> list[TestSpec]:
    family = get_system(SYSTEM)
    blocked, free = family.scenarios[0], family.scenarios[1]
    connected = family.scenarios[-1]
    return [
        TestSpec(
            id="s1_sine",
            file="tests/s1_sine.csv",
            scenario=blocked,
            input={"kind": "sine", "amplitude_deg": 30, "frequency_hz": 2.0},
            motor="passive",
            role="identification",
        ),
        TestSpec(
            id="s2_sine",
            file="tests/s2_sine.csv",
            scenario=free,
            input={"kind": "sine", "amplitude_deg": 30, "frequency_hz": 2.0},
            motor="passive",
            role="identification",
        ),
        TestSpec(
            id="s3_ctrl",
            file="tests/s3_ctrl.csv",
            scenario=connected,
            input={"kind": "sweep", "f0_hz": 0.1, "f1_hz": 5.0},
            motor="assist",
            role="control",
            vehicle_speed_kph=50.0,
            assist_mode="city",
        ),
    ]


def build(tmp_path: Path, fmt: str = "csv", name: str = NAME) -> Path:
    """Write a small valid campaign and return its directory."""
    specs = make_specs()
    tests = [(s, make_frame(s.scenario, seed=i)) for i, s in enumerate(specs)]
    known = {"pinion_radius_m": 0.0075, "worm_gear_ratio": 16.5}
    return write_campaign(
        tmp_path / "camp", name=name, system=SYSTEM, known=known, tests=tests, fmt=fmt
    )


def load_yaml(camp: Path) -> dict:
    return yaml.safe_load((camp / "campaign.yaml").read_text())


def save_yaml(camp: Path, doc: dict) -> None:
    (camp / "campaign.yaml").write_text(yaml.safe_dump(doc, sort_keys=False))


def edit_test(camp: Path, test_id: str, **changes) -> None:
    doc = load_yaml(camp)
    for entry in doc["tests"]:
        if entry["id"] == test_id:
            for key, value in changes.items():
                if value is None:
                    entry.pop(key, None)
                else:
                    entry[key] = value
    save_yaml(camp, doc)


def edit_csv(camp: Path, test_id: str, fn) -> None:
    path = camp / "tests" / f"{test_id}.csv"
    df = pd.read_csv(path)
    df = fn(df)
    df.to_csv(path, index=False)


def error(camp: Path) -> CampaignError:
    with pytest.raises(CampaignError) as info:
        read_campaign(camp)
    msg = str(info.value)
    assert "\n" not in msg
    assert "Traceback" not in msg
    return info.value


def family():
    return get_system(SYSTEM)


# --------------------------------------------------------------------------- happy path


def test_read_valid_campaign(tmp_path):
    camp = build(tmp_path)
    c = read_campaign(camp)
    assert isinstance(c, Campaign)
    assert c.name == NAME and c.system == SYSTEM
    assert c.path == camp
    assert c.known == {"pinion_radius_m": 0.0075, "worm_gear_ratio": 16.5}
    assert [s.id for s in c.tests] == ["s1_sine", "s2_sine", "s3_ctrl"]
    assert set(c.data) == {"s1_sine", "s2_sine", "s3_ctrl"}
    assert [s.id for s in c.identification_tests()] == ["s1_sine", "s2_sine"]
    assert [s.id for s in c.control_tests()] == ["s3_ctrl"]
    assert c.test("s3_ctrl").vehicle_speed_kph == 50.0
    assert c.sample_time_s("s1_sine") == pytest.approx(DT)


def test_accepts_yaml_path(tmp_path):
    camp = build(tmp_path)
    c = read_campaign(camp / "campaign.yaml")
    assert c.path == camp
    assert len(c.tests) == 3


def test_lazy_loading(tmp_path):
    camp = build(tmp_path)
    c = read_campaign(camp, load_data=False)
    assert c.data == {}
    df = c.frame("s2_sine")
    assert len(df) == N
    assert set(c.data) == {"s2_sine"}


def test_lazy_loading_still_validates(tmp_path):
    camp = build(tmp_path)
    edit_csv(camp, "s2_sine", lambda df: df.iloc[:50])
    c = read_campaign(camp, load_data=False)
    with pytest.raises(CampaignError, match="50 samples"):
        c.frame("s2_sine")


def test_unknown_test_id(tmp_path):
    c = read_campaign(build(tmp_path))
    with pytest.raises(CampaignError) as info:
        c.test("nope")
    assert "nope" in str(info.value) and "s1_sine" in str(info.value)


def test_error_str_names_every_piece():
    err = CampaignError(
        "value is NaN",
        campaign="demo-eps",
        test="s2_sine",
        column="steering_torque_nm",
        row=17,
        path="tests/s2_sine.csv",
    )
    assert str(err) == (
        "campaign 'demo-eps', test 's2_sine', file tests/s2_sine.csv, "
        "column 'steering_torque_nm', row 17: value is NaN"
    )
    assert str(CampaignError("plain\nmessage")) == "plain message"
    again = pickle.loads(pickle.dumps(err))
    assert str(again) == str(err) and again.row == 17


@pytest.mark.parametrize("fmt", ["csv", "parquet"])
def test_round_trip(tmp_path, fmt):
    specs = make_specs()
    specs[0].extra = {"operator": "jd", "notes": {"temp_c": 21.5}}
    frames = [make_frame(s.scenario, seed=i) for i, s in enumerate(specs)]
    frames[1]["lab_temperature_c"] = np.linspace(20.1, 21.3, N)
    camp = write_campaign(
        tmp_path / "rt",
        name=NAME,
        system=SYSTEM,
        known={"wheel_mass_kg": 80.0, "motor_inertia_kgm2": np.float64(4.5e-5)},
        tests=list(zip(specs, frames)),
        extra={"site": "bench 3", "date": "2024-05-01"},
        fmt=fmt,
    )
    c = read_campaign(camp)
    expected = [TestSpec(**{**s.__dict__, "file": f"tests/{s.id}.{fmt}"}) for s in specs]
    assert c.tests == expected
    assert c.known == {"wheel_mass_kg": 80.0, "motor_inertia_kgm2": 4.5e-5}
    assert c.extra == {"site": "bench 3", "date": "2024-05-01"}
    for spec, frame in zip(specs, frames):
        pd.testing.assert_frame_equal(c.frame(spec.id), frame, check_exact=True)
    doc = load_yaml(camp)
    assert doc["format"] == "mbst-campaign/1"
    assert list(doc)[:3] == ["format", "name", "system"]
    assert [t["id"] for t in doc["tests"]] == [s.id for s in specs]
    assert "vehicle_speed_kph" not in doc["tests"][0]
    assert doc["tests"][2]["assist_mode"] == "city"


def test_write_refuses_existing_without_overwrite(tmp_path):
    camp = build(tmp_path)
    with pytest.raises(CampaignError, match="already exists"):
        build(tmp_path)
    assert read_campaign(camp).name == NAME


def test_write_overwrite_replaces_and_cleans_up(tmp_path):
    camp = build(tmp_path)
    (camp / "stale.txt").write_text("old")
    spec = make_specs()[0]
    write_campaign(
        camp,
        name="second",
        system=SYSTEM,
        known={},
        tests=[(spec, make_frame(spec.scenario))],
        overwrite=True,
    )
    c = read_campaign(camp)
    assert c.name == "second" and [s.id for s in c.tests] == [spec.id]
    assert not (camp / "stale.txt").exists()
    # No temporary or backup siblings are left behind.
    assert sorted(p.name for p in tmp_path.iterdir()) == ["camp"]


def test_write_failure_leaves_nothing(tmp_path):
    spec = make_specs()[0]
    with pytest.raises(CampaignError):
        write_campaign(
            tmp_path / "bad",
            name=NAME,
            system=SYSTEM,
            known={},
            tests=[(spec, make_frame(spec.scenario))],
            extra={"unrepresentable": object()},
        )
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("bad", ["../s2/ramp", ".hidden", "a:b"])
def test_read_rejects_a_path_like_id(tmp_path, bad):
    """The id names the test's outputs: `check` and `identify` passed '../s2/ramp' and only
    `preprocess` refused it (found 2026-11-28)."""
    camp = build(tmp_path)
    edit_test(camp, "s1_sine", id=bad)
    msg = str(error(camp))
    assert f"test '{bad}'" in msg and "file name" in msg


def test_write_rejects_path_like_id(tmp_path):
    spec = make_specs()[0]
    spec.id = "../escape"
    with pytest.raises(CampaignError, match="file name"):
        write_campaign(
            tmp_path / "c",
            name=NAME,
            system=SYSTEM,
            known={},
            tests=[(spec, make_frame(spec.scenario))],
        )


def test_unknown_keys_preserved(tmp_path):
    camp = build(tmp_path)
    doc = load_yaml(camp)
    doc["operator"] = "J. Doe"
    doc["rig"] = {"id": 7}
    doc["tests"][1]["comment"] = "after re-zeroing"
    doc["tests"][1]["input"]["phase_deg"] = 90
    save_yaml(camp, doc)
    c = read_campaign(camp)
    assert c.extra == {"operator": "J. Doe", "rig": {"id": 7}}
    assert c.test("s2_sine").extra == {"comment": "after re-zeroing"}
    assert c.test("s2_sine").input["phase_deg"] == 90


def test_extra_columns_kept(tmp_path):
    camp = build(tmp_path)
    optional = [c.name for c in family().channels if not c.required_in]
    edit_csv(camp, "s1_sine", lambda df: df.assign(daq_status=1, **{optional[0]: 0.5}))
    df = read_campaign(camp).frame("s1_sine")
    assert "daq_status" in df.columns and optional[0] in df.columns
    assert df[optional[0]].dtype == np.float64


def test_summary_mentions_every_test(tmp_path):
    c = read_campaign(build(tmp_path))
    text = summarize_campaign(c)
    for spec in c.tests:
        assert spec.id in text
    assert NAME in text and SYSTEM in text and "pinion_radius_m" in text
    assert "1000.0" in text  # sample rate
    assert str(N) in text
    assert "WARNING" not in text


def test_summary_warns_without_control(tmp_path):
    camp = build(tmp_path)
    edit_test(camp, "s3_ctrl", role="identification")
    text = summarize_campaign(read_campaign(camp))
    assert "WARNING: no control test" in text
    assert "no identification test" not in text


def test_summary_warns_without_identification(tmp_path):
    camp = build(tmp_path)
    for tid in ("s1_sine", "s2_sine"):
        edit_test(camp, tid, role="control")
    text = summarize_campaign(read_campaign(camp))
    assert "WARNING: no identification test" in text



def test_summary_warns_of_a_test_whose_input_barely_moves(tmp_path):
    """A control test held at one angle, and a 0.24-s fragment of a sine under a 13-bit
    encoder (4 steps of it): a model's FIT there reads the noise, and `mbst check` says so
    before anything is fitted."""
    camp = build(tmp_path)
    q = 2 * np.pi / 2**13

    def still(df):
        df["steering_angle_rad"] = 0.1
        return df

    def fragment(df):
        df["steering_angle_rad"] = q * np.round(np.linspace(0.0, 4.0, len(df)))
        return df

    edit_csv(camp, "s3_ctrl", still)
    edit_csv(camp, "s2_sine", fragment)
    text = summarize_campaign(read_campaign(camp))
    assert "WARNING: test 's3_ctrl'" in text and "stays at one value" in text
    assert "WARNING: test 's2_sine'" in text and "4.0×" in text
    assert "WARNING: test 's1_sine'" not in text



def test_a_time_column_in_milliseconds_is_said(tmp_path):
    """A test logged at 500 Hz with its time in ms reads as 0.5 Hz and 1000x as long:
    `mbst check` passed it and identification was still fitting after 10 minutes (found
    2026-11-28). Both now say so; the other tests stay quiet."""
    from mbst.identify.cascade import prepare_campaign

    camp = build(tmp_path)

    def in_ms(df):
        df["time_s"] *= 1000.0
        return df

    edit_csv(camp, "s2_sine", in_ms)
    said = [ln for ln in summarize_campaign(read_campaign(camp)).splitlines() if "too slow" in ln]
    assert len(said) == 1 and "test 's2_sine'" in said[0] and "in seconds" in said[0], said
    _, warnings = prepare_campaign(read_campaign(camp), 0.005)
    assert [w for w in warnings if "too slow" in w] == [said[0].removeprefix("WARNING: ")]


def test_a_time_step_of_a_nanosecond_and_an_unknown_input_kind_are_said(tmp_path):
    """A '0.8 Hz sine' lasting 3 µs fitted without a word, and `sawtooth` (no kind of the
    spec) passed silently (found 2026-11-28); the data is still read."""
    camp = build(tmp_path)

    def in_ns(df):
        df["time_s"] *= 1e-6
        return df

    edit_csv(camp, "s2_sine", in_ns)
    edit_test(camp, "s1_sine", input={"kind": "sawtooth", "amplitude_deg": 30})
    warned = [ln for ln in summarize_campaign(read_campaign(camp)).splitlines()
              if ln.startswith("WARNING")]
    assert len(warned) == 2, warned
    assert any("test 's2_sine'" in w and "faster than any rig's logger" in w for w in warned)
    assert any("test 's1_sine'" in w and "input kind 'sawtooth'" in w for w in warned)


def test_a_glitch_of_one_to_three_samples_is_named_and_a_step_is_not(tmp_path):
    """One 100 rad sample in a ±0.5 rad angle passed `mbst check` and took the control
    torque FIT from 85 to 29 % without a word (found 2026-11-28). `check` and
    identification's warnings now name it, and a burst of two or three such samples (a
    dropped word; the single-sample check saw none, each bad sample's neighbour being bad
    too); a step of the input, as large, is no glitch."""
    from mbst.identify.cascade import prepare_campaign

    camp = build(tmp_path)

    def glitch(df):
        df.loc[99, "steering_angle_rad"] = 100.0  # data row 100
        return df

    def step(df):
        df.loc[100:, "steering_angle_rad"] += 100.0
        return df

    def burst(df):
        df.loc[[49, 50], "steering_torque_nm"] = -500.0  # data rows 50 and 51
        df.loc[[149, 150, 151], "steering_torque_nm"] = [300.0, 320.0, 310.0]  # rows 150-152
        return df

    edit_csv(camp, "s2_sine", glitch)
    edit_csv(camp, "s1_sine", step)
    text = summarize_campaign(read_campaign(camp))
    said = [ln for ln in text.splitlines() if "far off its neighbours" in ln]
    assert len(said) == 1, said
    assert "test 's2_sine'" in said[0] and "'steering_angle_rad', row 100" in said[0]
    _, warnings = prepare_campaign(read_campaign(camp), 0.005)
    assert [w for w in warnings if "far off" in w] == [said[0].removeprefix("WARNING: ")]

    edit_csv(camp, "s1_sine", burst)
    said = [ln for ln in summarize_campaign(read_campaign(camp)).splitlines()
            if "far off its neighbours" in ln and "s1_sine" in ln]
    assert len(said) == 1, said
    assert "'steering_torque_nm', row 50" in said[0] and "(and 1 more)" in said[0]


# --------------------------------------------------------------------------- campaign.yaml errors


def test_missing_campaign_yaml(tmp_path):
    camp = build(tmp_path)
    (camp / "campaign.yaml").unlink()
    err = error(camp)
    assert "missing campaign.yaml" in str(err)
    assert str(camp) in str(err)


def test_missing_directory(tmp_path):
    err = error(tmp_path / "nowhere")
    assert "nowhere" in str(err)


def test_a_key_given_twice_is_refused_with_its_line(tmp_path):
    """PyYAML keeps the last of two equal keys: a control test's second `role:` line made it
    an identification test without a word (found 2026-11-28)."""
    camp = build(tmp_path)
    lines = (camp / "campaign.yaml").read_text().splitlines()
    at = next(i for i, ln in enumerate(lines) if ln.strip() == "role: control")
    lines.insert(at + 1, lines[at].replace("control", "identification"))
    (camp / "campaign.yaml").write_text("\n".join(lines) + "\n")
    msg = str(error(camp))
    assert "key 'role' is given twice" in msg and f"line {at + 2}" in msg


def test_yaml_does_not_parse(tmp_path):
    camp = build(tmp_path)
    text = (camp / "campaign.yaml").read_text().splitlines()
    text.insert(2, "bad: [unclosed")
    (camp / "campaign.yaml").write_text("\n".join(text) + "\n")
    err = error(camp)
    assert "YAML does not parse" in str(err)
    assert "line " in str(err)
    assert "campaign.yaml" in str(err)


def test_top_level_not_mapping(tmp_path):
    camp = build(tmp_path)
    (camp / "campaign.yaml").write_text("- a\n- b\n")
    assert "must be a mapping" in str(error(camp))


def test_empty_yaml(tmp_path):
    camp = build(tmp_path)
    (camp / "campaign.yaml").write_text("")
    assert "empty file" in str(error(camp))


def test_wrong_format(tmp_path):
    camp = build(tmp_path)
    doc = load_yaml(camp)
    doc["format"] = "mbst-campaign/2"
    save_yaml(camp, doc)
    msg = str(error(camp))
    assert "mbst-campaign/2" in msg and "mbst-campaign/1" in msg and NAME in msg


def test_missing_format(tmp_path):
    camp = build(tmp_path)
    doc = load_yaml(camp)
    del doc["format"]
    save_yaml(camp, doc)
    assert "missing key 'format'" in str(error(camp))


@pytest.mark.parametrize("key", ["name", "system", "tests"])
def test_missing_top_key(tmp_path, key):
    camp = build(tmp_path)
    doc = load_yaml(camp)
    del doc[key]
    save_yaml(camp, doc)
    assert f"missing key '{key}'" in str(error(camp))


def test_unknown_system(tmp_path):
    camp = build(tmp_path)
    doc = load_yaml(camp)
    doc["system"] = "hydraulic-rack"
    save_yaml(camp, doc)
    msg = str(error(camp))
    assert "hydraulic-rack" in msg and NAME in msg
    for name in known_systems():
        assert name in msg


def test_known_value_not_number(tmp_path):
    camp = build(tmp_path)
    doc = load_yaml(camp)
    doc["known"]["worm_gear_ratio"] = "sixteen"
    save_yaml(camp, doc)
    msg = str(error(camp))
    assert "worm_gear_ratio" in msg and "sixteen" in msg and NAME in msg


def test_known_not_mapping(tmp_path):
    camp = build(tmp_path)
    doc = load_yaml(camp)
    doc["known"] = [1, 2]
    save_yaml(camp, doc)
    assert "'known' must be a mapping" in str(error(camp))


def test_tests_not_list(tmp_path):
    camp = build(tmp_path)
    doc = load_yaml(camp)
    doc["tests"] = {"id": "x"}
    save_yaml(camp, doc)
    assert "'tests' must be a list" in str(error(camp))


def test_tests_empty(tmp_path):
    camp = build(tmp_path)
    doc = load_yaml(camp)
    doc["tests"] = []
    save_yaml(camp, doc)
    assert "'tests' is empty" in str(error(camp))


@pytest.mark.parametrize("key", ["file", "scenario", "role", "motor", "input"])
def test_test_missing_key(tmp_path, key):
    camp = build(tmp_path)
    edit_test(camp, "s2_sine", **{key: None})
    err = error(camp)
    msg = str(err)
    assert f"missing key '{key}'" in msg
    assert f"campaign '{NAME}'" in msg and "test 's2_sine'" in msg
    assert err.test == "s2_sine"


def test_test_missing_id_named_by_index(tmp_path):
    camp = build(tmp_path)
    doc = load_yaml(camp)
    del doc["tests"][1]["id"]
    save_yaml(camp, doc)
    msg = str(error(camp))
    assert "tests entry 2" in msg and "missing key 'id'" in msg and NAME in msg


def test_test_entry_not_mapping(tmp_path):
    camp = build(tmp_path)
    doc = load_yaml(camp)
    doc["tests"][0] = "s1_sine"
    save_yaml(camp, doc)
    assert "tests entry 1 must be a mapping" in str(error(camp))


def test_duplicate_test_id(tmp_path):
    camp = build(tmp_path)
    edit_test(camp, "s2_sine", id="s1_sine")
    msg = str(error(camp))
    assert "duplicate test id" in msg and "test 's1_sine'" in msg and NAME in msg


def test_unknown_scenario(tmp_path):
    camp = build(tmp_path)
    edit_test(camp, "s2_sine", scenario="upside_down")
    msg = str(error(camp))
    assert "upside_down" in msg and "test 's2_sine'" in msg and NAME in msg
    for scenario in family().scenarios:
        assert scenario in msg


def test_bad_role(tmp_path):
    camp = build(tmp_path)
    edit_test(camp, "s3_ctrl", role="validation")
    msg = str(error(camp))
    assert "validation" in msg and "identification" in msg and "test 's3_ctrl'" in msg


def test_bad_motor(tmp_path):
    camp = build(tmp_path)
    edit_test(camp, "s1_sine", motor="turbo")
    msg = str(error(camp))
    assert "turbo" in msg and "test 's1_sine'" in msg
    for mode in family().motor_modes:
        assert mode in msg


def test_input_not_mapping(tmp_path):
    camp = build(tmp_path)
    edit_test(camp, "s1_sine", input="sine")
    msg = str(error(camp))
    assert "'input' must be a mapping" in msg and "test 's1_sine'" in msg


def test_file_not_found(tmp_path):
    camp = build(tmp_path)
    (camp / "tests" / "s2_sine.csv").unlink()
    err = error(camp)
    msg = str(err)
    assert "not found" in msg and "test 's2_sine'" in msg and NAME in msg
    assert "s2_sine.csv" in msg
    assert Path(err.path) == camp / "tests" / "s2_sine.csv"


def test_file_not_found_even_without_loading(tmp_path):
    camp = build(tmp_path)
    edit_test(camp, "s2_sine", file="tests/elsewhere.csv")
    with pytest.raises(CampaignError, match="elsewhere.csv"):
        read_campaign(camp, load_data=False)


def test_bad_extension(tmp_path):
    camp = build(tmp_path)
    (camp / "tests" / "s1_sine.csv").rename(camp / "tests" / "s1_sine.txt")
    edit_test(camp, "s1_sine", file="tests/s1_sine.txt")
    msg = str(error(camp))
    assert "extension" in msg and ".txt" in msg and "test 's1_sine'" in msg


# --------------------------------------------------------------------------- data errors


def test_unreadable_file(tmp_path):
    camp = build(tmp_path)
    (camp / "tests" / "s1_sine.csv").write_text("")
    msg = str(error(camp))
    assert "test 's1_sine'" in msg and "s1_sine.csv" in msg and NAME in msg


def test_unreadable_parquet(tmp_path):
    camp = build(tmp_path, fmt="parquet")
    (camp / "tests" / "s1_sine.parquet").write_bytes(b"not parquet at all")
    msg = str(error(camp))
    assert "cannot read parquet" in msg and "test 's1_sine'" in msg


def test_non_numeric_cell(tmp_path):
    camp = build(tmp_path)
    col = family().input_channel

    def corrupt(df):
        df[col] = df[col].astype(object)
        df.loc[41, col] = "12,5"  # 0-based 41 -> data row 42
        return df

    edit_csv(camp, "s1_sine", corrupt)
    err = error(camp)
    msg = str(err)
    assert f"column '{col}'" in msg and "row 42" in msg and "'12,5'" in msg
    assert "test 's1_sine'" in msg and NAME in msg
    assert err.row == 42 and err.column == col


def test_missing_required_column(tmp_path):
    camp = build(tmp_path)
    fam = family()
    spec = make_specs()[2]
    col = fam.required_channels(spec.scenario)[-1]
    edit_csv(camp, spec.id, lambda df: df.drop(columns=[col]))
    msg = str(error(camp))
    assert f"column '{col}'" in msg and "missing column" in msg
    assert f"test '{spec.id}'" in msg and NAME in msg


def test_header_names_with_spaces_after_the_commas_are_read(tmp_path):
    camp = build(tmp_path)
    spec = make_specs()[1]
    path = camp / "tests" / f"{spec.id}.csv"
    lines = path.read_text().splitlines()
    path.write_text("\n".join([lines[0].replace(",", ", ")] + lines[1:]) + "\n")
    df = read_campaign(camp).frame(spec.id)
    assert set(family().required_channels(spec.scenario)) <= set(df.columns)


def test_a_file_not_separated_by_commas_is_named_as_such(tmp_path):
    camp = build(tmp_path)
    spec = make_specs()[1]
    path = camp / "tests" / f"{spec.id}.csv"
    path.write_text(path.read_text().replace(",", ";"))
    msg = str(error(camp))
    assert "missing column" in msg and f"test '{spec.id}'" in msg
    assert "looks separated by ';'" in msg


def test_optional_column_not_required(tmp_path):
    # The blocked-column scenario needs fewer channels than the others.
    fam = family()
    blocked = make_specs()[0].scenario
    others = set(fam.required_channels(make_specs()[1].scenario))
    assert set(fam.required_channels(blocked)) < others
    read_campaign(build(tmp_path))


@pytest.mark.parametrize(("bad", "word"), [(np.nan, "NaN"), (np.inf, "inf"), (-np.inf, "-inf")])
def test_non_finite_required(tmp_path, bad, word):
    camp = build(tmp_path)
    col = family().required_channels(make_specs()[1].scenario)[2]

    def corrupt(df):
        df.loc[16, col] = bad  # data row 17
        df.loc[30, col] = bad  # a later one must not be reported
        return df

    edit_csv(camp, "s2_sine", corrupt)
    err = error(camp)
    msg = str(err)
    assert f"column '{col}'" in msg and "row 17" in msg and f"value is {word}" in msg
    assert "test 's2_sine'" in msg and NAME in msg


@pytest.mark.parametrize("fill", [1e30, -9.9e37])
def test_a_loggers_fill_value_is_named_not_read_as_data(tmp_path, fill):
    """A logger writes 1e30 or 9.9e37 for a missing sample: finite, and a discovery on it
    ran past ten minutes (found 2026-11-28). It is refused where it sits."""
    camp = build(tmp_path)
    col = family().required_channels(make_specs()[1].scenario)[2]

    def corrupt(df):
        df.loc[41, col] = fill  # data row 42
        return df

    edit_csv(camp, "s2_sine", corrupt)
    msg = str(error(camp))
    assert f"column '{col}'" in msg and "row 42" in msg and "no measurement" in msg
    assert "test 's2_sine'" in msg


def test_a_control_that_reads_an_identification_tests_file_is_refused(tmp_path):
    camp = build(tmp_path)
    doc = load_yaml(camp)
    fitted = next(e for e in doc["tests"] if e["role"] == "identification")
    control = next(e for e in doc["tests"] if e["role"] == "control")
    control["file"] = "./" + fitted["file"]  # the same file, written another way
    save_yaml(camp, doc)
    msg = str(error(camp))
    assert f"test '{control['id']}'" in msg and f"identification test '{fitted['id']}'" in msg


@pytest.mark.parametrize(("key", "value", "words"), [
    ("pinion_radius_m", 0.0, "must be > 0"),
    ("wheel_mass_kg", -80.0, "must be > 0"),
    ("torsion_bar.stiffness_nm_per_rad", -80.0, "must be > 0"),
    ("column_inertia_kgm2", 2.1, "a unit slip?"),  # g·m² written as kg·m²
    ("pinion_radius_m", 7.5e-6, "a unit slip?"),
])
def test_a_known_value_no_rig_has_is_refused_naming_it(tmp_path, key, value, words):
    """Found 2026-11-28: a zero pinion radius and a negative torsion-bar stiffness passed
    `mbst check` and ended identification in a bare traceback; a 1e30 inertia fitted to a
    control FIT of −1398 % without a word."""
    camp = build(tmp_path)
    doc = load_yaml(camp)
    doc["known"][key] = value
    save_yaml(camp, doc)
    msg = str(error(camp))
    assert f"known value '{key}'" in msg and words in msg and "range" in msg


def test_a_known_value_at_the_edge_of_a_real_rig_is_read(tmp_path):
    camp = build(tmp_path)
    doc = load_yaml(camp)
    doc["known"].update(pinion_radius_m=0.012, wheel_mass_kg=400.0)  # a truck's rig
    save_yaml(camp, doc)
    assert read_campaign(camp).known["wheel_mass_kg"] == 400.0


@pytest.mark.parametrize(("edit", "words"), [
    (lambda lines: lines.__setitem__(42, lines[42] + ",5,6"),
     "row 42: 5 fields where the header has 3"),
    (lambda lines: lines.__setitem__(42, lines[42].replace(",", ",\udcb0", 1)),
     "row 42: not UTF-8 text (byte 0xb0)"),
    (lambda lines: lines.__setitem__(0, lines[0].replace("steering_angle_rad",
                                                         "steering_angle_rad,steering_torque_nm")
                                     + ",x"),
     "column 'steering_torque_nm': column given twice"),
])
def test_a_malformed_csv_line_is_named_by_its_row_or_column(tmp_path, edit, words):
    """A long row, a Latin-1 byte and a column named twice passed through pandas' own text
    without a row or column, or not at all (found 2026-11-28)."""
    camp = build(tmp_path)
    path = camp / "tests" / "s1_sine.csv"
    lines = path.read_text().splitlines()
    assert len(lines[0].split(",")) == 3  # time, angle, torque: a blocked-column test
    edit(lines)
    path.write_bytes(("\n".join(lines) + "\n").encode("utf-8", "surrogateescape"))
    msg = str(error(camp))
    assert "test 's1_sine'" in msg and words in msg, msg


def test_empty_cell_is_nan(tmp_path):
    camp = build(tmp_path)
    path = camp / "tests" / "s1_sine.csv"
    lines = path.read_text().splitlines()
    header = lines[0].split(",")
    col = header[-1]
    cells = lines[5].split(",")  # line 5 = data row 5
    cells[-1] = ""
    lines[5] = ",".join(cells)
    path.write_text("\n".join(lines) + "\n")
    msg = str(error(camp))
    assert f"column '{col}'" in msg and "row 5" in msg and "NaN" in msg


def test_non_finite_optional_present(tmp_path):
    camp = build(tmp_path)
    optional = next(c.name for c in family().channels if not c.required_in)

    def corrupt(df):
        df[optional] = 0.0
        df.loc[99, optional] = np.nan  # data row 100
        return df

    edit_csv(camp, "s1_sine", corrupt)
    msg = str(error(camp))
    assert f"column '{optional}'" in msg and "row 100" in msg and "NaN" in msg


def test_nan_in_extra_column_is_fine(tmp_path):
    camp = build(tmp_path)

    def add(df):
        df["comment_code"] = 1.0
        df.loc[3, "comment_code"] = np.nan
        return df

    edit_csv(camp, "s1_sine", add)
    df = read_campaign(camp).frame("s1_sine")
    assert np.isnan(df.loc[3, "comment_code"])


def test_time_not_increasing(tmp_path):
    camp = build(tmp_path)
    tcol = family().time_channel

    def corrupt(df):
        df.loc[59, tcol] = df.loc[58, tcol]  # data row 60 repeats row 59
        return df

    edit_csv(camp, "s1_sine", corrupt)
    err = error(camp)
    msg = str(err)
    assert f"column '{tcol}'" in msg and "row 60" in msg and "strictly increasing" in msg
    assert "test 's1_sine'" in msg and NAME in msg


def test_time_not_uniform(tmp_path):
    camp = build(tmp_path)
    tcol = family().time_channel

    def corrupt(df):
        df.loc[120, tcol] += 0.05 * DT  # data row 121 is 5 % late
        return df

    edit_csv(camp, "s2_sine", corrupt)
    msg = str(error(camp))
    assert f"column '{tcol}'" in msg and "row 121" in msg and "not uniform" in msg
    assert "test 's2_sine'" in msg and NAME in msg


def test_time_jitter_within_tolerance(tmp_path):
    camp = build(tmp_path)
    tcol = family().time_channel

    def jitter(df):
        df.loc[120, tcol] += 0.004 * DT  # 0.4 %: allowed
        return df

    edit_csv(camp, "s2_sine", jitter)
    read_campaign(camp)


def test_too_few_samples(tmp_path):
    camp = build(tmp_path)
    edit_csv(camp, "s3_ctrl", lambda df: df.iloc[:99])
    msg = str(error(camp))
    assert "99 samples" in msg and "100" in msg and "test 's3_ctrl'" in msg and NAME in msg


def test_exactly_min_samples_ok(tmp_path):
    camp = build(tmp_path)
    edit_csv(camp, "s3_ctrl", lambda df: df.iloc[:100])
    assert len(read_campaign(camp).frame("s3_ctrl")) == 100


# --------------------------------------------------------------------------- output folders
@pytest.mark.parametrize("command", ["identify", "discover", "preprocess"])
def test_an_output_folder_that_would_replace_the_campaign_is_refused_before_the_work(
        tmp_path, capsys, command):
    """Found 2026-11-28: `mbst identify CAMP --out CAMP` fitted, then replaced the campaign
    with its results (exit 0); `--out` on a file replaced the file; an unwritable `--out`
    ended a 26 s fit in a traceback. Each is refused before any fit, nothing touched."""
    from mbst.cli import main

    camp = build(tmp_path)
    before = sorted(p.name for p in camp.rglob("*"))
    a_file = tmp_path / "notes.txt"
    a_file.write_text("keep me")
    for out, words in [(camp, "holds the input"), (tmp_path, "holds the input"),
                       (a_file, "is a file"), (a_file / "sub", "cannot create it")]:
        assert main([command, str(camp), "--out", str(out), "--quiet"]) == 2, out
        err = capsys.readouterr().err
        assert f"--out {out}" in err and words in err and "Traceback" not in err, err
    assert sorted(p.name for p in camp.rglob("*")) == before
    assert a_file.read_text() == "keep me"


def test_a_fault_of_mbst_is_said_in_one_line_before_its_traceback(tmp_path, capsys,
                                                                   monkeypatch):
    """Never a bare traceback: an error that is mbst's own (here planted in the identify
    step) is said first, naming the command and the error, then traced for a bug report;
    the exit status tells it from bad input (2) and the output folder is not written."""
    from mbst import cli
    from mbst.report import identify as identify_report

    def broken(*args, **kwargs):
        raise ZeroDivisionError("planted")

    monkeypatch.setattr(identify_report, "run_identify", broken)
    camp = build(tmp_path)
    assert cli.main(["identify", str(camp), "--out", str(tmp_path / "out"), "--quiet"]) == 3
    err = capsys.readouterr().err
    first, rest = err.split("\n", 1)
    assert first == "mbst identify: internal error: ZeroDivisionError: planted", err
    assert "fault in mbst, not in your data" in rest and "Traceback" in rest
    assert not (tmp_path / "out").exists()
