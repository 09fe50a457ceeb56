"""Hidden-effect tests of discovery (issue #4).

Each case plants one catalogue effect at its realistic size in a seeded bench
campaign and requires the first finding to name effect and component (and the
size, for backlash); clean campaigns must give an empty answer. The compact
plan (blocked column + free tie-rods) keeps a case at 1–3 minutes; every case runs under
``-m slow`` (CI checks the demo pipeline's own discovery against its bench truth instead,
``.ci/demo_answer.py``). (The worm-gear backlash case, whose result many
tests read, is in test_discover.py: a module of its own each keeps the two long
runs on different workers.)
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from discovery_cases import SETTINGS, assert_first_finding, run_case

from mbst.discovery.pipeline import DiscoverSettings, discover
from mbst.discovery.structure import stage_for
from mbst.io.campaign import read_campaign
from mbst.report.discovery import (
    discovery_record,
    markdown_summary,
    resolution_lines,
    resolution_table,
    write_discover_outputs,
)
from mbst.report.discovery_figures import resolution_bars
from mbst.systems.eps.bench import BenchRecipe, compact_plan, run_bench
from mbst.systems.eps.model import EPS_MODEL
from mbst.systems.eps.params import EFFECT_CATALOGUE, EFFECTS
from mbst.systems.eps.realism import BenchRealism

# Effects the compact plan cannot show at their realistic size, with the reason
# (measured 2026-11-23, compact plan seed 1, the true pair's share of its stage cost and
# ΔAIC; the margin is 10 % and ΔAIC ≤ -100). Strict: a fix shows up as an unexpected pass.
KNOWN_MISSES = {
    "power_law_damping:steering_column": (
        "invisible at any exponent: the column's whole viscous torque (0.012 N·m·s/rad × "
        "≤ 0.55 rad/s) is a third of the torque noise; exponent 0.5 or 0.2, no candidate "
        "removes more than 1.3 % of any stage's cost"),
    "power_law_damping:motor": (
        "1.6 % of the free-tie-rods cost at exponent 0.5, 1.1 % at 0.2; a 2 Hz free-tie-rods "
        "sine added to the plan did not raise it (0.8 %)"),
    "asymmetric_friction:steering_column": (
        "on a moving column it is a torque offset: ratio 1.6 removes 4.6 % of the "
        "blocked-column cost, 2.5 removes 15 % (ΔAIC -32), even 4 (the bound) only 26 % "
        "(ΔAIC -58): 12 s of blocked-column tests hold ~200 effective samples"),
    "stribeck_friction:steering_column": (
        "the column's Stribeck hump (0.056 N·m, under 3x the torque noise, only below "
        "0.02 rad/s, where the smoothed rate's noise is ~0.01 rad/s) removes 5 % of the "
        "blocked-column cost (ΔAIC -7) and is too small to stick-slip; at F_s/F_c = 3 it is "
        "named (test_known_miss_is_named_at_a_larger_size)"),
}
# A size at which a KNOWN_MISSES pair is named on the compact plan (the smallest of those
# tried: F_s/F_c 3 and 4): the candidate works, the realistic size is below the noise.
DETECTED_FROM = {
    "stribeck_friction:steering_column": "static_to_coulomb_ratio=3",
}


@pytest.mark.slow  # ~100 s; CI keeps the backlash, Stribeck and clean cases
def test_motor_angle_is_used_when_the_campaign_logs_it(tmp_path_factory):
    """The optional motor angle enters every refit and the comparison: the gear gap shows
    there directly, as the motor lagging the column by the width at each reversal."""
    from mbst.systems.eps.bench import DEFAULT_SENSORS

    out = tmp_path_factory.mktemp("disc_motor")
    recipe = BenchRecipe(effects=["backlash:worm_gear"], seed=1, plan=compact_plan(),
                         sensors=DEFAULT_SENSORS + ("motor_angle_rad",))
    camp = read_campaign(run_bench(out, recipe))
    truth = json.loads((out / "truth.json").read_text())
    result = discover(camp, DiscoverSettings(**SETTINGS))
    assert_first_finding(result, "backlash:worm_gear", truth)
    stage = next(c for c in result.rounds[0]["candidates"] if c["key"] == "backlash:worm_gear")
    assert stage["stage"] == "free_tie_rods"
    wide = result.comparison.pivot_table(index=["test", "channel"], columns="model",
                                         values="fit_percent")
    motor = wide.xs("motor_angle_rad", level="channel")
    assert (motor["base"] < motor["true"] - 1).all(), motor
    assert (motor["extended"] > motor["true"] - 0.5).all(), motor


@pytest.mark.slow  # ~150 s
def test_a_look_alike_named_before_the_effect_is_dropped_by_the_backward_check(
        tmp_path_factory):
    """A production-size worm-gear backlash (0.35°) with the motor angle logged: a motor
    presliding hysteresis won round 1 (it takes part of the gap's signature) and the
    backlash round 2. Out of the final model the presliding term was worth 1.2 % of its
    stage (ΔAIC −28): the backward check drops it, and the answer is the backlash alone.
    Since the rivals' screen (stop 84) the backlash wins round 1 here outright (the case
    failed on its missing backward round, 2026-11-30); a look-alike the rounds still name
    must be dropped by it."""
    from mbst.systems.eps.bench import DEFAULT_SENSORS

    out = tmp_path_factory.mktemp("backward")
    recipe = BenchRecipe(effects=["backlash:worm_gear:width_rad=0.0061"], seed=1,
                         plan=compact_plan(), sensors=DEFAULT_SENSORS + ("motor_angle_rad",))
    camp = read_campaign(run_bench(out, recipe))
    result = discover(camp, DiscoverSettings(max_effects=3, sparse=False, neural=False))
    named = [(f.effect, f.component) for f in result.findings if f.effect != "unexplained"]
    assert named == [("backlash", "worm_gear")], [f.evidence for f in result.findings]
    assert result.findings[0].parameters["width_rad"] == pytest.approx(0.0061, rel=0.2)
    accepted = [r["accepted"] for r in result.rounds if r.get("accepted")]
    backward = [r for r in result.rounds if r.get("kind") == "backward"]
    if accepted == ["backlash:worm_gear"]:
        assert not backward
        return
    (check,) = backward
    assert check["dropped"] == [r["key"] for r in check["checked"] if not r["needed"]]
    assert set(accepted) - set(check["dropped"]) == {"backlash:worm_gear"}


# ~130 s in CI: under -m slow since CI checks the pipeline's own run of the demo against its
# truth (.ci/demo_answer.py); the empty answer on clean data stays in CI at the scale of
# each family's checks (tests/test_screen.py, test_unexplained.py, test_prismatic.py,
# test_friction_damper.py)
@pytest.mark.parametrize("seed", [pytest.param(1, marks=pytest.mark.slow),
                                  pytest.param(2, marks=pytest.mark.slow)])
def test_clean_campaign_gives_no_finding(tmp_path_factory, seed):
    _, _, result = run_case(tmp_path_factory, [], seed=seed)
    assert result.findings == [], [f.evidence for f in result.findings]
    assert "noise floor" in result.rounds[0]["reason"]
    # the first round's screen predicted every candidate; those it refitted nest the base
    # model (effect off), so none may score below it
    assert len(result.rounds[0]["shortlist_screen"]["predicted_gain"]) >= 10
    scored = result.rounds[0]["candidates"]
    assert min((c["relative_gain"] for c in scored), default=0.0) >= 0.0, scored
    assert result.rounds[-1]["method"] == "stick_slip"
    assert "no stick-slip" in result.rounds[-1]["reason"]
    np.testing.assert_array_equal(result.extended_params, result.base.params)
    # what an empty answer covers: the prediction of what these tests resolve marks as
    # out of reach at the realistic size exactly the pairs the catalogue sweep misses
    resolution = {r.key: r for r in result.resolution}
    assert set(resolution) == set(EFFECTS)
    tested = {k for k, r in resolution.items() if r.stage is not None}
    assert tested == {e.key for e in EFFECT_CATALOGUE
                      if stage_for(e, {"blocked_column", "free_tie_rods"}, EPS_MODEL)}
    unresolved = {k for k in tested if not resolution[k].resolved_at_realistic_size}
    assert unresolved == set(KNOWN_MISSES), {k: resolution[k].size_at(1.0) for k in unresolved}
    # ... and column Stribeck, at a larger size: with the campaign's own significance
    # margin the sweep names it from a ratio of 2.6, 2x its realistic size (12.8 % of the
    # stage, ΔAIC −29; measured 2026-11-25), where the fixed ΔAIC ≤ −100 needed a ratio of 3
    assert resolution["stribeck_friction:steering_column"].resolved_from in (2.0, 3.0)
    # the structure test's refits (those the first round's screen left to refit) were scored
    # on the model the prediction starts from, and at the sizes they reached the prediction
    # agrees with them: no limit is withheld here
    checked = [r for r in resolution.values() if r.refit is not None]
    assert len(checked) == len([c for c in scored if not c["fell_back"] and c["headline"]])
    assert checked and not [(r.key, r.refit) for r in checked if r.refit.contradicts]
    if seed == 1:
        _check_resolution_report(result, tmp_path_factory.mktemp("resolution"))


# ~55 s; CI keeps the lag's paths in test_discover (the rival declines a winner) and
# test_unexplained (the lag described, and refitted where the library reads one)
@pytest.mark.slow
def test_a_torque_sensor_lag_is_not_named_as_a_catalogue_effect(tmp_path_factory):
    """eps-model.md: a torque sensor's own filter lags by a few ms, and discovery must not
    force it into a catalogue effect. The clean compact plan with a 3 ms lag on the torque
    channel and nothing else had a column Stribeck rise at its bound (ratio 4.0) named at
    0.58 and a rack presliding at 0.20 (measured 2026-11-27). The lag of the torque sensor,
    refitted with each winner's stage, matches the column Stribeck and the round names
    nothing from the catalogue. A rack power law (exponent 0.86, 10.2 % of the free
    tie-rods) still removed 18.0 % of what the lag refitted there alone left, and was named
    at 0.05 (since 653b5c6); beside the lag carried through the whole cascade it removes
    7.3 %, and is declined (2026-11-30)."""
    out = tmp_path_factory.mktemp("lag")
    camp = read_campaign(run_bench(out, BenchRecipe(
        effects=[], seed=1, plan=compact_plan(), realism=BenchRealism(torque_lag_s=0.003))))
    result = discover(camp, DiscoverSettings(**SETTINGS))
    named = [(f.effect, f.component, f.confidence) for f in result.findings
             if f.effect != "unexplained"]
    assert named == [], [f.evidence for f in result.findings]
    # ... it is said as what it is: the lag, at its size, and the model with it predicts
    # the held-out control better (before 2026-11-27: no finding at all)
    lag = [f.signature for f in result.findings if f.effect == "unexplained"]
    assert lag and (lag[0]["kind"], lag[0]["quantity"]) == ("lag", "steering_torque_nm")
    assert 0.0015 < lag[0]["lag_s"] < 0.0045, lag[0]
    means = result.comparison.groupby("model")["fit_percent"].mean()
    assert means["physics+learned"] > means["base"]
    gone = result.rounds[0]["rival_declined"]
    assert gone[0]["stage"] == "blocked_column" and gone[0]["sensor"] == "steering_torque_nm"
    assert 1.0 < gone[0]["lag_ms"] < 6.0
    through = [g for g in result.rounds[0].get("rival_beyond", []) if "through_cascade" in g]
    assert through and not any(g["stands"] for g in through), through
    # ... and the report says so: the answer is not "at the noise floor" alone
    assert f"Round 1, not named: {gone[0]['reason']}." in markdown_summary(result)


def _check_resolution_report(result, out) -> None:
    """What these tests resolve, as the report, resolution.csv, discovery.json and the
    figure state it: each pair's detection limit in its own unit, both ways for an effect
    that acts either way, and how far each stage's fit is from its noise floor."""
    sizes = resolution_table(result.resolution)
    report = "\n".join(resolution_lines(result))
    record = {r["effect"] + ":" + r["component"]: r for r in discovery_record(result)["resolution"]}
    first = sizes[(sizes.effect == "backlash") & (sizes.component == "rack_pinion")
                  & (sizes.multiple_of_realistic_size == 1.0) & (sizes.side == "realistic")]
    assert first["size.width_rad"].item() == EFFECTS["backlash:rack_pinion"].default_size[
        "rack_pinion.backlash.width_rad"] and first.resolved.item()
    assert "| backlash | rack_pinion | free_tie_rods |" in report
    # the detection limit, in the effect's own unit: the smallest width these tests resolve
    rp = next(r for r in result.resolution if r.key == "backlash:rack_pinion")
    limit = rp.detection_limit()
    assert limit.multiple < 1.0 and limit.share >= result.settings.min_relative_gain
    smaller = [s for s in rp.sizes if s.multiple < limit.multiple]
    assert all(not s.clears(result.settings.min_relative_gain, rp.aic_drop_needed)
               for s in smaller)
    deg = np.degrees(limit.values["width_rad"])
    bound = "at or below" if limit is rp.sizes[0] else "from"
    assert f"{bound} width_rad = {limit.values['width_rad']:.3g} ({deg:.2f}°)" in report
    assert set(sizes.detection_limit_multiple.dropna()) >= {limit.multiple}
    # a power law is tried either way from neutral, each side with its own limit
    power = sizes[(sizes.effect == "power_law_damping") & (sizes.component == "rack")]
    assert (power[power.side == "realistic"]["size.exponent"] < 1).all()
    assert (power[power.side == "other"]["size.exponent"] > 1).all()
    assert len(power[power.side == "other"]) >= 5
    # ... and the two sides differ: the motor's exponent below 1 is a known miss of this
    # plan (KNOWN_MISSES), above 1 it is resolved (from 0.5x, exponent 1.25, measured
    # 2026-11-26): a one-sided statement would have said the motor's power law is unseen
    pm = next(r for r in result.resolution if r.key == "power_law_damping:motor")
    assert pm.resolved_from is None and pm.other_side_resolved_from is not None, pm.other_side
    pr = next(r for r in result.resolution if r.key == "power_law_damping:rack")
    row = next(line for line in report.splitlines()
               if line.startswith("| power_law_damping | rack |"))
    assert "; the other way: " in row and (
        f"exponent = {pr.detection_limit(True).values['exponent']:.3g}"
        if pr.other_side_resolved_from else "**not resolved** up to exponent = 2") in row
    assert "other_side" in record[pr.key]
    # how far each stage's fit is from its noise floor: the base model explains the plain
    # bench down to it (a realistic rig's fit leaves 15-33x, mostly its AR(1) noise, which
    # the fast-noise floor does not count: docs/discovery.md)
    assert 0.8 < pr.stage_over_floor < 2.0
    assert f"{pr.stage_over_floor:.1f}× (free_tie_rods)" in report
    assert record[pr.key]["stage_cost_over_noise_floor"] == pr.stage_over_floor
    assert resolution_bars(result, out / "resolution.png")
    assert (out / "resolution.png").stat().st_size > 10_000


@pytest.mark.parametrize("key", [
    # ~77 s: under -m slow since the friction-damper family's hidden-play case took its
    # CI time (tests/test_friction_damper.py)
    pytest.param("stiffness_limit_stop:torsion_bar", marks=pytest.mark.slow),
    # stick-slip: the output-error structure test cannot see it, the envelope test does
    # (~76 s: under -m slow since the loop's design tests took its CI time; the envelope
    # test's parts stay in CI, tests/test_stickslip.py)
    pytest.param("stribeck_friction:motor", marks=pytest.mark.slow),
])
def test_hidden_effect_is_named(tmp_path_factory, key):
    # the finding is under test here; what the tests resolve is the clean case's
    _, truth, result = run_case(tmp_path_factory, [key], resolution=False)
    assert_first_finding(result, key, truth)
    if key.startswith("stribeck"):
        assert result.rounds[0]["accepted"] is None  # the output-error rounds miss it
        assert result.rounds[-1]["method"] == "stick_slip"
        assert "stick-slip" in result.findings[0].evidence
        wide = result.comparison.pivot_table(index=["test", "channel"], columns="model",
                                             values="fit_percent")
        assert wide["extended"].mean() > wide["base"].mean()
        out = tmp_path_factory.mktemp("stick-out")
        write_discover_outputs(result, out)
        rec = json.loads((out / "discovery.json").read_text(),
                         parse_constant=lambda c: pytest.fail(f"not JSON: {c}"))
        assert rec["findings"][0]["aic_delta"] is None
        assert rec["rounds"][-1]["accepted"] == key
        assert (out / "figures" / "stick_slip.png").stat().st_size > 10_000


@pytest.mark.slow
@pytest.mark.parametrize("key", [
    pytest.param(e.key, marks=pytest.mark.xfail(reason=KNOWN_MISSES[e.key], strict=True))
    if e.key in KNOWN_MISSES else e.key
    for e in EFFECT_CATALOGUE if stage_for(e, {"blocked_column", "free_tie_rods"}, EPS_MODEL)
])
def test_catalogue_effect_is_named(tmp_path_factory, key):
    _, truth, result = run_case(tmp_path_factory, [key])
    assert_first_finding(result, key, truth)


# The tires and tie-rod pairs need the demo plan's tires_on_ground tests (3-6 min each,
# tire Stribeck 28). Measured 2026-11-23, seed 1, with the structure test freeing what the
# cascade frees in the tires stage (the tie-rod force offsets first measured there, the
# tie-rod stiffness and damping carried from the skipped blocked_rack stage). Tire Stribeck
# was missed (39 % of the stage cost where the true model removes 99.99 %) until a candidate
# with evidence refined also from its element's Coulomb level at the typical value
# (EffectSpec.absorbed_by): the base fit had lifted it to 3544 N (true 2600 N).
# the headline the finding must carry within 20 % (the tie-rod Coulomb level is shared
# with the tires' own: 94 N for a true 150 N, so it is not checked)
TIRES_SIZED = {"asymmetric_friction:tires": "ratio", "power_law_damping:tires": "exponent",
               "presliding_hysteresis:tires": "stiffness"}


@pytest.mark.slow
@pytest.mark.parametrize("key", [
    e.key
    for e in EFFECT_CATALOGUE if not stage_for(e, {"blocked_column", "free_tie_rods"}, EPS_MODEL)
])
def test_tires_effect_is_named_on_the_demo_plan(tmp_path_factory, key):
    _, truth, result = run_case(tmp_path_factory, [key], plan=None)
    assert_first_finding(result, key, truth)
    if key in TIRES_SIZED:
        name = TIRES_SIZED[key]
        true_value = truth["effects"][0]["parameters"][name]
        assert result.findings[0].parameters[name] == pytest.approx(true_value, rel=0.2)


@pytest.mark.slow
@pytest.mark.parametrize("key", sorted(DETECTED_FROM))
def test_known_miss_is_named_at_a_larger_size(tmp_path_factory, key):
    """What the compact plan misses at the realistic size it names once the effect is larger."""
    _, truth, result = run_case(tmp_path_factory, [f"{key}:{DETECTED_FROM[key]}"])
    assert_first_finding(result, key, truth)
    name, value = DETECTED_FROM[key].split("=")
    assert result.findings[0].parameters[name] == pytest.approx(float(value), rel=0.25)


@pytest.mark.slow  # ~2 × 100 s
@pytest.mark.parametrize("planted", ["load_dependent_friction:rack:coefficient=0.041",
                                     "power_law_damping:rack:exponent=0.6"])
def test_issue_34_effects_are_named_on_a_drawn_rig(tmp_path_factory, planted):
    """The two effects whose candidates fell back on an independent simulator's campaigns,
    planted on a drawn rig: each candidate really tested, and the effect named in its own
    component — or, if these tests cannot resolve its size, no finding with the resolution
    step saying so (the load-dependent coefficient 0.041 is half the realistic 0.08: on the
    compact plan its candidate refits to 0.038 and removes 2.2 %, the detection limit is
    0.7x). Never another effect."""
    out = tmp_path_factory.mktemp("drawn")
    recipe = BenchRecipe(effects=[planted], seed=3, plan=compact_plan(),
                         realism=BenchRealism(draw_rig=True))
    camp = read_campaign(run_bench(out, recipe))
    result = discover(camp, DiscoverSettings(**SETTINGS))
    rows = [c for r in result.rounds for c in r.get("candidates", []) if "fell_back" in c]
    key = ":".join(planted.split(":")[:2])
    assert not [c["key"] for c in rows if c["key"] == key and c["fell_back"]]
    if not result.findings:
        res = next(r for r in result.resolution if r.key == key)
        headline, size = planted.split(":")[2].split("=")
        limit = res.detection_limit()
        assert limit is None or limit.values[headline] > float(size), limit
        return
    f = result.findings[0]
    assert (f.effect, f.component) == tuple(key.split(":")), f.evidence


@pytest.mark.slow  # ~140 s
@pytest.mark.parametrize("planted", ["backlash:worm_gear", "backlash:worm_gear:width_rad=0.007"])
def test_realistic_worm_gear_backlash_is_named_or_below_the_limit(tmp_path_factory, planted):
    """Issue #30: a worm-gear backlash on a rig that is not the model (drawn rig, inertias
    known 10 % off, AR(1) noise, quantisation, a torque-sensor lag, the bench's own
    integrator). The drawn 0.67° was named presliding hysteresis in the motor (its
    candidate's refit stuck at 0.13° from the catalogue's 2° start). Now: backlash in the
    worm gear with its width — or, at a production 0.4°, no finding with the resolution
    step putting the size below what these tests resolve. Never another effect."""
    out = tmp_path_factory.mktemp("realistic")
    recipe = BenchRecipe(effects=[planted], seed=100, plan=compact_plan(),
                         realism=BenchRealism.realistic())
    camp = read_campaign(run_bench(out, recipe))
    truth = json.loads((out / "truth.json").read_text())
    result = discover(camp, DiscoverSettings(**SETTINGS))
    true_w = truth["effects"][0]["parameters"]["width_rad"]
    if not result.findings:
        limit = next(r for r in result.resolution if r.key == "backlash:worm_gear"
                     ).detection_limit()
        assert limit is None or limit.values["width_rad"] > true_w, limit
        return
    f = result.findings[0]
    assert (f.effect, f.component) == ("backlash", "worm_gear"), f.evidence
    # measured 2026-11-25: 0.82° for 0.67°, 0.56° for a production 0.40° (the sensor lag
    # and the rest the bench adds leave a floor the gap's width trades against)
    assert f.parameters["width_rad"] == pytest.approx(true_w, rel=0.3 if true_w > 0.01 else 0.5)


@pytest.mark.slow  # ~3 min
def test_a_backlash_hidden_behind_misplaced_friction_is_named(tmp_path):
    """Realistic rig 200 (drawn rig, known values off, coloured noise, a torque lag): its
    base fit moves the rack's friction into the motor, and the worm-gear backlash
    candidate's refit stalled at 0.13° and 1.5 % of the stage while a motor Dahl term was
    named alone. With the stage's levels refitted before the width grid is read
    (``StageScorer._profiled_start``) it reached 42.5 %, still behind the Dahl term's 45.1 %;
    refitted from the Dahl term's stage fit (``catalogue._cross_seeded``) 50.3 %, and it is
    named first; nothing else is confident."""
    recipe = BenchRecipe(effects=["backlash:worm_gear"], seed=200, plan=compact_plan(),
                         realism=BenchRealism.realistic(), name="realistic")
    camp = read_campaign(run_bench(tmp_path, recipe))
    width = json.loads((tmp_path / "truth.json").read_text())["effects"][0]["parameters"][
        "width_rad"]
    result = discover(camp, DiscoverSettings(sparse=False, neural=False))
    cand = next(c for c in result.rounds[0]["candidates"] if c["key"] == "backlash:worm_gear")
    assert cand["relative_gain"] >= 0.3, cand
    assert cand["headline"]["width_rad"] == pytest.approx(width, rel=0.25)
    first = result.findings[0]
    assert ("backlash", "worm_gear") == (first.effect, first.component), first.evidence
    assert all(f.confidence < 0.5 for f in result.findings if f.effect != "backlash"), \
        [(f.effect, f.component, f.confidence) for f in result.findings]


@pytest.mark.slow  # ~3 min
def test_an_effect_masked_by_a_larger_one_is_named_once_that_one_is_in(tmp_path):
    """Realistic rig 121: a torsion-bar limit stop miscalibrates the cascade's torsion bar,
    and a rack position-dependent friction removed 0 % of its stage in round 1, 62.9 % once
    the stop was in. A later round rescored only what had shown evidence in round 1, so it
    was missed; the screen of every candidate against the extended model brings it back
    (``rounds/screen.py``). Both are named, with their components and sizes."""
    truth, named = _both_named(tmp_path, ["stiffness_limit_stop:torsion_bar",
                                          "position_dependent_friction:rack"], rig=121)
    stop = named["stiffness_limit_stop:torsion_bar"].parameters
    assert stop["stop_angle_rad"] == pytest.approx(
        truth["stiffness_limit_stop:torsion_bar"]["stop_angle_rad"], rel=0.15)
    bump = named["position_dependent_friction:rack"].parameters
    assert bump["position_m"] == pytest.approx(
        truth["position_dependent_friction:rack"]["position_m"], abs=0.005)


@pytest.mark.slow  # ~2.5 min
def test_a_gap_beside_an_asymmetry_is_named_once_the_asymmetry_is_refitted_with_it(tmp_path):
    """Realistic rig 120: a rack asymmetry (1.20) and a 0.49° worm-gear backlash. Round 1
    names the asymmetry, at 1.75 as it absorbs part of the gap; round 2 held it there and
    the gap refitted to 0.16° and 6.9 % of the stage (missed). Refitted with the round's
    candidates, as the extension fits it, the asymmetry returns to its size and the gap is
    named (2026-11-26: 1.206 and 0.54°, 55 % of the stage)."""
    truth, named = _both_named(tmp_path, ["backlash:worm_gear", "asymmetric_friction:rack"],
                               rig=120)
    assert named["asymmetric_friction:rack"].parameters["ratio"] == pytest.approx(
        truth["asymmetric_friction:rack"]["ratio"], rel=0.1)
    assert named["backlash:worm_gear"].parameters["width_rad"] == pytest.approx(
        truth["backlash:worm_gear"]["width_rad"], rel=0.25)


@pytest.mark.slow
def test_stated_values_a_bit_off_are_not_named_as_a_catalogue_effect(tmp_path):
    """eps-model.md: known values (inertias) "a few to 15 % off" are among what discovery
    must not force into a catalogue effect. A clean realistic rig with white noise (seed
    961: values written up to 10 % off, the motor inertia 4.65e-5 kg·m² for 5.15e-5, and
    the bench's 3 ms torque lag) had a rack load-dependent friction named at 0.23 (19.8 %
    of the free tie-rods stage, before 2026-11-27); the stated values refitted within
    ±15 % remove 24.4 % there. No catalogue name; the round says which values to check."""
    recipe = BenchRecipe(effects=[], seed=961, plan=compact_plan(),
                         realism=BenchRealism.realistic(noise_ar1=0.0))
    camp = read_campaign(run_bench(tmp_path, recipe))
    result = discover(camp, DiscoverSettings(sparse=False, neural=False, resolution=False))
    named = [(f.effect, f.component, f.confidence) for f in result.findings
             if f.effect != "unexplained"]
    assert named == [], [f.evidence for f in result.findings]
    declined = [g for r in result.rounds for g in r.get("rival_declined", [])
                if g["rival"] == "stated_values:campaign"]
    assert declined and "motor_inertia_kgm2" in declined[0]["reason"], result.rounds


def _both_named(tmp_path, effects: list[str], rig: int) -> tuple[dict, dict]:
    """Discovery on a realistic rig with ``effects`` planted: the truth's and the named
    catalogue findings' parameters by key, after checking that exactly those are named."""
    recipe = BenchRecipe(effects=effects, seed=rig, plan=compact_plan(),
                         realism=BenchRealism.realistic(), name="realistic")
    camp = read_campaign(run_bench(tmp_path, recipe))
    truth = {f"{e['effect']}:{e['component']}": e["parameters"]
             for e in json.loads((tmp_path / "truth.json").read_text())["effects"]}
    result = discover(camp, DiscoverSettings(sparse=False, neural=False))
    named = {f"{f.effect}:{f.component}": f for f in result.findings if f.effect != "unexplained"}
    assert set(named) == set(truth), {k: f.confidence for k, f in named.items()}
    return truth, named
