"""Stated known values a bit off: a rival of every structure-test winner (``rivals.py``)."""

from __future__ import annotations

import pytest

from mbst.discovery import rivals
from mbst.discovery.structure import StageScorer
from mbst.identify.fitting import channel_scales, prepare_test
from mbst.io.campaign import read_campaign
from mbst.systems.eps.bench import BenchRecipe, compact_plan, run_bench
from mbst.systems.eps.model import EPS_MODEL
from mbst.systems.eps.realism import BenchRealism

STAGE = "free_tie_rods"
INERTIA = "motor_inertia_kgm2"


@pytest.fixture(scope="module")
def stage(tmp_path_factory):
    """The compact plan's free tie-rods stage of a clean rig, the base model at the truth
    but for the motor inertia, which the campaign states 12 % low (eps-model.md: known
    values "a few to 15 % off")."""
    return _stage_stated_low(tmp_path_factory.mktemp("stated"), [])


def _stage_stated_low(out, effects: list[str], off: tuple[str, ...] = ()
                      ) -> tuple[StageScorer, float]:
    """The compact plan's free tie-rods stage of a rig with ``effects``, the base model at
    the truth but for the motor inertia (stated 12 % low) and the effects' parameters
    ``off`` (back at neutral); and the rig's true inertia."""
    recipe = BenchRecipe(effects=effects, seed=1, plan=compact_plan())
    camp = read_campaign(run_bench(out, recipe))
    tests = [prepare_test(camp, s, 0.005) for s in camp.identification_tests()
             if s.scenario == STAGE]
    truth = recipe.true_params()
    true_inertia = float(truth[EPS_MODEL.param_index[INERTIA]])
    base = truth.copy()
    base[EPS_MODEL.param_index[INERTIA]] = 0.88 * true_inertia
    for name in off:
        base[EPS_MODEL.param_index[name]] = EPS_MODEL.spec(name).default
    return StageScorer(tests, STAGE, base, channel_scales(tests), max_nfev=10), true_inertia


def _refit(scorer: StageScorer, stated: float, tolerance: float):
    found = rivals.rivals(scorer, EPS_MODEL, 500.0,
                          rivals.Stated({INERTIA: stated}, tolerance))
    return next(s for s in found if s.effect == rivals.STATED)


# ~16 s; CI keeps the match declining a winner, the geometry band and _past_rivals' use
@pytest.mark.slow
def test_stated_values_are_refitted_within_their_tolerance_and_read_as_such(stage):
    """Refitted within ±15 %, the stated inertia goes back to the rig's and takes the
    stage's misfit above the noise; within ±5 % it stops on its bound. The round says which value
    moved and by how much."""
    scorer, true_inertia = stage
    stated = 0.88 * true_inertia
    wide = _refit(scorer, stated, 0.15)
    # the rest of the stage's cost is the sensors' noise (28 % removed here)
    assert wide.relative_gain > 0.2, wide.relative_gain
    assert wide.headline[INERTIA] == pytest.approx(true_inertia, rel=0.03)
    narrow = _refit(scorer, stated, 0.05)
    assert narrow.headline[INERTIA] == pytest.approx(1.05 * stated, rel=1e-6)
    assert narrow.relative_gain < wide.relative_gain
    assert "(+5.0 %, its bound)" in rivals.reading(narrow, rivals.Stated({INERTIA: stated}, 0.05))
    said = rivals.reading(wide, rivals.Stated({INERTIA: stated}, 0.15))
    assert "within ±15 %" in said and INERTIA in said and "its bound" not in said
    change = 100 * (wide.headline[INERTIA] / stated - 1.0)
    assert f"({change:+.1f} %)" in said


def test_a_winner_the_stated_values_match_is_not_named_and_they_stay_as_stated(stage):
    """The match declines the winner (``rivals.matching``); the record says the values are
    the campaign's statement to check, not an effect the unexplained round refits."""
    from dataclasses import replace

    scorer, true_inertia = stage
    rival = _refit(scorer, 0.88 * true_inertia, 0.15)
    winner = replace(rival, key="load_dependent_friction:rack",
                     effect="load_dependent_friction", component="rack",
                     cost=rival.cost_base - 0.8 * (rival.cost_base - rival.cost))
    assert rivals.matching(winner, [rival]) is rival
    gone = rivals.declined(winner, rival, rivals.Stated({INERTIA: 0.88 * true_inertia}, 0.15))
    assert "may be the stated values'" in gone["reason"] and "mbst identify" in gone["reason"]
    stronger = replace(winner, cost=rival.cost * 0.5)
    assert rivals.matching(stronger, [rival]) is None


def test_a_value_the_stage_fits_already_or_a_family_without_a_tolerance_adds_no_rival(stage):
    scorer, true_inertia = stage
    free = rivals.Stated({INERTIA: true_inertia, "motor.coulomb_nm": 0.02}, 0.15)
    specs = rivals.specs(scorer.tests, EPS_MODEL, free.without(scorer.stage_free))
    stated = [s for s in specs if s.effect == rivals.STATED]
    assert [s.free for s in stated] == [(INERTIA,)]
    assert stated[0].bounds[INERTIA] == pytest.approx((0.85 * true_inertia,
                                                       1.15 * true_inertia))
    assert not any(s.effect == rivals.STATED for s in rivals.specs(
        scorer.tests, EPS_MODEL, rivals.Stated({INERTIA: true_inertia}, 0.0)))
    # a value with nothing to move in: 0, fixed by the family, outside the family's range
    odd = rivals.Stated({"motor.regularisation_velocity_rad_per_s": 1e-3, INERTIA: 0.0,
                         "wheel_mass_kg": 250.0}, 0.15)
    assert not any(s.effect == rivals.STATED for s in rivals.specs(scorer.tests, EPS_MODEL, odd))


@pytest.mark.slow  # ~25 s; CI keeps a lag's step from its typical size (the test after)
def test_a_rival_is_refitted_only_where_one_step_says_it_can_come_near(stage):
    """One Gauss–Newton step of each rival and the stage's parameters (the stated values
    from their statement, within the tolerance) reads what its refit reaches, here to a
    few points; where that is under half the winner's share the refit is not run."""
    scorer, true_inertia = stage
    told = rivals.Stated({INERTIA: 0.88 * true_inertia}, 0.15)
    found = rivals.specs(scorer.tests, EPS_MODEL, told, rivals.held_offsets(scorer))
    assert {sp.effect for sp in found} == {rivals.LAG, rivals.DRIFT, rivals.STATED,
                                           rivals.OFFSET}
    for spec in found:
        step = scorer.linearised_share(spec, at_default_size=spec.effect == rivals.LAG)
        assert step == pytest.approx(scorer.score(spec, 500.0).relative_gain, abs=0.05), \
            spec.key
    spec = rivals.stated_spec(told, EPS_MODEL)
    step = scorer.linearised_share(spec)
    keys = {s.key for s in rivals.rivals(scorer, EPS_MODEL, 500.0, told, 1.9 * step)}
    assert spec.key in keys
    keys = {s.key for s in rivals.rivals(scorer, EPS_MODEL, 500.0, told, 2.1 * step)}
    assert spec.key not in keys


def test_a_sensor_lag_is_screened_from_its_typical_size(tmp_path_factory):
    """A discrete first-order lag is flat at zero (its pole goes as e^(−dt/τ)), so a step
    from no lag reads nothing of a 3 ms torque lag that its refit takes half the blocked
    column for; from the typical 3 ms it reads the refit's share, and the lag is refitted
    beside a winner it matches."""
    camp = read_campaign(run_bench(tmp_path_factory.mktemp("lag"), BenchRecipe(
        effects=[], seed=1, plan=compact_plan(), realism=BenchRealism(torque_lag_s=0.003))))
    stage = "blocked_column"
    tests = [prepare_test(camp, s, 0.005) for s in camp.identification_tests()
             if s.scenario == stage]
    base = BenchRecipe(effects=[], seed=1, plan=compact_plan()).true_params()
    base[EPS_MODEL.param_index[EPS_MODEL.sensor_lags["steering_torque_nm"]]] = 0.0
    scorer = StageScorer(tests, stage, base, channel_scales(tests), max_nfev=10)
    lag = next(sp for sp in rivals.specs(scorer.tests, EPS_MODEL) if sp.effect == rivals.LAG)
    refit = scorer.score(lag, 500.0).relative_gain
    assert refit > 0.3, refit
    assert scorer.linearised_share(lag) < 0.5 * refit
    assert scorer.linearised_share(lag, at_default_size=True) == pytest.approx(refit, abs=0.05)
    assert lag.key in {s.key for s in rivals.rivals(scorer, EPS_MODEL, 500.0,
                                                    winner_share=0.9 * refit)}


def test_geometry_is_stated_closer_than_an_inertia():
    """eps-model.md's "a few to 15 % off" is the inertias': a gear's tooth ratio and a
    pinion's radius from a drawing move within the family's tighter band, so the stated
    values cannot take a stage's misfit by a gear ratio 6 % off (realistic rig 1904)."""
    from mbst.discovery.rounds.catalogue import stated
    from mbst.discovery.structure import CandidateScore

    told = {INERTIA: 4.0e-5, "worm_gear_ratio": 16.5, "pinion_radius_m": 0.0075}

    class _Campaign:
        known, priors = told, {}

    class _State:
        campaign, model = _Campaign(), EPS_MODEL

    spec = rivals.stated_spec(stated(_State()), EPS_MODEL)
    tight = EPS_MODEL.stated_tolerance_by_name["worm_gear_ratio"]
    assert tight <= 0.05 < EPS_MODEL.stated_tolerance
    assert spec.bounds["worm_gear_ratio"] == pytest.approx((16.5 * (1 - tight),
                                                            16.5 * (1 + tight)))
    assert spec.bounds["pinion_radius_m"][1] == pytest.approx(0.0075 * (1 + tight))
    assert spec.bounds[INERTIA] == pytest.approx((0.85 * 4.0e-5, 1.15 * 4.0e-5))
    # the reading says each band, and a ratio on its bound as on its bound
    moved = CandidateScore(
        key=spec.key, effect=spec.effect, component=spec.component, stage=STAGE, tests=[],
        free=list(spec.free), k_effect=3, cost_base=1.0, cost=0.8, n_eff=100.0,
        aic_delta=-10.0, params=None,
        headline={INERTIA: 3.4e-5, "worm_gear_ratio": 16.5 * (1 + tight),
                  "pinion_radius_m": 0.0075})
    said = rivals.reading(moved, stated(_State()))
    band = f"±{100 * tight:g} %"
    assert f"within ±15 % (pinion_radius_m {band}, worm_gear_ratio {band})" in said
    assert (f"worm_gear_ratio 16.5 → {16.5 * (1 + tight):.4g} "
            f"(+{100 * tight:.1f} %, its bound)") in said


@pytest.mark.slow  # ~19 s; CI keeps _past_rivals' use of it (test_discover) and the bands
def test_an_effect_the_stated_values_stand_in_for_does_not_stand_beyond_them(stage):
    """Nested with the stated values (``rivals.beyond``), a catalogue effect on a clean
    stage whose motor inertia is stated 12 % low adds nothing the values do not: it stays
    declined."""
    scorer, true_inertia = stage
    told = rivals.Stated({INERTIA: 0.88 * true_inertia}, 0.15)
    rival = _refit(scorer, 0.88 * true_inertia, 0.15)
    effect = scorer.score(EPS_MODEL.effects["load_dependent_friction:rack"], rival.n_eff)
    past = rivals.beyond(scorer, EPS_MODEL, effect, rival, told)
    assert past.cost_base == rival.cost
    assert past.relative_gain < 0.10, (past.relative_gain, effect.relative_gain,
                                       rival.relative_gain)


@pytest.mark.slow  # two bench stages and four refits, ~40 s
def test_an_effect_the_stage_has_beyond_the_stated_values_stands(tmp_path):
    """A planted motor asymmetry beside a motor inertia stated 12 % low: the stated values
    alone take part of the stage, but the asymmetry, nested with them, still removes more
    than the margin of what they leave (realistic rig 1904 had such an asymmetry declined)."""
    scorer, true_inertia = _stage_stated_low(
        tmp_path, ["asymmetric_friction:motor:ratio=0.75"],
        off=("motor.asymmetric_friction.ratio",))
    told = rivals.Stated({INERTIA: 0.88 * true_inertia}, 0.15)
    effect = scorer.score(EPS_MODEL.effects["asymmetric_friction:motor"], 500.0)
    rival = _refit(scorer, 0.88 * true_inertia, 0.15)
    past = rivals.beyond(scorer, EPS_MODEL, effect, rival, told)
    assert past.relative_gain > 0.10 and past.aic_delta < -10, (
        past.relative_gain, past.aic_delta, effect.relative_gain, rival.relative_gain)
