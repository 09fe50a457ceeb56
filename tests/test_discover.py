"""Discovery on the worm-gear backlash case and the units of its rounds (issue #4).

The backlash campaign's result is read by many tests (its name and width, the spec of
the record, what the control tests decide, failing figures and evidence); the other
hidden-effect cases are in test_hidden_effects.py.
"""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pandas as pd
import pytest
from discovery_cases import assert_first_finding, run_case
from scipy.stats import chi2

import mbst.discovery.extension as extension_mod
import mbst.discovery.pipeline as pipeline_mod
from mbst.cli import main
from mbst.discovery import acceptance
from mbst.discovery.pipeline import DiscoverSettings, discover
from mbst.discovery.rounds.resolution import scaled_size
from mbst.discovery.structure import CandidateScore, effective_samples, start_grid
from mbst.io.campaign import read_campaign
from mbst.report.discovery import discovery_record, write_discover_outputs
from mbst.systems.eps.bench import BenchRecipe, compact_plan, run_bench
from mbst.systems.eps.model import EPS_MODEL
from mbst.systems.eps.params import EFFECT_CATALOGUE, EFFECTS
from mbst.systems.friction_damper.bench import run_friction_damper_bench


def _spied(run):
    """``run()``'s discovery, with every simulated test id recorded in order.

    Every simulation of identification and discovery goes through
    ``fitting.twins_of_tests``; the spy replaces it wherever a module holds it.
    """
    import sys

    import mbst.identify.fitting as fitting_mod

    seen: list[str] = []
    real_twins, real_compare = fitting_mod.twins_of_tests, pipeline_mod.compare

    def spy_twins(pts, pss):
        seen.extend(pt.id for pt in pts)
        return real_twins(pts, pss)

    def spy_compare(*a, **k):
        seen.append("COMPARE")
        return real_compare(*a, **k)

    holders = [m for name, m in list(sys.modules.items()) if name.startswith("mbst.")
               and getattr(m, "twins_of_tests", None) is real_twins]
    assert fitting_mod in holders and len(holders) >= 4  # fitting, identify, structure, ...
    with pytest.MonkeyPatch.context() as mp:
        for mod in holders:
            mp.setattr(mod, "twins_of_tests", spy_twins)
        mp.setattr(pipeline_mod, "compare", spy_compare)
        camp, truth, result = run()
    result.simulated_ids = seen
    return camp, truth, result


@pytest.fixture(scope="module")
def backlash(tmp_path_factory):
    """The worm-gear backlash case on the compact plan (~3 min: its tests are slow; CI
    checks the same case on the demo pipeline's own run, ``.ci/demo_answer.py``)."""
    # without the resolution step (12.7 s alone, ~20 s in CI beside the other worker):
    # the clean campaign's test checks it and its report section
    return _spied(lambda: run_case(tmp_path_factory, ["backlash:worm_gear"],
                                   resolution=False))


@pytest.fixture(scope="module")
def play(tmp_path_factory):
    """A play planted in the friction damper's band (a few seconds): the whole discovery
    path, rounds, evidence, comparison and outputs, at a size CI can afford."""
    def run():
        out = tmp_path_factory.mktemp("play")
        camp = read_campaign(run_friction_damper_bench(
            out, {"band.backlash.width_m": 1.2e-3}, seed=3))
        return camp, None, discover(camp, DiscoverSettings(max_effects=1, neural=False))
    return _spied(run)


@pytest.mark.slow  # the backlash case (~3 min)
def test_worm_gear_backlash_is_named_with_its_width(backlash):
    camp, truth, result = backlash
    assert_first_finding(result, "backlash:worm_gear", truth)
    f = result.findings[0]
    assert 0.5 < f.confidence <= 1.0
    assert f.cv["folds"] == 3 and f.cv["wins"] >= 2
    assert "structure test" in f.evidence and "runner-up" in f.evidence
    # the unexplained round finds nothing left beside it, and says so
    assert f.confirmation == "confirmed", f.evidence
    assert [g.effect for g in result.findings] == ["backlash"]


@pytest.mark.slow  # the backlash case (~3 min)
def test_extension_restores_control_fit_to_the_true_model(backlash):
    _, _, result = backlash
    wide = result.comparison.pivot_table(index=["test", "channel"], columns="model",
                                         values="fit_percent")
    torque = wide.xs("steering_torque_nm", level="channel")
    assert (torque["base"] < torque["true"] - 3).all()  # the effect is visible on the control
    # the compact plan has a third of the demo's data: 1.5 points here, 0.1 on the demo
    # campaign (benchmarks/discover.py)
    assert (torque["extended"] > torque["true"] - 1.5).all()
    closed = (torque["extended"] - torque["base"]) / (torque["true"] - torque["base"])
    assert (closed > 0.85).all()
    assert result.gain["control_fit_percent_mean"] > 0


@pytest.mark.slow  # the backlash case (~3 min)
def test_discovery_record_follows_the_spec(backlash):
    _, _, result = backlash
    rec = json.loads(json.dumps(discovery_record(result)))
    assert rec["format"] == "mbst-discovery/2"
    for key in ("campaign", "base", "findings", "extended", "gain"):
        assert key in rec
    f = rec["findings"][0]
    spec = EFFECTS[f"{f['effect']}:{f['component']}"]
    assert set(f["parameters"]) == set(spec.headline)
    assert isinstance(f["evidence"], str) and 0 <= f["confidence"] <= 1
    assert set(rec["base"]["control_fit_percent"]) == {"s2_sine_0p8hz_ctrl"}
    assert "worm_gear.backlash.width_rad" in rec["extended"]["params"]
    assert "worm_gear.backlash.width_rad" not in rec["base"]["params"]
    assert rec["gain"]["aic_delta"] < 0


@pytest.mark.slow  # the backlash case (~3 min)
def test_control_tests_decide_nothing(backlash):
    """No control test is simulated before the comparison step (spied in the fixture)."""
    _, _, result = backlash
    seen = result.simulated_ids
    assert "COMPARE" in seen
    before = seen[: seen.index("COMPARE")]
    assert {"s1_sine_0p5hz", "s2_sine_0p25hz"} <= set(before)
    assert "s2_sine_0p8hz_ctrl" not in before
    assert "s2_sine_0p8hz_ctrl" in seen[seen.index("COMPARE"):]


def test_control_tests_decide_nothing_in_any_family(play):
    """The same guard on the friction damper's whole discovery (CI's share): its held-out
    earthquake record is simulated only once the comparison starts."""
    camp, _, result = play
    seen = result.simulated_ids
    assert "COMPARE" in seen and result.findings
    before = seen[: seen.index("COMPARE")]
    ids = {t.id for t in camp.identification_tests()}
    controls = {t.id for t in camp.tests if t.role == "control"}
    assert controls and ids <= set(before)
    assert not controls & set(before)
    assert controls <= set(seen[seen.index("COMPARE"):])


def test_effective_samples_counts_coloured_noise_as_fewer_samples():
    rng = np.random.default_rng(0)
    white = rng.standard_normal(4000)
    coloured = np.convolve(white, np.ones(20) / 20, mode="same")
    assert effective_samples([white]) == pytest.approx(4000, rel=0.15)
    assert effective_samples([coloured]) < 600


def test_start_grid_covers_each_headline_parameter():
    for spec in EFFECT_CATALOGUE:
        grid = start_grid(spec, EPS_MODEL)
        assert grid, spec.key
        for name in spec.free:
            assert len({g[name] for g in grid}) >= 2, (spec.key, name)


def test_resolution_is_judged_against_the_model_as_it_stands(monkeypatch):
    """What an accepted effect explains is no longer a candidate of the resolution step
    (the backlash fixture runs without that step; its report is checked on the clean
    campaign, tests/test_hidden_effects.py)."""
    from types import SimpleNamespace

    import mbst.discovery.rounds.resolution as resolution_mod

    seen = {}
    monkeypatch.setattr(resolution_mod, "campaign_resolution",
                        lambda *a, **k: seen.update(k) or [])
    state = SimpleNamespace(
        ids=[], p=np.zeros(1), p_searched=None, scales={},
        model_free_by_stage={"free_tie_rods": ["x"]},
        accepted=["backlash:worm_gear"], compensating=lambda: {"x": 1.0}, timings={},
        rounds=[], model=EPS_MODEL,
        settings=SimpleNamespace(min_relative_gain=0.1, min_aic_drop=None,
                                 identify=SimpleNamespace(decimate=2)))
    resolution_mod.resolution_round(state)
    assert seen["exclude"] == {"backlash:worm_gear"}
    assert seen["reset"] == {"x": 1.0}
    assert state.resolution == [] and "resolution_s" in state.timings
    # ... and the step leaves out what it is told to: every pair but one the blocked
    # column cannot show is excluded, so nothing is simulated and that one is not tested
    monkeypatch.undo()
    pt = SimpleNamespace(model=EPS_MODEL, scenario="blocked_column",
                         spec=SimpleNamespace(motor="passive"))
    keep = "stribeck_friction:tires"
    out = resolution_mod.campaign_resolution(
        [pt], np.zeros(len(EPS_MODEL.param_index)), {}, {}, 0.1, None,
        exclude={e.key for e in EFFECT_CATALOGUE} - {keep})
    assert [(r.key, r.stage, r.sizes) for r in out] == [(keep, None, [])]


def _stated(refit_share: float, predicted_share: float, other_side: bool = False,
            multiple: float = 0.36):
    """A pair resolved from 0.2x, judged against a refit that removed ``refit_share`` at
    ``multiple`` of the realistic size, where the prediction there says ``predicted_share``
    (ΔAIC −50 both)."""
    from mbst.discovery.rounds.resolution import RefitCheck, Resolution, SizeScore, judge_refit

    sizes = [SizeScore(m, {"static_to_coulomb_ratio": 1 + 0.8 * m}, 0.5 * m, -200 * m)
             for m in (0.1, 0.2, 1.0)]
    r = Resolution("stribeck_friction:motor", "stribeck_friction", "motor", "free_tie_rods",
                   ["static_to_coulomb_ratio"], sizes, resolved_from=0.2, aic_drop_needed=10.5,
                   other_side=list(sizes), other_side_resolved_from=0.2)
    r.refit = RefitCheck(SizeScore(multiple, {"static_to_coulomb_ratio": 1.29},
                                   predicted_share, -50.0), refit_share, -50.0, other_side)
    judge_refit(r, 0.10, 10.5)
    return r


def test_a_limit_of_an_effect_that_grows_as_its_parameter_falls_is_stated_that_way():
    """Realistic rig 2512: the motor presliding, resolved already at the weakest size tried
    (stiffness 20: stiffer is weaker), read "at or below stiffness = 20", the wrong way
    round: every stiffness of 20 and less was resolved. A parameter that falls as the
    effect grows (a presliding's stiffness, a power law's exponent below 1) is stated "at
    or above", "from … down" and "not resolved down to"; one that rises keeps its words."""
    from mbst.discovery.rounds.resolution import Resolution, SizeScore
    from mbst.report.discovery import limit_text

    def pair(values, resolved_from):
        sizes = [SizeScore(m, {"stiffness": v}, 0.3 * m, -60 * m)
                 for m, v in zip((0.1, 0.5, 1.0, 4.0), values, strict=True)]
        return Resolution("presliding_hysteresis:motor", "presliding_hysteresis", "motor",
                          "free_tie_rods", ["stiffness"], sizes, resolved_from=resolved_from)

    falls = (20.0, 4.0, 2.0, 0.5)
    assert limit_text(pair(falls, 0.1), False) == ("at or above stiffness = 20, weaker than "
                                                   "the realistic size")
    assert limit_text(pair(falls, 1.0), False) == "from stiffness = 2 down, the realistic size"
    assert limit_text(pair(falls, None), False) == "**not resolved** down to stiffness = 0.5"
    rises = (0.2, 1.0, 2.0, 8.0)
    assert limit_text(pair(rises, 0.1), False) == ("at or below stiffness = 0.2, below the "
                                                   "realistic size")
    assert limit_text(pair(rises, 4.0), False) == "from stiffness = 8, 4× the realistic size"
    assert limit_text(pair(rises, None), False) == "**not resolved** up to stiffness = 8"


def test_a_limit_the_structure_tests_own_refit_contradicts_is_not_stated():
    """At a refit's optimum the share it removes is, to first order, the prediction at the
    size it reached. Realistic rig 954: a motor Stribeck of 1.54 missed, its refit reaching
    6.9 % of the stage at 1.29, while the limit was stated at 1.16 — an empty answer that
    ruled out what the rig had. Where the prediction at the refit's size clears the margins
    and the refit did not, no limit is stated on that side, and the report says why."""
    from types import SimpleNamespace

    from mbst.report.discovery import limit_text, resolution_lines, resolution_table

    r = _stated(0.069, 0.18)
    # both sides: one linearisation gives both limits, and the refit, free on both sides,
    # tests it (realistic rig 2412: a rack power law at 1.5 missed, its refit at 0.69
    # removing 1.3 % where 86 % was predicted, while the other way read "from 1.1")
    assert r.refit.contradicts and r.resolved_from is None and r.other_side_resolved_from is None
    text = limit_text(r, False)
    assert "no limit stated" in text and "6.9 %" in text and "18.0 %" in text
    assert limit_text(r, True).startswith("**no limit stated** either")
    from mbst.report.discovery_figures import _side_label  # the figure's label says it too

    assert _side_label(r, False) == ("no limit stated (its refit removed 7 % where 18 % is "
                                     "predicted)")
    assert _side_label(r, True) == "no limit stated either"
    table = resolution_table([r])
    refit_row = table[table.side == "refit"]
    assert refit_row.refit_relative_gain.item() == 0.069
    assert not table[table.side == "realistic"].resolved.any()
    result = SimpleNamespace(settings=DiscoverSettings(), resolution=[r], rounds=[],
                             base=SimpleNamespace(model=EPS_MODEL))
    assert any("no limit stated" in line for line in resolution_lines(result))
    # a refit on the other side of neutral withholds both limits alike
    other = _stated(0.069, 0.18, other_side=True)
    assert other.resolved_from is None and other.other_side_resolved_from is None
    assert limit_text(other, False).startswith("**no limit stated** either")
    # a refit that agrees with the prediction, or stopped where no effect would show,
    # leaves the limit as predicted
    assert _stated(0.17, 0.18).resolved_from == 0.2
    assert _stated(0.03, 0.04).resolved_from == 0.2
    # ... and a refit below the stated limit does not test it (a clean bench's rack
    # presliding refit ended at 0.005x, the Dahl law's stiff end: 27 % predicted, 0.7 %)
    assert _stated(0.007, 0.27, multiple=0.005).resolved_from == 0.2


def test_a_refits_size_reads_as_a_multiple_of_the_realistic_size():
    """``size_multiple`` reads ``scaled_size`` backwards, on either side of neutral and for
    a size that grows as its parameter falls (a presliding stiffness)."""
    from mbst.discovery.rounds.resolution import size_multiple

    for key, m, other in [("stribeck_friction:motor", 0.36, False),
                          ("presliding_hysteresis:rack", 2.0, False),
                          ("power_law_damping:rack", 0.5, True),
                          ("stiffness_limit_stop:torsion_bar", 1.5, False)]:
        spec = EFFECTS[key]
        values = scaled_size(spec, EPS_MODEL, m, other_side=other)
        assert size_multiple(spec, EPS_MODEL, values, other) == pytest.approx(m), key


def test_the_refits_checked_are_those_scored_on_the_model_the_step_predicts_from():
    """Only the last structure round's refits, and only where it accepted nothing and no
    backward check moved the model after it; a refit that fell back was not tested."""
    from mbst.discovery.rounds.resolution import last_round_refits

    cand = {"key": "stribeck_friction:motor", "relative_gain": 0.069, "aic_delta": -14.3,
            "fell_back": False,
            "headline": {"static_to_coulomb_ratio": 1.29, "stribeck_velocity": 1.4}}
    fell = {**cand, "key": "stribeck_friction:rack", "fell_back": True}
    first = {"round": 1, "candidates": [], "accepted": "backlash:worm_gear"}
    last = {"round": 2, "candidates": [cand, fell], "accepted": None}
    stick = {"round": 3, "method": "stick_slip", "candidates": [], "accepted": None}
    refits = last_round_refits([first, last, stick], EPS_MODEL)
    assert list(refits) == ["stribeck_friction:motor"]
    rf = refits["stribeck_friction:motor"]
    assert rf.values == {"motor.stribeck_friction.static_to_coulomb_ratio": 1.29,
                         "motor.stribeck_friction.stribeck_velocity": 1.4}
    assert (rf.share, rf.aic_delta) == (0.069, -14.3)
    assert last_round_refits([last, first], EPS_MODEL) == {}
    dropped = {"round": 3, "kind": "backward", "dropped": ["backlash:worm_gear"]}
    assert last_round_refits([first, last, dropped], EPS_MODEL) == {}


def test_a_pair_the_last_rounds_screen_spared_is_checked_against_its_earlier_refit():
    """Where the last round's screen refitted a pair no more, its latest earlier refit
    checks the prediction (realistic rig 2301: a present rack load-dependent friction
    refitted in round 1 at 3.9 % was stated resolved from 0.024 after round 2 refitted
    nothing). It passes where it cleared the margins in its own round or with the cost it
    removed carried to what is left now (the demo's rack power law: 0.56 % of a stage the
    backlash then cut to 2.8 %)."""
    from mbst.discovery.rounds.resolution import (
        RefitCheck,
        Resolution,
        SizeScore,
        judge_refit,
        last_round_refits,
    )
    from mbst.discovery.structure import aic_delta
    from mbst.report.discovery import limit_text

    load = {"key": "load_dependent_friction:rack", "relative_gain": 0.039, "aic_delta": -21.4,
            "cost_base": 1000.0, "fell_back": False, "headline": {"coefficient": 0.079}}
    gap = {**load, "key": "backlash:worm_gear", "relative_gain": 0.49,
           "headline": {"width_rad": 0.008}}
    first = {"round": 1, "candidates": [gap, load], "accepted": "backlash:worm_gear"}
    second = {"round": 2, "candidates": [], "accepted": None}
    rf = last_round_refits([first, second], EPS_MODEL)["load_dependent_friction:rack"]
    assert (rf.round, rf.share, rf.aic_delta, rf.stage_cost) == (1, 0.039, -21.4, 1000.0)
    # 39 of the 1000 it was refitted against; 510 are left now: 7.6 %
    share, aic = rf.carried(510.0, 500.0, 1)
    assert share == pytest.approx(39.0 / 510.0)
    assert aic == pytest.approx(aic_delta(471.0, 510.0, 500.0, 1))
    # the last round's own refit of the pair comes first, taken as it is
    third = {"round": 3, "candidates": [{**load, "relative_gain": 0.02}], "accepted": None}
    rf3 = last_round_refits([first, second, third], EPS_MODEL)[load["key"]]
    assert (rf3.round, rf3.share, rf3.carried(510.0, 500.0, 1)) == (None, 0.02, None)

    def judged(carried_to: float) -> Resolution:
        r = Resolution(load["key"], "load_dependent_friction", "rack", "free_tie_rods",
                       ["coefficient"],
                       sizes=[SizeScore(0.3, {"coefficient": 0.024}, 0.16, -48)],
                       resolved_from=0.3)
        r.refit = RefitCheck(SizeScore(0.99, {"coefficient": 0.079}, 0.71, -355), rf.share,
                             rf.aic_delta, False, rf.round, rf.carried(carried_to, 500.0, 1))
        judge_refit(r, 0.10, 10.4)
        return r

    # the prediction at that size clears the margins, the refit on neither reading: no
    # limit stated
    r = judged(510.0)
    assert r.refit.contradicts and r.resolved_from is None
    assert r.refit.record()["refit_round"] == 1
    assert "refit in round 1" in limit_text(r, False) and "7.6 % of what is left now" in \
        limit_text(r, False)
    # carried to a residual cut to a tenth, it clears: the limit stands
    r = judged(100.0)
    assert not r.refit.contradicts and r.resolved_from == 0.3


def test_effect_sizes_scale_from_the_neutral_value():
    """Only what sets an effect's strength is scaled, away from its neutral value."""
    stop = scaled_size(EFFECTS["stiffness_limit_stop:torsion_bar"], EPS_MODEL, 2.0)
    assert stop == {"torsion_bar.stiffness_limit_stop.stop_angle_rad": 0.02,  # where it stops
                    "torsion_bar.stiffness_limit_stop.stiffness_ratio": 15.0}  # 1 + 2 x 7
    power = scaled_size(EFFECTS["power_law_damping:motor"], EPS_MODEL, 2.0)
    assert power == {"motor.power_law_damping.exponent": 0.2}  # 1 - 2 x 0.5, at its bound
    # ... and the other way from neutral, from its realistic size there (1.5)
    spec = EFFECTS["power_law_damping:motor"]
    assert scaled_size(spec, EPS_MODEL, 0.5, other_side=True) == {
        "motor.power_law_damping.exponent": 1.25}
    assert scaled_size(spec, EPS_MODEL, 4.0, other_side=True) == {
        "motor.power_law_damping.exponent": 2.0}  # 1 + 4 x 0.5, at its bound
    asym = EFFECTS["asymmetric_friction:rack"]  # a mirror image: one side tells the other
    assert scaled_size(asym, EPS_MODEL, 1.0, other_side=True) == asym.default_size
    dahl = scaled_size(EFFECTS["presliding_hysteresis:rack"], EPS_MODEL, 2.0)
    assert dahl == {"rack.presliding_hysteresis.stiffness": 5e6}  # twice the presliding travel
    strib = scaled_size(EFFECTS["stribeck_friction:rack"], EPS_MODEL, 1.5)
    assert strib["rack.stribeck_friction.static_to_coulomb_ratio"] == pytest.approx(2.2)
    assert strib["rack.stribeck_friction.stribeck_velocity"] == 1e-3


@pytest.mark.slow  # the backlash case (~3 min)
def test_discover_outputs_carry_the_findings(backlash, tmp_path):
    _, _, result = backlash
    write_discover_outputs(result, tmp_path)
    on_disk = json.loads((tmp_path / "discovery.json").read_text())
    assert on_disk["findings"] == json.loads(json.dumps(discovery_record(result)))["findings"]
    table = pd.read_csv(tmp_path / "comparison.csv")
    assert set(table.model) == {"base", "extended", "true"}
    merged = table.merge(result.comparison, on=["test", "channel", "model"])
    assert len(merged) == len(result.comparison)
    np.testing.assert_allclose(merged.fit_percent_x, merged.fit_percent_y, atol=1e-3)
    ranking = pd.read_csv(tmp_path / "structure_test.csv")
    assert ranking.iloc[0]["key"] == "backlash:worm_gear"
    report = (tmp_path / "discovery.md").read_text()
    assert "| 1 | backlash | worm_gear |" in report
    # what these tests resolve is written and checked on the clean campaign
    # (test_hidden_effects.py): the fixture runs without that step, for CI's time
    assert pd.read_csv(tmp_path / "resolution.csv").empty
    for fig in ("reversal_zoom.png", "structure_test.png", "comparison.png", "hysteresis.png"):
        assert (tmp_path / "figures" / fig).stat().st_size > 10_000


def test_outputs_carry_the_findings_in_any_family(play, tmp_path):
    """What `mbst discover` writes holds the answer as the spec says (CI's share of the
    backlash case's output tests): the record's format and finding, the comparison table
    as scored, the engineer's figures."""
    _, _, result = play
    write_discover_outputs(result, tmp_path)
    rec = json.loads((tmp_path / "discovery.json").read_text(),
                     parse_constant=lambda c: pytest.fail(f"not JSON: {c}"))
    assert rec["format"] == "mbst-discovery/2"
    assert rec["findings"] == json.loads(json.dumps(discovery_record(result)))["findings"]
    f = rec["findings"][0]
    spec = result.base.model.effects[f"{f['effect']}:{f['component']}"]
    assert set(f["parameters"]) == set(spec.headline) and 0 <= f["confidence"] <= 1
    # the play's width is measured by these tests: its noise-only standard error is stated
    # and small beside it, and the finding does not call it unmeasured
    se = f["size_std_error"]["width_m"]
    assert 0 < se < 0.1 * f["parameters"]["width_m"]
    assert "size_not_measured" not in f and "SIZE NOT MEASURED" not in f["evidence"]
    table = pd.read_csv(tmp_path / "comparison.csv")
    merged = table.merge(result.comparison, on=["test", "channel", "model"])
    assert len(merged) == len(result.comparison) > 0
    np.testing.assert_allclose(merged.fit_percent_x, merged.fit_percent_y, atol=1e-3)
    assert "| 1 | backlash | band |" in (tmp_path / "discovery.md").read_text()
    for fig in ("structure_test.png", "comparison.png", "hysteresis.png"):
        assert (tmp_path / "figures" / fig).stat().st_size > 10_000


def test_cli_discover_bad_campaign_writes_nothing(tmp_path, capsys):
    camp_dir = run_bench(tmp_path / "bench", BenchRecipe(effects=[], seed=1, plan=compact_plan()))
    f = camp_dir / "tests" / "s2_ramp.csv"
    df = pd.read_csv(f)
    df.loc[9, "rack_position_m"] = np.nan
    df.to_csv(f, index=False)
    out = tmp_path / "out"
    assert main(["discover", str(camp_dir), "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    assert "'s2_ramp'" in err and "rack_position_m" in err and "row 10" in err
    assert not out.exists()


@pytest.fixture(scope="module")
def clean_compact(tmp_path_factory):
    return run_bench(tmp_path_factory.mktemp("bench"),
                     BenchRecipe(effects=[], seed=1, plan=compact_plan()))


@pytest.mark.parametrize("command", [
    ["discover", "--tau", "nan"],  # a bare ValueError from the optimiser's bounds
    ["identify", "--tau", "inf"],
    ["preprocess", "--tau", "-0.005"],
    ["discover", "--multistart", "0"],  # identify refused it, discover ran
    ["discover", "--min-aic-drop", "nan"],
])
def test_cli_settings_outside_what_they_mean_are_refused_by_name(clean_compact, tmp_path,
                                                                  capsys, command):
    camp_dir = clean_compact
    out = tmp_path / "out"
    assert main([command[0], str(camp_dir), "--out", str(out), "--quiet", *command[1:]]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"mbst {command[0]}: error: {command[1]} must be")
    assert "Traceback" not in err and not out.exists()


def test_confidence_weighs_candidates_with_one_sample_count():
    """A candidate removing 91 % of a stage's cost outweighs one removing 64 %.

    Each candidate's own ΔAIC counts its own residual's effective samples; the
    demo-assist campaign's backlash (507 samples) lost its weight to a motor
    hysteresis (1767) before the weights used one count.
    """
    from types import SimpleNamespace

    from mbst.discovery.acceptance import akaike_weight
    from mbst.discovery.structure import aic_delta

    def cand(gain, n_eff):
        return SimpleNamespace(stage="free_tie_rods", cost=1.0 - gain, cost_base=1.0,
                               k_effect=1, n_eff=n_eff,
                               aic_delta=aic_delta(1.0 - gain, 1.0, n_eff, 1))

    backlash, hysteresis = cand(0.913, 507.0), cand(0.643, 1767.0)
    assert hysteresis.aic_delta < backlash.aic_delta  # what misled the old weight
    assert akaike_weight(backlash, [backlash, hysteresis]) > 0.99
    assert akaike_weight(hysteresis, [hysteresis, backlash]) < 0.01


def test_a_tie_is_declared_only_between_components_that_move_as_one_body():
    """Motor and rack behind a rigid mesh, removing 89.3 vs 89.1 %, are one answer.

    The same score gap between components that move differently, or a clear gap
    between tied ones, names one component.
    """
    from types import SimpleNamespace

    from mbst.discovery.acceptance import tied_components
    from mbst.discovery.data import TestResidual

    t = np.linspace(0.0, 4.0, 2001)
    pinion = np.cos(2 * np.pi * 0.5 * t)
    rng = np.random.default_rng(0)

    def test_(i, motor):
        return TestResidual(id=f"t{i}", scenario="free_tie_rods", role="identification",
                            motor="passive", dt_s=t[1], time_s=t, angle_rad=pinion,
                            omega_rad_per_s=pinion, measured={}, simulated={},
                            states={"rack_speed_m_per_s": 7.5e-3 * pinion,
                                    "motor_speed_rad_per_s": motor})

    one_body = {"t0": test_(0, 16.5 * pinion * (1 + 1e-4 * rng.standard_normal(t.size)))}
    apart = {"t0": test_(0, 16.5 * np.sin(2 * np.pi * 0.5 * t))}

    def cand(effect, component, gain, params=None):
        return SimpleNamespace(key=f"{effect}:{component}", effect=effect,
                               component=component, stage="free_tie_rods", tests=["t0"],
                               cost=1.0 - gain, cost_base=1.0, params=params)

    rack = cand("asymmetric_friction", "rack", 0.8925)
    motor = cand("asymmetric_friction", "motor", 0.8910)
    column = cand("asymmetric_friction", "steering_column", 0.8920)
    other = cand("presliding_hysteresis", "motor", 0.8920)
    scores = [rack, column, other, motor]
    tied = tied_components(rack, scores, one_body, EPS_MODEL)
    assert [(s.component, round(c, 3)) for s, c in tied] == [("motor", 1.0)]
    assert tied_components(rack, scores, apart, EPS_MODEL) == []
    weak_motor = cand("asymmetric_friction", "motor", 0.87)  # 2.25 points less removed
    assert tied_components(rack, [rack, weak_motor], one_body, EPS_MODEL) == []
    # ... unless its size ended on the end of its range: its cost is then a bound, set by
    # how the base fit split the levels (realistic rig 122: 46.2 % at a ratio of 3.99 of 4
    # beside the winner's 50.3 % at 1.26)
    p = np.array(EPS_MODEL.default_vector(), float)
    p[EPS_MODEL.param_index["motor.asymmetric_friction.ratio"]] = 3.986
    censored = cand("asymmetric_friction", "motor", 0.87, params=p)
    assert [s.component for s, _ in
            tied_components(rack, [rack, censored], one_body, EPS_MODEL)] == ["motor"]
    assert tied_components(rack, [rack, censored], apart, EPS_MODEL) == []
    p[EPS_MODEL.param_index["motor.asymmetric_friction.ratio"]] = 2.5
    assert tied_components(rack, [rack, cand("asymmetric_friction", "motor", 0.87, params=p)],
                           one_body, EPS_MODEL) == []


@pytest.mark.slow  # the backlash case (~3 min)
def test_base_refit_also_starts_from_the_reset_parameters(backlash):
    """A gain the reset start alone gives belongs to the base model, not to an effect.

    The extended model with its gear stiffness stuck at 1000 N·m/rad and its mesh
    damping at its bound of 20 N·m·s/rad (how a base model compensates for the
    backlash: soft and heavily damped; demo-assist kept such a gear and a motor
    Dahl term then "removed" 33 % of the stage cost): refitted only from where it
    is, the stage stays 70 % above the fitted cost; from the reset start too it
    gets back within 0.1 %. (With the stiffness alone stuck the plain refit stayed
    9 % above on one machine and escaped to 0.6 % on another: the test needs a
    start that stays stuck.)
    """
    from mbst.discovery.restarts import compensating_parameters
    from mbst.discovery.structure import StageScorer
    from mbst.identify.fitting import channel_scales

    camp, _, result = backlash
    model = result.base.model
    ids = [result.base.prepared[s.id] for s in camp.identification_tests()]
    stage = model.stage_tests("free_tie_rods", ids)
    fitted = result.extended_params
    stuck = fitted.copy()
    stuck[model.param_index["worm_gear.stiffness_nm_per_rad"]] = 1000.0
    stuck[model.param_index["worm_gear.damping_nms_per_rad"]] = model.spec(
        "worm_gear.damping_nms_per_rad").upper
    reset = compensating_parameters(stuck, list(model.stage_free()["free_tie_rods"]), model)
    assert {"worm_gear.stiffness_nm_per_rad", "worm_gear.damping_nms_per_rad"} <= set(reset)
    args = (stage, "free_tie_rods", stuck, channel_scales(ids), result.base.preid["upper"], 2)
    plain, with_reset = StageScorer(*args), StageScorer(*args, reset=reset)
    cost_fitted = plain.costs(fitted[None]).sum()
    assert plain.base_refit()[1] > 1.3 * cost_fitted
    assert with_reset.base_refit()[1] < 1.03 * cost_fitted


@pytest.mark.parametrize("quick_cost, expected_runs", [(0.9, [1]), (1.1, [1, 3])])
def test_extension_falls_back_to_the_cascade_restarts(monkeypatch, quick_cost, expected_runs):
    """The quick extension (deliberate starts only) stands when it lowers the cost;
    otherwise the cascade runs again with its own restarts and that result counts.

    (The powered backlash case needs the fallback; it is slow, so the branch is
    checked here with a stand-in cascade.)
    """
    from mbst.identify.cascade import IdentifySettings

    runs: list[int] = []

    def cascade(campaign, settings, ids, scales, starts, extra_free, work_reference=None):
        runs.append(settings.multistart)
        cost = quick_cost if settings.multistart == 1 else 0.5
        return np.full(2, float(settings.multistart)), cost

    monkeypatch.setattr(extension_mod, "extended_cascade", cascade)
    p, cost = extension_mod.extend(None, IdentifySettings(multistart=3), [], {}, [None], {}, 1.0)
    assert runs == expected_runs
    assert cost == (0.9 if expected_runs == [1] else 0.5)
    assert p[0] == expected_runs[-1]


@pytest.mark.slow  # ~14 s in CI: a tires_on_ground campaign of its own; CI's time
def test_tires_candidates_refit_the_offsets_the_cascade_frees(tmp_path):
    """A tire friction asymmetry is symmetric friction plus a constant force, which a base
    fit puts into the tie-rod force offsets. Refitted with only the tire parameters the
    asymmetry cannot pay; with the cascade's free set of that stage (the offsets are first
    measured there) it removes nearly all of the stage cost."""
    from mbst.discovery.structure import StageScorer
    from mbst.identify.fitting import channel_scales, prepare_test

    recipe = BenchRecipe(effects=["asymmetric_friction:tires"], seed=1)
    camp = read_campaign(run_bench(tmp_path, recipe))
    tests = [prepare_test(camp, s, 0.005) for s in camp.identification_tests()
             if s.scenario == "tires_on_ground"]
    base = recipe.true_params()
    idx = EPS_MODEL.param_index
    base[idx["tires.asymmetric_friction.ratio"]] = 1.0
    for side in ("left", "right"):  # where the base fit (demo plan) put the mean force
        base[idx[f"offset.tie_rod_force_{side}_n"]] += 216.0
    cascade_free = [*EPS_MODEL.stage_free()["tires_on_ground"],
                    "offset.tie_rod_force_left_n", "offset.tie_rod_force_right_n"]
    spec = EPS_MODEL.effects["asymmetric_friction:tires"]
    args = (tests, "tires_on_ground", base, channel_scales(tests))
    gains = {}
    for label, free in (("isolated", None), ("cascade", cascade_free)):
        scorer = StageScorer(*args, free=free)
        gains[label] = scorer.score(spec, 1000.0).relative_gain
    assert gains["cascade"] > 0.99, gains  # measured 99.98 %
    assert gains["isolated"] < 0.8, gains  # measured 47.6 %: the offsets hold the mean force


def test_extension_keeps_its_start_when_the_cascade_ends_worse(monkeypatch):
    """A start is already a complete extended model; a cascade that ends in a worse basin
    from it must not cost the finding (the powered backlash case: start 0.00163, cascade
    0.00762 against the base's 0.00413)."""
    from mbst.identify.cascade import Cascade, IdentifySettings

    def cascade(campaign, settings, base, extra_free, work_reference=None):
        return Cascade(base + 1.0, [], {}, [], {})  # the cascade moves every parameter

    def cost(ids, p, scales, decimate=2):
        return float(p[0]), []  # the moved vector costs more than its start

    monkeypatch.setattr(extension_mod, "run_cascade", cascade)
    monkeypatch.setattr(extension_mod, "total_cost", cost)
    start = np.array([0.3, 7.0])
    p, c = extension_mod.extended_cascade(None, IdentifySettings(), [], {}, [start, None], {})
    np.testing.assert_array_equal(p, start)
    assert c == 0.3


def test_a_candidate_with_evidence_refines_from_the_level_it_absorbed(tmp_path, monkeypatch):
    """A fit without Stribeck lifts the element's Coulomb level to stand in for the rise
    (tires: 3544 N for a true 2600 N, and the refit then stalled at 39 % of the stage cost).
    A candidate that removed at least the evidence share at screening refines also from
    that level back at its typical value; one below it, or an effect nothing absorbs,
    does not (their refits stay as cheap as before)."""
    from dataclasses import replace

    import mbst.discovery.structure as structure_mod
    from mbst.discovery.structure import StageScorer
    from mbst.identify.fitting import channel_scales, prepare_test

    recipe = BenchRecipe(effects=[], seed=1, plan=compact_plan())
    camp = read_campaign(run_bench(tmp_path, recipe))
    tests = [prepare_test(camp, s, 0.005) for s in camp.identification_tests()
             if s.scenario == "blocked_column"]
    coulomb = "steering_column.coulomb_nm"
    i = EPS_MODEL.param_index[coulomb]
    base = recipe.true_params()
    base[i] *= 1.5  # lifted, but inside the 3x that the reset counts as compensation
    scorer = StageScorer(tests, "blocked_column", base, channel_scales(tests),
                         evidence_gain=0.05)
    seen: list[list[float]] = []
    real_solve = structure_mod.solve

    def spy(prob, starts, **kw):
        seen.append([float(s[i]) for s in starts])
        return real_solve(prob, starts, **kw)

    monkeypatch.setattr(structure_mod, "solve", spy)
    typical = EPS_MODEL.spec(coulomb).default
    for key, gain, extra in (("stribeck_friction:steering_column", 0.06, True),
                             ("stribeck_friction:steering_column", 0.04, False),
                             ("asymmetric_friction:steering_column", 0.5, False)):
        spec = EPS_MODEL.effects[key]
        screened = scorer.score(spec, 1000.0, max_nfev=2)
        seen.clear()
        scorer.score(spec, 1000.0, max_nfev=2,
                     start=replace(screened, cost=(1.0 - gain) * screened.cost_base))
        # the first solve holds the starts; any later one continues the refit to
        # convergence or runs the neutral start (#34), from one start each
        starts = seen[0]
        assert (typical in starts) is extra, (key, gain, starts)
        assert len(starts) == 1 + extra
        assert all(len(later) == 1 for later in seen[1:]), seen


def test_a_failing_figure_or_page_never_loses_the_answer(play, tmp_path, monkeypatch):
    """Issue #30: a figure that dies (here as the reported ``KeyError: 'sindy'``) and a page
    that cannot be drawn up are listed as failures; discovery.json still holds the answer."""
    from mbst.report import discovery as discovery_report
    from mbst.report import discovery_figures

    _, _, result = play
    result = dataclasses.replace(result, failures=[])

    def broken(*args, **kwargs):
        raise KeyError("sindy")

    monkeypatch.setattr(discovery_figures, "comparison_bars", broken)
    write_discover_outputs(result, tmp_path / "figure")
    rec = json.loads((tmp_path / "figure" / "discovery.json").read_text())
    assert [(f["effect"], f["component"]) for f in rec["findings"]] == [("backlash", "band")]
    assert rec["failures"] == ["figure comparison.png: KeyError: 'sindy'"]
    page = (tmp_path / "figure" / "discovery.md").read_text()
    assert "## What failed" in page and "comparison.png" in page
    assert "| 1 | backlash | band |" in page  # the rest of the page is intact
    assert not (tmp_path / "figure" / "figures" / "comparison.png").exists()
    assert (tmp_path / "figure" / "figures" / "structure_test.png").stat().st_size > 10_000

    monkeypatch.setattr(discovery_report, "markdown_summary", broken)
    result = dataclasses.replace(result, failures=[])
    write_discover_outputs(result, tmp_path / "page")
    page = (tmp_path / "page" / "discovery.md").read_text()
    assert "backlash / band" in page and "discovery.md: KeyError" in page
    assert json.loads((tmp_path / "page" / "discovery.json").read_text())["findings"]


def test_a_failing_evidence_method_is_recorded_not_raised(play, monkeypatch):
    from mbst.discovery.evidence import collect, neural, sindy

    def broken(*args, **kwargs):
        raise FloatingPointError("planted")

    monkeypatch.setattr(neural.NeuralResidual, "fit", broken)
    monkeypatch.setattr(sindy, "residual_regression", broken)
    _, _, result = play
    library = result.base.model.candidate_library
    model, ev = collect.neural_evidence(result.residual_tests, DiscoverSettings(), library)
    assert model is None and ev["error"] == "FloatingPointError: planted"
    assert collect.sparse_evidence(result.residual_tests, library)["error"] == \
        "FloatingPointError: planted"


def _planted_failure(calls: list[int], at: int, real):
    """``real`` that raises a planted error on its ``at``-th call (counted in ``calls``)."""
    def broken(*args, **kwargs):
        calls.append(1)
        if len(calls) == at:
            raise FloatingPointError("planted")
        return real(*args, **kwargs)
    return broken


def test_a_structure_round_that_fails_is_undone_and_said(play, tmp_path, monkeypatch):
    """#30, no answer lost: a round that raises after its extension changed the model (here
    in its ranking bootstrap) is undone — the model back at the base, no finding — and the
    page says that a round failed, not that the base model is at the noise floor."""
    camp, _, _ = play
    calls: list[int] = []
    monkeypatch.setattr(acceptance, "ranking_bootstrap",
                        _planted_failure(calls, 1, acceptance.ranking_bootstrap))
    result = discover(camp, DiscoverSettings(max_effects=1, neural=False, sparse=False))
    assert calls, "the planted failure was never reached"
    # the play stays in the residual: the later rounds describe it, at no more than even
    # odds, as what a catalogue search that did not run through may have named
    assert [f.effect for f in result.findings] == ["unexplained"]
    assert result.findings[0].confidence <= acceptance.EVEN_ODDS
    assert result.findings[0].evidence.startswith("CATALOGUE NOT SEARCHED THROUGH")
    np.testing.assert_array_equal(result.extended_params, result.base.params)
    assert result.failures[0].startswith("structure round 1: FloatingPointError: planted")
    assert result.rounds[0]["failed"] == "FloatingPointError: planted"
    write_discover_outputs(result, tmp_path / "out")
    page = (tmp_path / "out" / "discovery.md").read_text()
    assert "## What failed" in page and "structure round 1: FloatingPointError" in page
    rec = json.loads((tmp_path / "out" / "discovery.json").read_text())
    assert rec["failures"] == result.failures
    assert len(rec["findings"]) == len(result.findings)
    # with no finding at all the page says a round failed, not that the base model is at
    # the noise floor
    empty = dataclasses.replace(result, findings=[])
    write_discover_outputs(empty, tmp_path / "empty")
    page = (tmp_path / "empty" / "discovery.md").read_text()
    assert "No finding: a structure round failed" in page
    assert "down to the noise floor" not in page


def test_a_later_round_that_fails_keeps_the_findings_before_it(play, tmp_path, monkeypatch):
    """#30: a failure in a later structure round or in another of the family's rounds costs
    that round only: the play the first round named stands, with its extended model."""
    camp, _, named = play
    calls: list[int] = []
    import mbst.discovery.rounds.catalogue as catalogue_mod

    # the second round's screen fails; the first round's proposal stands
    monkeypatch.setattr(catalogue_mod, "_screen",
                        _planted_failure(calls, 2, catalogue_mod._screen))

    def broken(state):
        raise KeyError("planted")

    monkeypatch.setitem(pipeline_mod.ROUNDS, "resolution", broken)
    result = discover(camp, DiscoverSettings(max_effects=2, neural=False))
    assert len(calls) == 2, "the second round's screen was never reached"
    assert [(f.effect, f.component) for f in result.findings] == [("backlash", "band")]
    np.testing.assert_allclose(result.extended_params, named.extended_params, rtol=1e-9)
    assert [f.split(";")[0] for f in result.failures] == [
        "structure round 2: FloatingPointError: planted", "resolution round: KeyError: 'planted'"]
    assert result.rounds[1]["round"] == 2 and result.rounds[1]["accepted"] is None
    assert result.resolution == []


class _TableScorer:
    """A stage whose per-sample costs are given: row 0 the base, row i candidate i."""

    def __init__(self, table: np.ndarray, noise_cost: float):
        self.table, self._noise_cost = table, noise_cost

    def noise_cost(self) -> float:
        return self._noise_cost

    def base_refit(self):
        return np.array([0.0]), float(self.table[0].sum())

    def sample_costs(self, ps):
        return self.table[[int(p[0]) for p in ps]]


def _candidate(i: int, key: str, table: np.ndarray, n_eff: float) -> CandidateScore:
    return CandidateScore(key=key, effect=key.split(":")[0], component=key.split(":")[1],
                          stage="free_tie_rods", tests=[], free=[], k_effect=1,
                          cost_base=float(table[0].sum()), cost=float(table[i].sum()),
                          n_eff=n_eff, aic_delta=-500.0, params=np.array([float(i)]))


def test_bootstrap_confidence_drops_when_one_stretch_carries_the_winner():
    """Issue #30: a winner whose gain comes from one short stretch of the data (a few
    reversals a wrong effect happens to fit) is not named with confidence 1; one whose
    gain is spread over the whole stage is."""
    rng = np.random.default_rng(0)
    n = 4000
    base = 1.0 + 0.1 * rng.standard_normal(n) ** 2
    base[:120] = 40.0  # one stretch of large misfit (a few reversals): half the cost
    spread = base * 0.7  # removes 30 % everywhere
    lumped = base.copy()
    lumped[:120] *= 0.4  # removes 60 % of that stretch only: 33 % in total
    table = np.stack([base, lumped, spread])
    cands = [_candidate(1, "backlash:worm_gear", table, 400.0),
             _candidate(2, "stribeck_friction:rack", table, 400.0)]
    assert cands[0].relative_gain > cands[1].relative_gain  # the lumped one wins on the sum
    at_noise = _TableScorer(table, float(spread.sum()))  # what spread leaves is noise
    weak = acceptance.ranking_bootstrap(at_noise, cands[0], cands, 0.1)
    assert weak["wins_share"] < 0.7 and weak["confidence"] < 0.7, weak
    # the rival the resamples often prefer is named beside the winner
    assert [a["key"] for a in weak["alternatives"]] == ["stribeck_friction:rack"], weak
    assert weak["alternatives"][0]["winner_better_share"] == pytest.approx(weak["wins_share"])
    strong = acceptance.ranking_bootstrap(at_noise, cands[1], cands[1:], 0.1)
    assert strong["confidence"] == 1.0, strong
    assert strong["alternatives"] == []
    # determinism: the same seed gives the same answer
    assert acceptance.ranking_bootstrap(at_noise, cands[0], cands, 0.1) == weak
    # the same winner where the noise floor lies far below: it explains 30 % of the
    # structure left, and the confidence says so
    partly = acceptance.ranking_bootstrap(_TableScorer(table, 0.0), cands[1], cands[1:], 0.1)
    assert partly["wins_share"] == 1.0
    assert partly["confidence"] == pytest.approx(0.3, abs=1e-6)


def test_significance_margin_holds_its_false_alarm_rate():
    """Issue #30: the significance margin comes from the campaign's effective samples,
    not from a constant fitted to the demo. On pure noise, 25 candidates of one
    parameter each (random regressors, as a catalogue's effects are to a residual they
    do not explain) clear it in about ``FALSE_ALARM_RATE`` of campaigns; one real effect
    of 5 % of the cost on 500 samples clears it nearly always."""
    rng = np.random.default_rng(3)
    n, m, trials = 500, 25, 2000
    drop = acceptance.aic_drop_needed(1, m)
    assert drop == pytest.approx(chi2.isf(acceptance.FALSE_ALARM_RATE / m, 1) - 2.0)
    assert acceptance.aic_drop_needed(1, m, min_aic_drop=30.0) == 30.0
    assert acceptance.aic_drop_needed(2, m) > drop  # more parameters, more evidence needed

    def best_aic_delta(effect: float) -> float:
        e = rng.standard_normal(n)
        x = rng.standard_normal((m, n))
        e = e + effect * x[0]
        proj = (x @ e) / np.einsum("ij,ij->i", x, x)
        cost = np.sum((e - proj[:, None] * x) ** 2, axis=1)
        return float(np.min(n * np.log(cost / np.sum(e * e)) + 2.0))

    false_alarms = np.mean([best_aic_delta(0.0) <= -drop for _ in range(trials)])
    assert false_alarms <= 2 * acceptance.FALSE_ALARM_RATE, false_alarms
    found = np.mean([best_aic_delta(0.23) <= -drop for _ in range(200)])  # ≈ 5 % gain
    assert found >= 0.9, found


def test_parts_the_stage_cannot_tell_apart_lead_by_their_share_of_the_body_friction():
    """Realistic rigs 955 and 921: a rack asymmetry removed 78.38 % of the stage in the
    motor and in the rack alike, and the catalogue's order named the motor first. Motor
    and rack turn as one body through the mesh; the part that carries most of the body's
    sliding friction (referred at equal power: the rack's 270 N against the motor's
    0.03 N·m × 2200 rad/m = 66 N) leads. A clear winner, or a twin whose size the range cut
    short, keeps its place."""
    from types import SimpleNamespace

    import mbst.discovery.rounds.catalogue as catalogue_mod
    from mbst.discovery.data import TestResidual
    from mbst.systems.eps.params import PARAM_SPECS

    t = np.linspace(0.0, 4.0, 400)
    rack_speed = 0.02 * np.cos(t)  # m/s; the motor turns N / r = 2200 rad per m of rack
    res = TestResidual(id="s2", scenario="free_tie_rods", role="identification",
                       motor="passive", dt_s=0.01, time_s=t, angle_rad=np.sin(t),
                       omega_rad_per_s=np.cos(t), measured={}, simulated={},
                       states={"rack_speed_m_per_s": rack_speed,
                               "motor_speed_rad_per_s": 2200.0 * rack_speed})
    p = np.array([s.default for s in PARAM_SPECS])
    idx = EPS_MODEL.param_index

    def cand(component, gain, ratio=0.8):
        key = f"asymmetric_friction:{component}"
        q = p.copy()
        q[idx[f"{component}.asymmetric_friction.ratio"]] = ratio
        return CandidateScore(key=key, effect="asymmetric_friction", component=component,
                              stage="free_tie_rods", tests=["s2"], free=[], k_effect=1,
                              cost_base=1.0, cost=1.0 - gain, n_eff=500.0,
                              aic_delta=-500.0 * gain, params=q)

    state = SimpleNamespace(model=EPS_MODEL, residuals=[res], p=p)
    motor, rack = cand("motor", 0.7838), cand("rack", 0.7838)
    other = cand("steering_column", 0.5)
    assert [s.component for s in catalogue_mod._body_share_first(state, [motor, rack, other])
            ] == ["rack", "motor", "steering_column"]
    # a motor that clearly fits better keeps its lead; so does one whose rack twin's size
    # ended on the end of its range (its cost only a bound)
    clear = cand("motor", 0.80)
    assert catalogue_mod._body_share_first(state, [clear, rack])[0] is clear
    bound = cand("rack", 0.7838, ratio=0.25)
    assert catalogue_mod._body_share_first(state, [motor, bound])[0] is motor


def test_a_winner_a_sensor_lag_matches_is_not_named(monkeypatch):
    """eps-model.md: a torque sensor's own filter lags by a few ms, and no catalogue effect
    describes it. A clean realistic rig with white noise and a 3 ms torque lag (seed 958)
    had a column Stribeck rise of 2.7 named at 0.66: 24.3 % of the blocked-column stage,
    where the lag refitted with the stage removes 27.2 %. A winner the lag of a sensor its
    stage measures matches is not named, and the round goes on with the other stages; a
    lag that does not match is a rival for the ranking bootstrap; a winner short of the
    margins costs no lag refit."""
    from types import SimpleNamespace

    import mbst.discovery.rounds.catalogue as catalogue_mod
    from mbst.discovery import rivals as rivals_mod

    def cand(key, stage, gain):
        return CandidateScore(key=key, effect=key.split(":")[0], component=key.split(":")[1],
                              stage=stage, tests=["t"], free=[], k_effect=1, cost_base=1.0,
                              cost=1.0 - gain, n_eff=500.0, aic_delta=-500.0 * gain,
                              params=np.zeros(1), headline={"lag_s": 0.0036})

    column = cand("stribeck_friction:steering_column", "blocked_column", 0.243)
    dahl = cand("presliding_hysteresis:rack", "free_tie_rods", 0.116)
    asym = cand("asymmetric_friction:rack", "free_tie_rods", 0.05)
    lag_gain = {"blocked_column": 0.272, "free_tie_rods": 0.10}
    refitted = []

    def rivals(scorer, model, n_eff, stated=None, winner_share=0.0, screened=None):
        refitted.append(scorer)
        screened["friction_drift:campaign"] = 0.01  # one step put it under the winner's half
        return [cand("sensor_lag:steering_torque_nm", scorer, lag_gain[scorer])]

    # nested with the lag, the winner removes this share of what the lag leaves
    beyond_gain = {"blocked_column": 0.02, "free_tie_rods": 0.02}

    def beyond(scorer, model, best, rival, stated=None):
        left = rival.cost * (1.0 - beyond_gain[scorer])
        return dataclasses.replace(best, cost_base=rival.cost, cost=left,
                       aic_delta=500.0 * math.log(left / rival.cost) + 2.0)

    # with the lag carried through the whole cascade, the winner removes this share
    through_gain = {"blocked_column": 0.30, "free_tie_rods": 0.30}

    def through(state, best, rival, row):
        row.update(stands=through_gain[best.stage] > 0.1,
                   through_cascade={"relative_gain": through_gain[best.stage]})
        row["reason"] += f", and with the lag carried through the cascade {through_gain}"

    monkeypatch.setattr(rivals_mod, "rivals", rivals)
    monkeypatch.setattr(rivals_mod, "beyond", beyond)
    monkeypatch.setattr(catalogue_mod, "_beyond_the_lag_through_the_cascade", through)
    monkeypatch.setattr(catalogue_mod, "aic_drop", lambda state, k: 10.0)
    state = SimpleNamespace(settings=DiscoverSettings(), model=EPS_MODEL,
                            campaign=SimpleNamespace(known={}, priors={}), failures=[])
    scorers = {"blocked_column": "blocked_column", "free_tie_rods": "free_tie_rods"}
    rec = {"round": 1}
    left, lags = catalogue_mod._past_rivals(state, scorers, [column, dahl, asym], rec)
    assert left == [dahl, asym] and [s.relative_gain for s in lags] == [pytest.approx(0.10)]
    gone = rec["rival_declined"]
    assert [g["key"] for g in gone] == [column.key]
    assert "3.6 ms lag of the steering_torque_nm sensor alone 27.2 %" in gone[0]["reason"]
    assert len(rec["rivals"]) == 2
    assert rec["rivals_screened"] == [
        {"key": "friction_drift:campaign", "stage": stage, "predicted_gain": 0.01,
         "winner": winner.key} for stage, winner in (("blocked_column", column),
                                                     ("free_tie_rods", dahl))]
    # a lag that matches every stage's winner leaves nothing to name
    lag_gain["free_tie_rods"] = 0.225
    left, lags = catalogue_mod._past_rivals(state, scorers, [column, dahl, asym], {
        "round": 1})
    assert left == [] and lags == []
    # a winner short of the margins is left to them, with no lag refitted
    refitted.clear()
    weak = cand("asymmetric_friction:rack", "free_tie_rods", 0.05)
    assert catalogue_mod._past_rivals(state, scorers, [weak], {"round": 1}) == ([weak], [])
    assert refitted == []
    # a winner that still removes the margin of what the lag leaves stands beside it: the
    # lag is its rival in the ranking bootstrap, not its match (``rivals.beyond``)
    beyond_gain["blocked_column"] = 0.30
    rec = {"round": 1}
    left, lags = catalogue_mod._past_rivals(state, scorers, [column, dahl, asym], rec)
    assert left[0] is column and [s.key for s in lags] == ["sensor_lag:steering_torque_nm"]
    assert "rival_declined" not in rec
    assert rec["rival_beyond"][0]["stands"] and "30.0 % of what the latter leaves" in \
        rec["rival_beyond"][0]["reason"]
    # ... unless the lag, carried through the cascade, takes what it stood beyond: a lag
    # biases the stages upstream too (the power law of the compact lag case, 2026-11-30)
    through_gain["blocked_column"] = 0.02
    rec3 = {"round": 3}
    left, _ = catalogue_mod._past_rivals(state, scorers, [column, dahl, asym], rec3)
    assert column not in left and rec3["rival_declined"][0]["key"] == column.key
    assert not rec3["rival_beyond"][0]["stands"]
    assert "through the cascade" in rec3["rival_beyond"][0]["reason"]
    assert "beside the lag carried through the whole cascade it removes 2.0 %" in \
        rec3["rival_declined"][0]["reason"]
    through_gain["blocked_column"] = 0.30
    # a refit beside the rival that fails leaves the match (declined), and says so
    monkeypatch.setattr(rivals_mod, "beyond", lambda *a, **k: 1 / 0)
    rec2 = {"round": 2}
    left, _ = catalogue_mod._past_rivals(state, scorers, [column, dahl, asym], rec2)
    assert [g["key"] for g in rec2["rival_declined"]][0] == column.key
    assert "ZeroDivisionError" in state.failures[-1]
    # ... and its finding says so beside "not ruled out"
    said = catalogue_mod._beyond_text(SimpleNamespace(rounds=[rec]), column.key)
    assert said.startswith("; BEYOND A RIVAL THAT MATCHED IT: stribeck_friction:steering_colu")
    assert catalogue_mod._beyond_text(SimpleNamespace(rounds=[rec]), dahl.key) == ""


def test_a_winner_that_loses_its_held_out_tests_leaves_the_next_one_tried(monkeypatch):
    """Realistic rig 2013 (a planted 0.2° worm-gear backlash, compact plan): a rack
    presliding took 22.3 % of the free tie-rods and won 1 of 3 leave-one-test-out folds;
    the round stopped there, and the backlash behind it (18.1 %, ΔAIC −96) was never
    tried. The next candidate that clears the margins, and that no rival outside the
    catalogue matches, is cross-validated in turn; one short of the margins never is, and
    the name's evidence says what lost ahead of it."""
    from types import SimpleNamespace

    import mbst.discovery.rounds.catalogue as catalogue_mod
    from mbst.discovery import acceptance

    def cand(key, gain, aic):
        return CandidateScore(key=key, effect=key.split(":")[0], component=key.split(":")[1],
                              stage="free_tie_rods", tests=["t"], free=[], k_effect=1,
                              cost_base=1.0, cost=1.0 - gain, n_eff=500.0, aic_delta=aic,
                              params=np.zeros(1))

    dahl = cand("presliding_hysteresis:rack", 0.223, -57.9)
    gap = cand("backlash:worm_gear", 0.181, -96.5)
    small = cand("asymmetric_friction:motor", 0.033, -14.6)
    wins = {dahl.key: 1, gap.key: 3, small.key: 3}
    tried = []

    def cross_validate(scorer, c, p, nfev):
        tried.append(c.key)
        return {"folds": 3, "wins": wins[c.key], "held_out_gain": 0.1}

    monkeypatch.setattr(acceptance, "cross_validate", cross_validate)
    monkeypatch.setattr(catalogue_mod, "aic_drop", lambda state, k: 10.4)
    state = SimpleNamespace(settings=DiscoverSettings(), p=np.zeros(1), rounds=[])
    scorers = {"free_tie_rods": "free_tie_rods"}
    rec = {"round": 1}
    scores, cv, lags = catalogue_mod._cross_validated(state, scorers, [dahl, gap, small],
                                                      [], rec)
    assert scores == [gap, dahl, small] and cv["wins"] == 3 and lags == []
    assert tried == [dahl.key, gap.key]
    assert rec["cross_validation_lost"] == [{"key": dahl.key, "relative_gain": pytest.approx(0.223),
                                             "wins": 1, "folds": 3, "held_out_gain": 0.1,
                                             "per_fold": []}]
    state.rounds = [rec | {"accepted": gap.key}]
    assert "AHEAD OF IT, NOT HELD OUT: presliding_hysteresis:rack removed 22.3 % but won " \
        "1/3" in catalogue_mod._lost_text(state, gap.key)
    # a rival in the stage that removes as much as the next one, and that it does not
    # stand beyond, keeps it from being tried
    from mbst.discovery import rivals as rivals_mod

    lag = cand("sensor_lag:steering_torque_nm", 0.20, -80.0)
    monkeypatch.setattr(rivals_mod, "beyond", lambda scorer, model, best, rival, stated=None:
                        dataclasses.replace(best, cost_base=rival.cost, cost=rival.cost,
                                            aic_delta=2.0))
    state.campaign, state.model, state.failures = \
        SimpleNamespace(known={}, priors={}), EPS_MODEL, []
    tried.clear()
    rec = {"round": 1}
    assert catalogue_mod._cross_validated(state, scorers, [dahl, gap, small], [lag],
                                          rec) is None
    assert tried == [dahl.key] and not rec["rival_beyond"][0]["stands"]
    # all that clear the margins lose: nothing named, the round says why
    wins[gap.key] = 0
    tried.clear()
    rec = {"round": 1}
    assert catalogue_mod._cross_validated(state, scorers, [dahl, gap, small], [], rec) is None
    assert tried == [dahl.key, gap.key] and "backlash:worm_gear lost" in rec["reason"]
    # a best short of the margins: no fold is run
    tried.clear()
    rec = {"round": 1}
    assert catalogue_mod._cross_validated(state, scorers, [small], [], rec) is None
    assert tried == [] and "is at the noise floor" in rec["reason"]


def test_a_winner_of_most_folds_whose_held_out_cost_rises_does_not_hold_out(monkeypatch):
    """Realistic rig 2512 (motor presliding and rack Stribeck planted, compact plan):
    round 2 named a rack asymmetry of 1.004 at 0.38 for 57 % of the blocked column. It
    won 2 of 3 folds, yet the held-out cost of the three rose 222 % (its ramp fold 4.5
    times the base's). Winning most folds is not enough: the pooled held-out cost must
    fall too, else the next candidate is tried and the round says why."""
    from types import SimpleNamespace

    import mbst.discovery.rounds.catalogue as catalogue_mod
    from mbst.discovery import acceptance

    def cand(key, gain):
        return CandidateScore(key=key, effect=key.split(":")[0], component=key.split(":")[1],
                              stage="blocked_column", tests=["t"], free=[], k_effect=1,
                              cost_base=1.0, cost=1.0 - gain, n_eff=500.0, aic_delta=-200.0,
                              params=np.zeros(1))

    lopsided = cand("asymmetric_friction:rack", 0.57)
    next_one = cand("presliding_hysteresis:motor", 0.40)
    folds = {lopsided.key: (2, -2.225), next_one.key: (2, 0.31)}

    def cross_validate(scorer, c, p, nfev):
        wins, gain = folds[c.key]
        return {"folds": 3, "wins": wins, "held_out_gain": gain}

    monkeypatch.setattr(acceptance, "cross_validate", cross_validate)
    monkeypatch.setattr(catalogue_mod, "aic_drop", lambda state, k: 10.4)
    state = SimpleNamespace(settings=DiscoverSettings(), p=np.zeros(1), rounds=[])
    rec = {"round": 2}
    scores, cv, _ = catalogue_mod._cross_validated(
        state, {"blocked_column": "blocked_column"}, [lopsided, next_one], [], rec)
    assert scores[0] is next_one and cv["held_out_gain"] == 0.31
    state.rounds = [rec | {"accepted": next_one.key}]
    assert "asymmetric_friction:rack removed 57.0 % but won 2/3 leave-one-test-out folds, " \
        "the held-out cost of all of them +222 %" in catalogue_mod._lost_text(state,
                                                                             next_one.key)
    # the same with nothing behind it: nothing named, and the round says why
    rec = {"round": 2}
    assert catalogue_mod._cross_validated(
        state, {"blocked_column": "blocked_column"}, [lopsided], [], rec) is None
    assert "(won 2/3 leave-one-test-out folds, the held-out cost of all of them +222 %)" \
        in rec["reason"]
    assert [g["key"] for g in rec["cross_validation_lost"]] == [lopsided.key]  # the figure's
    # a count of folds with a held-out cost that falls holds, as do stages with no fold
    assert acceptance.holds_out({"folds": 3, "wins": 2, "held_out_gain": 0.05})
    assert not acceptance.holds_out({"folds": 3, "wins": 1, "held_out_gain": 0.5})
    assert acceptance.holds_out({"folds": 0, "wins": 0, "held_out_gain": None})


def test_the_structure_figure_says_which_candidate_lost_its_held_out_tests(
        monkeypatch, tmp_path):
    """Rig 2013's round 1 drew the rack presliding above the accepted backlash with nothing
    to say why it was passed over: its label now says it lost its held-out tests."""
    from discovery_cases import ROW, structure_axes

    rounds = [{"round": 1, "accepted": "backlash:worm_gear", "candidates": [
        {**ROW, "key": "presliding_hysteresis:rack", "relative_gain": 0.223},
        {**ROW, "key": "backlash:worm_gear", "relative_gain": 0.181}],
        "cross_validation_lost": [{"key": "presliding_hysteresis:rack",
                                   "relative_gain": 0.223, "wins": 1, "folds": 3}]}]
    labels = [t.get_text().replace("\n", " ")  # top to bottom, wrapped at 60 characters
              for t in structure_axes(monkeypatch, rounds, tmp_path / "s.png"
                                      ).get_yticklabels()]
    assert labels == ["presliding_hysteresis:rack (free_tie_rods) — won 1/3 held-out tests",
                      "backlash:worm_gear (free_tie_rods)"], labels
    # one that won most folds while the held-out cost of all of them rose says so
    rounds[0]["cross_validation_lost"] = [{"key": "presliding_hysteresis:rack",
                                           "relative_gain": 0.223, "wins": 2, "folds": 3,
                                           "held_out_gain": -2.225}]
    labels = [t.get_text().replace("\n", " ")
              for t in structure_axes(monkeypatch, rounds, tmp_path / "t.png"
                                      ).get_yticklabels()]
    assert labels[0] == ("presliding_hysteresis:rack (free_tie_rods) — won 2/3 held-out "
                         "tests, all of them +222 % in cost"), labels


def test_a_stage_whose_winner_a_rival_matched_is_not_called_at_the_noise_floor():
    """Realistic powered rig r5 (stop 71, a motor Dahl term planted): the stated values
    matched free tie-rods' winner (13.5 % against 12.3 %), and the round then stopped on the
    tyres' best, 1.7 %, saying "the residual is at the noise floor of the catalogue", two
    lines under the stage it had just declined. The claim now leaves that stage out, and
    the summary says what was matched instead of "down to the noise floor"."""
    from types import SimpleNamespace

    weak = CandidateScore(key="asymmetric_friction:tires", effect="asymmetric_friction",
                          component="tires", stage="tires_on_ground", tests=["t"], free=[],
                          k_effect=1, cost_base=1.0, cost=0.983, n_eff=300.0, aic_delta=-2.0,
                          params=np.zeros(1))
    plain = acceptance.margin_shortfall(weak, 0.1, 10.0)
    assert plain.endswith(": the residual is at the noise floor of the catalogue")
    said = acceptance.margin_shortfall(weak, 0.1, 10.0, ("free_tie_rods",))
    assert said.startswith("best candidate asymmetric_friction:tires removes 1.7 %")
    assert "the residual of the other stages than free_tie_rods (whose winner a reality " \
        "outside the catalogue matched) is at the noise floor" in said
    from mbst.report.discovery import markdown_summary

    result = SimpleNamespace(
        campaign="r5", wall_s=1.0, findings=[], resolution=[], benchmark=None, signatures=[],
        failures=[], gain={}, comparison=pd.DataFrame({"test": ["c"], "channel": ["steering_torque_nm"],
                                              "model": ["base"], "fit_percent": [98.8]}),
        rounds=[{"round": 1, "reason": said, "rival_declined": [
            {"key": "presliding_hysteresis:rack", "stage": "free_tie_rods",
             "reason": "the stated values alone 13.5 %"}]}])
    text = pipeline_mod.DiscoveryResult.summary(result)
    assert "presliding_hysteresis:rack matched as well by a reality outside" in text
    page = markdown_summary(result)
    assert "No finding: no catalogue effect is named" in page
    assert "down to the noise floor" not in text + page
    result.rounds[0].pop("rival_declined")
    assert "down to the noise floor" in pipeline_mod.DiscoveryResult.summary(result)
    assert "down to the noise floor" in markdown_summary(result)


def test_look_alikes_are_refitted_from_each_others_stage_fit(monkeypatch):
    """A look-alike that fits some test of the stage better than the round's winner is
    refitted from the winner's stage fit, and the winner from its; a candidate the winner
    beats on every test, or one of another stage, is not. Realistic rig 200: a worm-gear
    backlash refitted from its own starts stalled at 42.5 % beside a motor Dahl term at
    45.1 %, from the Dahl term's stage fit it reached 50.3 % and was named."""
    from types import SimpleNamespace

    import mbst.discovery.rounds.catalogue as catalogue_mod

    def cand(key, stage, gain, per_test):
        return CandidateScore(key=key, effect=key.split(":")[0], component=key.split(":")[1],
                              stage=stage, tests=list(per_test), free=[], k_effect=1,
                              cost_base=1.0, cost=1.0 - gain, n_eff=500.0,
                              aic_delta=-500.0 * gain, params=np.zeros(1),
                              per_test_cost=per_test)

    dahl = cand("presliding_hysteresis:motor", "free_tie_rods", 0.451, {"a": 0.2, "b": 0.3})
    gap = cand("backlash:worm_gear", "free_tie_rods", 0.425, {"a": 0.1, "b": 0.475})
    # the same effect in a part one body with the motor: a contender though beaten on every
    # test (its refit may have ended in another basin); another effect so beaten is not
    twin = cand("presliding_hysteresis:rack", "free_tie_rods", 0.406, {"a": 0.25, "b": 0.34})
    beaten = cand("asymmetric_friction:rack", "free_tie_rods", 0.40, {"a": 0.25, "b": 0.34})
    # the same effect in a part with a motion of its own, beaten on every test, is not
    # (the demo's rack-pinion backlash beside the worm gear's)
    apart = cand("presliding_hysteresis:steering_column", "free_tie_rods", 0.40,
                 {"a": 0.25, "b": 0.34})
    other = cand("backlash:rack_pinion", "tires_on_ground", 0.40, {"c": 0.1})
    calls = []

    def reseeded(spec, c, rival):
        calls.append((c.key, rival.key))
        if c.key == gap.key:  # the basin the Dahl term's fit found suits the gap too
            return dataclasses.replace(c, cost=1.0 - 0.503, seeded_from=rival.key)
        return c

    state = SimpleNamespace(settings=DiscoverSettings(), model=EPS_MODEL, residuals=[])
    monkeypatch.setattr(catalogue_mod, "aic_drop", lambda state, k: 10.0)
    monkeypatch.setattr(catalogue_mod.acceptance, "moves_with",
                        lambda best, comp, res, model: {best.component, comp} ==
                        {"motor", "rack"})
    out = catalogue_mod._cross_seeded(state, SimpleNamespace(reseeded=reseeded),
                                      [dahl, gap, twin, beaten, apart, other])
    assert sorted(calls) == sorted([(gap.key, dahl.key), (dahl.key, gap.key),
                                    (twin.key, dahl.key), (dahl.key, twin.key)])
    assert [c.key for c in out] == [gap.key, dahl.key, twin.key, beaten.key, apart.key,
                                    other.key]
    assert out[0].seeded_from == dahl.key and out[0].relative_gain == pytest.approx(0.503)


def test_a_reseeded_refit_starts_from_the_rivals_stage_fit_with_its_effect_off(monkeypatch):
    """The start of ``StageScorer.reseeded``: the rival's stage parameters, the rival's
    effect at its neutral end, the candidate's effect at its own fitted size."""
    from types import SimpleNamespace

    from mbst.discovery.structure import StageScorer

    base = np.array(EPS_MODEL.default_vector(), float)
    idx = EPS_MODEL.param_index
    gap, dahl = EPS_MODEL.effects["backlash:worm_gear"], \
        EPS_MODEL.effects["presliding_hysteresis:motor"]
    rival_p, cand_p = base.copy(), base.copy()
    rival_p[idx["rack.coulomb_n"]] *= 1.4  # what the rival's refit moved
    rival_p[idx[dahl.free[0]]] = 1.2
    cand_p[idx[gap.free[0]]] = 0.009

    def score(spec, n_eff, start):
        seen.append(start.params)
        return dataclasses.replace(start, cost=0.4)

    seen: list[np.ndarray] = []
    fake = SimpleNamespace(model=EPS_MODEL, base=base, upper={}, score=score)
    fake.neutral_start = lambda p, spec: StageScorer.neutral_start(fake, p, spec)
    fake._bounds = lambda bounds: StageScorer._bounds(fake, bounds)
    common = dict(effect="", component="", stage="free_tie_rods", tests=[], free=[],
                  k_effect=1, cost_base=1.0, n_eff=1.0, aic_delta=0.0)
    cand = CandidateScore(key=gap.key, cost=0.6, params=cand_p, **common)
    rival = CandidateScore(key=dahl.key, cost=0.55, params=rival_p, **common)
    out = StageScorer.reseeded(fake, gap, cand, rival)
    start = seen[0]
    assert start[idx["rack.coulomb_n"]] == rival_p[idx["rack.coulomb_n"]]
    assert start[idx[gap.free[0]]] == 0.009
    assert start[idx[dahl.free[0]]] == StageScorer.neutral_start(fake, base, dahl)[
        idx[dahl.free[0]]]
    assert out.cost == 0.4 and out.seeded_from == dahl.key
    # a refit that ends worse keeps the candidate as it was
    fake.score = lambda spec, n_eff, start: dataclasses.replace(start, cost=0.7)
    assert StageScorer.reseeded(fake, gap, cand, rival) is cand
    # the same effect in another part starts at the rival's dimensionless size (a rack
    # asymmetry that ended on its bound, refitted from the motor's), a dimensional one
    # (a Stribeck velocity in m/s against rad/s) at its own
    fake.score = score
    for effect, name, own, theirs, expected in (
            ("asymmetric_friction", "ratio", 4.0, 1.26, 1.26),
            ("stribeck_friction", "stribeck_velocity", 0.002, 0.5, 0.002)):
        mine, other = EPS_MODEL.effects[f"{effect}:rack"], EPS_MODEL.effects[f"{effect}:motor"]
        cand_p, rival_p = base.copy(), base.copy()
        cand_p[idx[mine.headline[name]]] = own
        rival_p[idx[other.headline[name]]] = theirs
        seen.clear()
        StageScorer.reseeded(fake, mine, dataclasses.replace(cand, key=mine.key, params=cand_p),
                             dataclasses.replace(rival, key=other.key, params=rival_p))
        assert seen[0][idx[mine.headline[name]]] == expected, effect


def test_comparison_bars_draw_a_slot_per_measured_channel_only(monkeypatch, tmp_path):
    """A control test without a channel (free tie rods: no tie-rod force) has no slot in
    the FIT bars, and a family missing on a channel leaves its bar out, not the figure."""
    from types import SimpleNamespace

    from mbst.report import discovery_figures

    rows = [("free", "steering_torque_nm", "base", 86.0), ("free", "steering_torque_nm",
                                                            "extended", 98.0),
            ("loaded", "steering_torque_nm", "base", 99.0),
            ("loaded", "steering_torque_nm", "extended", 99.5),
            ("loaded", "tie_rod_force_left_n", "base", 99.1),
            ("loaded", "tie_rod_force_left_n", "extended", 99.6),
            ("loaded", "tie_rod_force_left_n", "sindy", 63.0)]
    result = SimpleNamespace(comparison=pd.DataFrame(
        rows, columns=["test", "channel", "model", "fit_percent"]))
    drawn = []
    monkeypatch.setattr(discovery_figures.plots, "save_figure",
                        lambda fig, path: drawn.append(fig))
    discovery_figures.comparison_bars(result, tmp_path / "comparison.png")
    ticks = [t.get_text() for t in drawn[0].axes[0].get_xticklabels()]
    assert ticks == ["free\nsteering_torque_nm", "loaded\nsteering_torque_nm",
                     "loaded\ntie_rod_force_left_n"]
    legend = [t.get_text() for t in drawn[0].axes[0].get_legend().get_texts()]
    assert legend == ["base", "extended", "sindy"]
    # the family's blank slots say so (sindy on the two torque slots), the others' do not
    marks = [t for t in drawn[0].axes[0].texts if t.get_text() == "no FIT"]
    assert len(marks) == 2


def test_the_report_names_refits_that_stopped_at_their_work_budget():
    """A candidate refitted short (its step far finer than the base model's) is named, so a
    reader knows which scores are a best point rather than a converged refit."""
    from mbst.report.discovery import untested_lines

    rounds = [{"round": 2, "candidates": [
        {"key": "stribeck_friction:rack", "fell_back": False, "work_spent": True},
        {"key": "stribeck_friction:motor", "fell_back": False, "work_spent": False}]}]
    text = " ".join(untested_lines(rounds))
    assert "1 stopped at their work budget" in text and "stribeck_friction:rack (round 2)" in text
    assert "stribeck_friction:motor" not in text
    rounds[0]["candidates"][0]["work_spent"] = False
    assert "work budget" not in " ".join(untested_lines(rounds))


@pytest.mark.parametrize("spent", [True, False])
def test_a_refined_refit_takes_no_further_step_once_its_work_is_spent(monkeypatch, spent):
    """A refined candidate continues in steps while a step gains (``_refit``); a step that
    stopped at its work budget ends it, or each further step would spend another budget
    at a step far finer than the base's (realistic rig 932)."""
    from types import SimpleNamespace

    import mbst.discovery.structure as structure_mod

    calls = []

    def fake_solve(prob, starts, max_nfev, interior):
        calls.append(max_nfev)
        # each step gains 10 %, stopped on its evaluation budget (status 0)
        return SimpleNamespace(p=np.zeros(1), cost=0.9 ** len(calls), status=0,
                               work_spent=spent)

    monkeypatch.setattr(structure_mod, "solve", fake_solve)
    scorer = SimpleNamespace(stage_free=[], problem=lambda free, base, bounds=None: None,
                             neutral_start=lambda p, spec: p)
    spec = SimpleNamespace(free=(), bounds={})
    structure_mod.StageScorer._refit(scorer, spec, np.zeros(1), [np.zeros(1)], 15,
                                     converge=True)
    assert len(calls) == (1 if spent else structure_mod.MAX_REFINE_STEPS)


def test_the_control_table_leaves_no_row_of_blanks_and_says_what_it_could_not_score():
    """The demo's free-tie-rods control does not log the tie-rod forces, yet the table's
    pivot over tests × channels gave it their rows, "nan" in every family. The table keeps
    the comparison's rows; a channel it has but no family scores (constant in its test) is
    listed beneath; a family without a FIT in one cell shows a dash; the means follow."""
    from mbst.report.discovery import control_lines

    rows = [("s2", "steering_torque_nm", "base", 85.3), ("s2", "steering_torque_nm",
                                                          "extended", 98.4),
            ("s2", "steering_torque_nm", "sindy", np.nan),
            ("s2", "tie_rod_force_left_n", "base", np.nan),
            ("s2", "tie_rod_force_left_n", "extended", np.nan),
            ("s2", "tie_rod_force_left_n", "sindy", np.nan),
            ("s3", "steering_torque_nm", "base", 98.8), ("s3", "steering_torque_nm",
                                                          "extended", 99.8),
            ("s3", "steering_torque_nm", "sindy", 67.3)]
    table = pd.DataFrame(rows, columns=["test", "channel", "model", "fit_percent"])
    text = "\n".join(control_lines(table))
    assert "nan" not in text
    assert "| s2 | steering_torque_nm | 85.3 | 98.4 | – |" in text
    assert "| s2 | tie_rod_force_left_n |" not in text
    assert text.endswith("nor a twin that could not be simulated): s2 tie_rod_force_left_n.")
    assert "Mean over the rows above: base 92.0 %, extended 99.1 %, sindy 67.3 %." in text


def test_a_rack_power_law_is_refitted_from_starts_that_keep_its_damping_force(tmp_path):
    """A power law's damping changes units with its exponent (b·|v|^a): moving the exponent
    alone from 1 to 0.7 multiplies a rack's damping force by ~4 at 1 cm/s. The grid's
    starts then cost many times the base and the screen's short refit fell back, so a
    realistic rig's rack power law (0.71, seed 2404) was never refitted. Its starts keep
    the damping force over the stage's speeds: the screen's budget finds it."""
    from mbst.discovery.structure import StageScorer
    from mbst.identify.fitting import channel_scales, prepare_test

    recipe = BenchRecipe(effects=["power_law_damping:rack:exponent=0.7"], seed=1,
                         plan=compact_plan())
    camp = read_campaign(run_bench(tmp_path, recipe))
    tests = [prepare_test(camp, s, 0.005) for s in camp.identification_tests()
             if s.scenario == "free_tie_rods"]
    idx = EPS_MODEL.param_index
    exponent, damping = "rack.power_law_damping.exponent", "rack.viscous_ns_per_m"
    base = recipe.true_params()
    base[idx[exponent]] = 1.0
    base[idx[damping]] *= 2.5  # a base fit lifts it to stand in for the low-speed force
    scorer = StageScorer(tests, "free_tie_rods", base, channel_scales(tests))
    spec = EPS_MODEL.effects["power_law_damping:rack"]

    p = scorer.base_refit()[0]
    row = p.copy()
    row[idx[exponent]] = 0.7
    kept = scorer.keep_damping_force(row[None], p, spec)[0]
    v = np.abs(scorer._element_speed("rack"))
    force = p[idx[damping]] * v
    assert np.linalg.norm(kept[idx[damping]] * v ** 0.7 - force) < 0.5 * np.linalg.norm(force)
    assert kept[idx[damping]] < 0.5 * p[idx[damping]]  # |v|^0.7 >> |v| at rack speeds

    screened = scorer.score(spec, 1000.0, max_nfev=5)  # the screen's budget
    assert screened.relative_gain > 0.1, screened.relative_gain
    assert abs(screened.headline["exponent"] - 0.7) < 0.1, screened.headline


def test_an_extension_that_does_worse_on_the_controls_is_said_so(play, tmp_path):
    """Fitted on the identification tests, named effects can fail to carry over (a
    realistic rig's 20 mN·m motor cogging, outside the catalogue: control FIT 95.6 → 91.8
    % with two weak names). The page and the command's summary say so; the answer itself
    is the same, as the controls never choose it."""
    from mbst.report.discovery import markdown_summary

    _, _, result = play
    assert pipeline_mod.controls_below_base(result.findings, result.comparison) is None
    assert "extension does worse" not in markdown_summary(result)
    worse = result.comparison.copy()
    ext, base = (worse.model == m for m in ("extended", "base"))
    worse.loc[ext, "fit_percent"] = worse.loc[base, "fit_percent"].to_numpy() - 5.0
    bad = dataclasses.replace(result, comparison=worse)
    base_mean = worse[worse.model == "base"].fit_percent.mean()
    got = pipeline_mod.controls_below_base(bad.findings, bad.comparison)
    assert got is not None and got[0] == pytest.approx(base_mean)
    assert got[1] < got[0] - 4.9
    assert "**Held out, the extension does worse:**" in markdown_summary(bad)
    assert "scores below the base on the controls" in bad.summary()
    write_discover_outputs(bad, tmp_path / "out")
    rec = json.loads((tmp_path / "out" / "discovery.json").read_text())
    assert [f["effect"] for f in rec["findings"]] == [f.effect for f in result.findings]


def test_a_gain_the_stage_reaches_with_the_effect_off_is_not_the_effects(tmp_path):
    """A candidate's refit frees the stage's parameters with the effect, and from its
    starts it can reach a better basin of the base model than the base refit did
    (realistic rig 2512: a rack asymmetry of 1.004 "removed" 57 % of its stage beside a
    rack Stribeck term the same refit moved to its true velocity, and was named). Its
    share is measured against its own fit with the effect off: on a clean stage whose base
    refit sits in a worse basin, an asymmetry gains nothing."""
    from mbst.discovery.structure import StageScorer
    from mbst.identify.fitting import channel_scales, prepare_test

    recipe = BenchRecipe(effects=[], seed=1, plan=compact_plan())
    camp = read_campaign(run_bench(tmp_path, recipe))
    tests = [prepare_test(camp, s, 0.005) for s in camp.identification_tests()
             if s.scenario == "blocked_column"]
    scorer = StageScorer(tests, "blocked_column", recipe.true_params(), channel_scales(tests))
    p, cost = scorer.base_refit()
    # a base refit stuck in a worse basin: the column's Coulomb level 60 % too high
    stuck = p.copy()
    stuck[EPS_MODEL.param_index["steering_column.coulomb_nm"]] *= 1.6
    per_test = scorer.costs(stuck[None])[0]
    assert per_test.sum() > 2 * cost
    scorer._base_fit, scorer._base_per_test = (stuck, float(per_test.sum())), per_test

    score = scorer.score(EPS_MODEL.effects["asymmetric_friction:steering_column"], 1000.0,
                         max_nfev=5)
    assert score.cost < 0.7 * per_test.sum()  # the refit left the stuck basin
    assert score.relative_gain < 0.05, (score.relative_gain, score.headline)
