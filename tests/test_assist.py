"""Power assist (issue #8, seed 001): curve per mode, active damping per speed, HPS form."""

from __future__ import annotations

import json

import numpy as np
import pytest
import yaml

from mbst.identify.cascade import (
    IdentifySettings,
    correlate,
    identify,
    run_cascade,
)
from mbst.identify.fitting import prepare_test, simulate_twin
from mbst.io.campaign import CampaignError, read_campaign
from mbst.report.identify import write_identify_outputs
from mbst.systems.eps import assist as eps_assist
from mbst.systems.eps.bench import (
    DEFAULT_SENSORS,
    DEMO_ASSIST_CURVES,
    DEMO_ASSIST_DAMPING,
    BenchRecipe,
    compact_assist_plan,
    run_bench,
)


@pytest.fixture(scope="module")
def clean_assist(tmp_path_factory):
    out = tmp_path_factory.mktemp("assist")
    camp = run_bench(out, BenchRecipe(effects=[], plan=compact_assist_plan(), name="assist"))
    truth = json.loads((out / "truth.json").read_text())
    return read_campaign(camp), truth


@pytest.fixture(scope="module")
def discovered(clean_assist):
    """Discovery on the clean powered campaign; its base fit is the identification."""
    from mbst.discovery.pipeline import DiscoverSettings, discover

    camp, _ = clean_assist
    return discover(camp, DiscoverSettings(max_effects=1, sparse=False, neural=False))


@pytest.fixture(scope="module")
def current_assist(tmp_path_factory):
    """The same campaign with the assist motor's current logged (seed 001's layout)."""
    out = tmp_path_factory.mktemp("assist-current")
    camp = run_bench(out, BenchRecipe(effects=[], plan=compact_assist_plan(), name="assist",
                                      sensors=DEFAULT_SENSORS + ("motor_current_a",)))
    truth = json.loads((out / "truth.json").read_text())
    return read_campaign(camp), truth


@pytest.fixture(scope="module")
def identified(current_assist, tmp_path_factory):
    camp, truth = current_assist
    result = identify(camp, IdentifySettings())
    out = tmp_path_factory.mktemp("assist-id")
    write_identify_outputs(result, out, IdentifySettings())
    return camp, truth, result, out


@pytest.fixture(scope="module")
def identified_without_current(clean_assist):
    camp, truth = clean_assist
    return camp, truth, identify(camp, IdentifySettings())


@pytest.mark.slow  # ~2 min; CI keeps the clean-data checks of each family at a smaller scale
def test_clean_powered_campaign_gives_an_empty_answer(discovered):
    """The counterpart of the hidden-backlash test: nothing to name on a clean rig."""
    assert discovered.findings == [], [f"{f.effect}:{f.component}" for f in discovered.findings]


def test_campaign_brings_one_curve_per_mode_and_one_damping_per_speed(clean_assist):
    camp, _ = clean_assist
    model = camp.model()
    for mode in ("normal", "city"):
        for q in ("c1", "c2", "c3"):
            assert model.spec(f"assist.{mode}.{q}").kind == "base"
    for v in (60, 120):
        assert model.spec(f"assist.{v}kph.active_damping_nms_per_rad").kind == "base"
    # every powered test names its mode and speed: the generic slots are not fitted
    assert model.spec("assist.c1").kind == "fixed"
    stages = [s for s, _ in model.cascade]
    assert stages[-2:] == ["assist_characteristic", "active_damping"]
    # a passive campaign keeps the family's own model
    passive = BenchRecipe(effects=[])
    assert passive.model() is camp.family.model()


def test_each_powered_test_runs_on_its_own_curve_and_damping(clean_assist):
    camp, truth = clean_assist
    model = camp.model()
    p = model.vector_from(truth["params"])
    spec = camp.test("on_loaded_0p05hz_city")
    pt = prepare_test(camp, spec, 0.005)
    city = simulate_twin(pt, p)["steering_torque_nm"]
    # the same test in the other mode needs more driver torque (normal assists less)
    q = p.copy()
    for c in ("c1", "c2", "c3"):
        q[model.param_index[f"assist.city.{c}"]] = truth["params"][f"assist.normal.{c}"]
    normal = simulate_twin(pt, q)["steering_torque_nm"]
    assert np.max(np.abs(normal)) > 1.2 * np.max(np.abs(city))
    # the kernel's generic slot is ignored for a test that names its mode
    r = p.copy()
    r[model.param_index["assist.c1"]] = 5.0
    assert np.allclose(simulate_twin(pt, r)["steering_torque_nm"], city)
    # stages: slow powered tests give the curve, fast ones the damping
    assert model.stages_of(pt) == ("assist_characteristic",)
    fast = prepare_test(camp, camp.test("on_loaded_1hz_normal_60kph"), 0.005)
    assert model.stages_of(fast) == ("active_damping",)
    off = prepare_test(camp, camp.test("off_loaded_0p05hz"), 0.005)
    assert model.stages_of(off) == ("tires_on_ground", "assist_characteristic")


def test_bad_assist_entries_are_named(clean_assist, tmp_path, capsys):
    """... by `mbst check` too: it passed them, and identification refused them (found
    2026-11-28)."""
    from mbst.cli import main

    camp, _ = clean_assist
    doc = yaml.safe_load((camp.path / "campaign.yaml").read_text())
    import shutil

    shutil.copytree(camp.path, tmp_path / "c")
    bad = dict(doc)
    bad["tests"] = [dict(t) for t in doc["tests"]]
    bad["tests"][-1]["assist_mode"] = "city mode"
    (tmp_path / "c" / "campaign.yaml").write_text(yaml.safe_dump(bad))
    with pytest.raises(CampaignError, match="city mode"):
        read_campaign(tmp_path / "c").model()
    bad["tests"][-1]["assist_mode"] = "city"
    bad["assist_characteristic"] = "pneumatic"
    (tmp_path / "c" / "campaign.yaml").write_text(yaml.safe_dump(bad))
    with pytest.raises(CampaignError, match="assist_characteristic is 'pneumatic'"):
        read_campaign(tmp_path / "c").model()
    assert main(["check", str(tmp_path / "c")]) == 2
    assert "assist_characteristic is 'pneumatic'" in capsys.readouterr().err


@pytest.mark.slow  # ~9 s; CI identifies the HPS curve from the motor current (next test)
def test_hps_curve_is_identified(tmp_path):
    """Seed 001's HPS form c·sign(T)·(e^|T| − 1): one parameter per mode."""
    recipe = BenchRecipe(effects=[], plan=compact_assist_plan(), name="hps",
                         assist_characteristic="hps",
                         assist_curves={"normal": {"c1": 0.5}, "city": {"c1": 0.8}})
    camp = read_campaign(run_bench(tmp_path, recipe))
    model = camp.model()
    assert model.spec("assist.c2").kind == "fixed" and "assist.normal.c2" not in model.param_index
    truth = json.loads((tmp_path / "truth.json").read_text())["params"]
    base = model.vector_from(truth)
    only = {"assist.normal.c1", "assist.city.c1"}
    for n in only:  # start far from the truth
        base[model.param_index[n]] = 2.0
    p = run_cascade(camp, IdentifySettings(multistart=1), base=base, only=only).params
    for n in only:
        assert p[model.param_index[n]] == pytest.approx(truth[n], rel=0.05)


def test_hps_curve_from_the_motor_current(tmp_path):
    """The measured-points fit serves the HPS form too (one parameter per mode)."""
    recipe = BenchRecipe(effects=[], plan=compact_assist_plan(), name="hps",
                         assist_characteristic="hps",
                         assist_curves={"normal": {"c1": 0.5}, "city": {"c1": 0.8}},
                         sensors=DEFAULT_SENSORS + ("motor_current_a",))
    camp = read_campaign(run_bench(tmp_path, recipe))
    truth = json.loads((tmp_path / "truth.json").read_text())["params"]
    model = camp.model()
    tests = [prepare_test(camp, s, 0.005) for s in camp.identification_tests()]
    pre = model.pre_identify(camp, tests, model.vector_from(camp.known))
    assert set(pre["held"]) == {"assist.normal.c1", "assist.city.c1",
                                "assist.60kph.active_damping_nms_per_rad",
                                "assist.120kph.active_damping_nms_per_rad"}
    for n in pre["held"]:
        assert pre["values"][n] == pytest.approx(truth[n], rel=0.10), n
    for n in ("assist.normal.c1", "assist.city.c1"):
        assert pre["values"][n] == pytest.approx(truth[n], rel=0.02), n
    assert pre["boost_curve"]["method"].startswith("orthogonal distance regression")
    assert pre["boost_curve"]["converged"]


@pytest.mark.slow  # ~50 s in CI (its fixture); CI identifies the powered curves in the HPS cases
def test_assist_identification_on_the_bench(identified):
    """Issue #8 targets on a seeded compact campaign of seed 001's layout, current logged.

    c1, c2, c3 within 5 %, the damping per speed within 10 %, the control FIT
    within 1 point of the true model's. The curve and the damping come from
    the measured points (motor current against the torque sensor, errors in
    variables, ``eps_boost_curve``) and are held by the cascade.
    """
    camp, truth, result, out = identified
    model, p = result.model, result.params
    t = truth["params"]
    for mode, c_true in DEMO_ASSIST_CURVES.items():
        for q, v in c_true.items():
            assert p[model.param_index[f"assist.{mode}.{q}"]] == pytest.approx(v, rel=0.05), \
                (mode, q)
    damp = eps_assist.dampings(model, p)
    assert set(damp) == {60.0, 120.0}
    for v, c_ad in damp.items():
        assert c_ad == pytest.approx(DEMO_ASSIST_DAMPING[v], rel=0.10), v
    # the cascade held them: no output-error stage refitted them
    params = json.loads((out / "params.json").read_text())["params"]
    assert params["assist.city.c1"]["stage"] == "measured_points"
    assert params["assist.60kph.active_damping_nms_per_rad"]["stage"] == "measured_points"
    assert params["assist.city.c1"]["std_error"] < 0.05 * DEMO_ASSIST_CURVES["city"]["c1"]
    assert not any("assist.city.c1" in st.free for st in result.stages)
    # control FIT within 1 point of the true model's
    controls = [result.prepared[s.id] for s in camp.control_tests()]
    truth_corr, _ = correlate(controls, model.vector_from(t))
    merged = result.correlation.merge(truth_corr, on=["test", "channel"], suffixes=("", "_true"))
    assert len(merged) >= 10 and "motor_current_a" in set(merged.channel)
    assert (merged.fit_percent > merged.fit_percent_true - 1.0).all(), merged


@pytest.mark.slow  # ~1.5 min; CI identifies the campaign with the current logged
def test_assist_curve_without_a_current_sensor(identified_without_current):
    """Without the motor current the output-error cascade fits the curve.

    The curve is checked where it acts: A(T) within 5 % (or 0.05 N·m where it
    is small) over the torque the tests reach (0.5–6 N·m) and c3 within 5 %. c1
    (the slope at zero torque) and c2 trade against each other, the column
    friction and the angle noise (docs/eps-model.md "Power assist"): held to
    35 % and 10 %; the damping per speed needs ``--joint`` (below).
    """
    camp, truth, result = identified_without_current
    model, p = result.model, result.params
    assert "held" not in result.preid
    grid = np.linspace(0.5, 6.0, 60)
    for mode, c_true in DEMO_ASSIST_CURVES.items():
        c = {q: p[model.param_index[f"assist.{mode}.{q}"]] for q in c_true}
        assert c["c3"] == pytest.approx(c_true["c3"], rel=0.05), mode
        assert c["c2"] == pytest.approx(c_true["c2"], rel=0.10), mode
        assert c["c1"] == pytest.approx(c_true["c1"], rel=0.35), mode
        a, a_true = eps_assist.characteristic(grid, c), eps_assist.characteristic(grid, c_true)
        assert np.all(np.abs(a - a_true) < np.maximum(0.05 * a_true, 0.05)), mode
    damp = eps_assist.dampings(model, p)
    assert damp[120.0] == pytest.approx(DEMO_ASSIST_DAMPING[120.0], rel=0.20)
    assert abs(damp[60.0] - DEMO_ASSIST_DAMPING[60.0]) < 0.02
    controls = [result.prepared[s.id] for s in camp.control_tests()]
    truth_corr, _ = correlate(controls, model.vector_from(truth["params"]))
    merged = result.correlation.merge(truth_corr, on=["test", "channel"], suffixes=("", "_true"))
    assert (merged.fit_percent > merged.fit_percent_true - 1.0).all(), merged


@pytest.mark.slow  # reads the same fixture (~50 s)
def test_assist_report(identified):
    camp, _, result, out = identified
    assert (out / "figures" / "assist_characteristic.png").stat().st_size > 10_000
    assert (out / "figures" / "active_damping.png").stat().st_size > 5_000
    md = (out / "identify.md").read_text()
    assert "## Power assist" in md and "| city |" in md and "| 120 |" in md
    bounds = result.preid["assist_friction_bounds"]["tires_on_ground"]
    # seed 001 Fig. 11: the assist narrows the loop
    assert bounds["half_width_on_nm"] < bounds["half_width_off_nm"]
    assert "motor current against the torque sensor" in md
    params = json.loads((out / "params.json").read_text())["params"]
    # the friction refitted beside the held curve and damping (seed 001 Table 1)
    assert params["rack.coulomb_n"]["stage"] == "assist_characteristic"
    assert params["rack.viscous_ns_per_m"]["stage"] == "active_damping"


@pytest.mark.slow  # ~5 min: the joint refit is 28 parameters on 15 tests
def test_joint_refinement_gets_the_damping_per_speed(identified_without_current):
    """Issue #8's 10 % on the damping per speed without a current sensor: `--joint`.

    The cascade leaves the small 60 km/h damping tens of per cent off (it takes up
    the column's viscous error); refitting everything on all identification tests
    together tells them apart (docs/eps-model.md "Power assist").
    """
    camp, _, cascade = identified_without_current
    result = identify(camp, IdentifySettings(joint_refinement=True))
    assert result.stages[-1].scenario == "joint"
    damp = eps_assist.dampings(result.model, result.params)
    for v, true in DEMO_ASSIST_DAMPING.items():
        if v in damp:
            assert damp[v] == pytest.approx(true, rel=0.10), v
    # what the joint refit fixes
    small = eps_assist.dampings(cascade.model, cascade.params)[60.0]
    assert abs(small / DEMO_ASSIST_DAMPING[60.0] - 1) > 0.2


@pytest.mark.slow  # 3.5 min; discovery of this backlash runs in CI on the passive rig
def test_hidden_worm_gear_backlash_is_found_under_assist(tmp_path):
    """Issue #8: discovery still names a worm-gear backlash in a powered campaign."""
    from mbst.discovery.pipeline import DiscoverSettings, discover

    recipe = BenchRecipe(effects=["backlash:worm_gear"], plan=compact_assist_plan(),
                         name="assist-backlash")
    camp = read_campaign(run_bench(tmp_path, recipe))
    result = discover(camp, DiscoverSettings(max_effects=1, sparse=False, neural=False))
    assert [f"{f.effect}:{f.component}" for f in result.findings] == ["backlash:worm_gear"]
    width = result.findings[0].parameters["width_rad"]
    assert width == pytest.approx(0.035, rel=0.20)
