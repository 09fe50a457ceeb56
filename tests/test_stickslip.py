"""The phase-free envelope test for Stribeck stick-slip (discovery/stickslip.py)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from mbst.core.filtering import exponential_filter
from mbst.discovery.rounds.stickslip import (
    MIN_BASE_MISFIT,
    StickSlipScore,
    envelope_misfit,
    rank,
)

DT, TAU, NOISE = 0.002, 0.01, 0.02


def _rig(phase: float, stick_slip: bool, noise_seed: int | None = None) -> np.ndarray:
    """A slow drive with a 6 Hz sawtooth during two slow phases, filtered like a channel."""
    t = np.arange(0.0, 8.0, DT)
    y = 2.0 * np.sin(2 * np.pi * 0.25 * t)
    if stick_slip:
        saw = 0.3 * (((6.0 * t + phase) % 1.0) - 0.5)
        y = y + saw * ((np.abs(t - 2.0) < 0.6) | (np.abs(t - 6.0) < 0.6))
    if noise_seed is not None:
        y = y + NOISE * np.random.default_rng(noise_seed).standard_normal(len(t))
    return exponential_filter(y, DT, TAU)


def _test(measured: np.ndarray) -> SimpleNamespace:
    from mbst.core.filtering import filtered_noise_gain

    return SimpleNamespace(measured={"steering_torque_nm": measured}, dt_s=DT, tau_s=TAU,
                           noise={"steering_torque_nm": NOISE * filtered_noise_gain(DT, TAU)})


def test_envelope_misfit_ignores_the_phase_of_a_sawtooth_that_output_error_punishes():
    pt = _test(_rig(0.0, True, noise_seed=1))
    meas = pt.measured["steering_torque_nm"]
    twin = lambda y: {"steering_torque_nm": y}  # noqa: E731
    smooth, shifted = _rig(0.0, False), _rig(0.5, True)
    # output error prefers the model without stick-slip over the right one out of phase
    assert np.sum((shifted - meas) ** 2) > np.sum((smooth - meas) ** 2)
    # the envelope does the opposite, and by far
    assert envelope_misfit(pt, twin(smooth)) > MIN_BASE_MISFIT
    assert envelope_misfit(pt, twin(shifted)) < 0.2 * envelope_misfit(pt, twin(smooth))


def test_sensor_noise_alone_stays_under_the_search_threshold():
    for seed in range(3):
        pt = _test(_rig(0.0, False, noise_seed=seed))
        assert envelope_misfit(pt, {"steering_torque_nm": _rig(0.0, False)}) < \
            0.5 * MIN_BASE_MISFIT


def _score(key: str, misfit: float, typicality: float = 0.0, at_bound=()) -> StickSlipScore:
    effect, component = key.split(":")
    return StickSlipScore(key, effect, component, "free_tie_rods", 100.0, misfit,
                          np.zeros(1), typicality=typicality, at_bound=list(at_bound))


def test_rank_puts_a_size_on_its_bound_behind_an_inside_fit():
    motor = _score("stribeck_friction:motor", 4.0, at_bound=["static_to_coulomb_ratio"])
    rack = _score("stribeck_friction:rack", 8.0)
    order = rank([motor, rack])
    assert [s.key for s in order] == ["stribeck_friction:rack", "stribeck_friction:motor"]
    assert order[0].decided_by == "range"


def test_rank_breaks_a_near_tie_by_the_more_typical_size():
    a = _score("stribeck_friction:motor", 1.0, typicality=1.4)
    b = _score("stribeck_friction:rack", 1.1, typicality=0.2)
    c = _score("stribeck_friction:steering_column", 90.0)  # removes too little to contend
    order = rank([a, b, c])
    assert [s.component for s in order] == ["rack", "motor", "steering_column"]
    assert order[0].decided_by == "typical size"
    # the finding names both: the near tie is the data's answer, the typical size a guess
    assert order[0].tied_with == ["motor"]
    # outside the tie the misfit decides
    a2, b2 = _score("stribeck_friction:motor", 1.0, 1.4), _score("stribeck_friction:rack", 2.0)
    assert rank([b2, a2])[0].component == "motor" and rank([b2, a2])[0].decided_by == "misfit"
    assert rank([b2, a2])[0].tied_with == []


def test_a_look_alike_that_fits_with_the_levels_at_typical_values_is_tied():
    """Motor and rack move as one body; a base fit that put the friction in the motor
    (rack Coulomb on its bound) leaves a rack Stribeck rise nothing to scale. With the
    levels back at their typical values the rack candidate fits as well: the finding lists
    it and the rule that decided is "levels". Where it still fits worse there than the
    winner does in 95 % of its resamples, no tie."""
    from mbst.discovery.rounds.stickslip import _level_ties
    from mbst.systems.eps.model import EPS_MODEL

    idx = EPS_MODEL.param_index
    rack_c, motor_c = "rack.coulomb_n", "motor.coulomb_nm"

    class Envelope:  # misfit 10 without stick-slip; a Stribeck rise removes it where the
        # element carries friction (its Coulomb level at least a third of typical)
        stage = "free_tie_rods"
        tests = [SimpleNamespace(model=EPS_MODEL, time_s=np.zeros(100), id="t")]

        def misfits(self, ps):
            out = []
            for p in ps:
                m = 10.0
                for elem, c in (("rack", rack_c), ("motor", motor_c)):
                    ratio = p[idx[f"{elem}.stribeck_friction.static_to_coulomb_ratio"]]
                    if ratio > 1.3 and p[idx[c]] >= EPS_MODEL.spec(c).default / 3:
                        m = min(m, 1.0 + rack_weight * (elem == "rack"))
                out.append([m])
            return np.array(out)

    base = np.array(EPS_MODEL.default_vector(), float)
    base[idx[rack_c]], base[idx[motor_c]] = 1.0, 5 * EPS_MODEL.spec(motor_c).default
    reset = {rack_c: EPS_MODEL.spec(rack_c).default, motor_c: EPS_MODEL.spec(motor_c).default}
    env = Envelope()
    from mbst.discovery.rounds.stickslip import score_candidate

    for rack_weight, tied in ((0.1, True), (5.0, False)):
        scores = [score_candidate(env, EPS_MODEL.effects[f"stribeck_friction:{e}"], base,
                                  np.array([10.0])) for e in ("motor", "rack")]
        ranked = rank(scores)
        assert ranked[0].component == "motor" and ranked[1].relative_gain == 0.0
        _level_ties(env, ranked, base, reset, np.array([10.0]))
        assert (ranked[0].tied_with == ["rack"]) is tied
        assert ranked[0].decided_by == ("levels" if tied else "misfit")
    # with the winner's resamples, the tie is what they say, not a fixed factor: the
    # winner (the motor, 90 % of the misfit) removes 85 % or more in 95 % of them (rig 904:
    # the rack re-split at 96.0 %, the motor's 5th percentile 95.6 %, its misfit 1.25x)
    for rack_weight, tied in ((0.3, True), (0.8, False)):
        scores = [score_candidate(env, EPS_MODEL.effects[f"stribeck_friction:{e}"], base,
                                  np.array([10.0])) for e in ("motor", "rack")]
        ranked = rank(scores)
        ranked[0].bootstrap = {"gain_5_95_percent": [0.85, 0.95]}
        _level_ties(env, ranked, base, reset, np.array([10.0]))
        assert (ranked[0].tied_with == ["rack"]) is tied, rack_weight


def test_rank_compares_stages_by_the_share_of_their_own_misfit_removed():
    """Realistic rig 302: a column candidate that removed nothing of a small blocked-column
    misfit (3.0 → 3.001) left less misfit than a motor one that removed 91 % of the free
    tie-rods' (312 → 29); ranked by the misfit left, the motor's name came from the range
    rule and its confidence was halved."""
    column = StickSlipScore("stribeck_friction:steering_column", "stribeck_friction",
                            "steering_column", "blocked_column", 3.0, 3.001, np.zeros(1))
    motor = StickSlipScore("stribeck_friction:motor", "stribeck_friction", "motor",
                           "free_tie_rods", 312.0, 29.0, np.zeros(1))
    rack = StickSlipScore("stribeck_friction:rack", "stribeck_friction", "rack",
                          "free_tie_rods", 312.0, 309.0, np.zeros(1), at_bound=["ratio"])
    order = rank([column, rack, motor])
    assert order[0] is motor and order[0].decided_by == "misfit"


def test_each_grid_point_is_integrated_at_the_step_it_needs_itself(tmp_path):
    """A batch runs at the finest step any of its rows needs: the steepest Stribeck dip
    of the grid set every point's step (rig 122: 3652 sub-steps a sample for the base's
    19, 311 s for one candidate). Each point's misfit is the one it has alone."""
    from mbst.discovery.rounds.stickslip import StageEnvelope
    from mbst.identify.fitting import prepare_test
    from mbst.io.campaign import read_campaign
    from mbst.systems.eps.bench import BenchRecipe, compact_plan, run_bench

    recipe = BenchRecipe(effects=[], seed=1, plan=compact_plan())
    camp = read_campaign(run_bench(tmp_path, recipe))
    pt = next(prepare_test(camp, s, 0.005) for s in camp.identification_tests()
              if s.scenario == "free_tie_rods")
    model = pt.model
    ratio, velocity = model.effects["stribeck_friction:rack"].free
    ps = np.repeat(recipe.true_params()[None], 2, axis=0)
    ps[:, model.param_index[ratio]] = 3.5
    ps[0, model.param_index[velocity]] = model.spec(velocity).default / 4  # a steeper dip
    steps = model.row_steps(pt, ps)
    assert steps[0] > 2 * steps[1], steps  # they need different steps
    env = StageEnvelope([pt], "free_tie_rods")
    together = env.misfits(ps)
    np.testing.assert_array_equal(together[1], env.misfits(ps[1:])[0])


def _residual(test_id: str, motor_speed: np.ndarray, rack_speed: np.ndarray):
    from mbst.discovery.data import TestResidual

    t = np.arange(len(motor_speed)) * 1e-3
    return TestResidual(id=test_id, scenario="free_tie_rods", role="identification",
                        motor="off", dt_s=1e-3, time_s=t, angle_rad=t, omega_rad_per_s=t,
                        measured={}, simulated={},
                        states={"motor_speed_rad_per_s": motor_speed,
                                "rack_speed_m_per_s": rack_speed})


def _finding(effect: str, component: str, confidence: float):
    from mbst.discovery.state import Finding

    return Finding(effect=effect, component=component, parameters={"static_to_coulomb_ratio":
                                                                   1.5}, confidence=confidence,
                   evidence="named", stage="free_tie_rods", relative_gain=0.1,
                   aic_delta=None, cv={})


def test_one_effect_named_in_two_parts_of_one_body_is_one_finding():
    """Realistic rig 602: the output-error test named a rack Stribeck in the motor (0.037)
    and the stick-slip test in the rack (0.45); motor and rack move as one body through the
    stiff mesh, so the answer is one Stribeck finding that names both parts."""
    from mbst.discovery.acceptance import fold_one_body
    from mbst.systems.eps.model import EPS_MODEL

    w = np.sin(np.linspace(0, 20, 4000))
    one_body = [_residual("a", 16.0 / 0.0075 * w, w), _residual("b", 16.0 / 0.0075 * w, w)]
    motor = _finding("stribeck_friction", "motor", 0.037)
    rack = _finding("stribeck_friction", "rack", 0.45)
    other = _finding("asymmetric_friction", "motor", 0.6)
    out = fold_one_body([motor, other, rack], one_body, EPS_MODEL)
    assert [(f.effect, f.component) for f in out] == [("asymmetric_friction", "motor"),
                                                      ("stribeck_friction", "rack")]
    assert out[1].indistinguishable_from == ["motor"]
    assert "ONE BODY" in out[1].evidence and "0.04" in out[1].evidence
    assert out[1].confidence == 0.45
    # parts that move apart (a rack-pinion gap, a soft mesh) keep their own findings
    apart = [_residual("a", 16.0 / 0.0075 * w, np.cos(np.linspace(0, 33, 4000)))]
    out = fold_one_body([_finding("stribeck_friction", "motor", 0.037),
                         _finding("stribeck_friction", "rack", 0.45)], apart, EPS_MODEL)
    assert [f.component for f in out] == ["motor", "rack"]


def test_a_ratio_named_in_one_part_of_a_body_is_stated_as_the_body_s():
    """Realistic rig 711 (200 Hz): a rack asymmetry of 0.766 (rack 229 N, motor 0.0203 N·m)
    was fitted as 0.393 on a rack level of 67 N beside a motor level of 0.099 N·m and named
    "rack or motor": the same ~60 N between the directions, on another split of the body's
    level. The finding now states the body's ratio, which these tests pin; the fitted split
    gives the truth's to 1 %."""
    from mbst.discovery.lumped import state_body_sizes
    from mbst.systems.eps.model import EPS_MODEL

    n, r_p = 16.0, 0.0078
    w = np.sin(np.linspace(0, 20, 4000))
    body = [_residual("a", n / r_p * w, w)]
    idx = EPS_MODEL.param_index

    def stated(rack_n, motor_nm, ratio, tied=("motor",)):
        p = EPS_MODEL.default_vector().copy()
        p[idx["rack.coulomb_n"]], p[idx["motor.coulomb_nm"]] = rack_n, motor_nm
        p[idx["rack.asymmetric_friction.ratio"]] = ratio
        f = _finding("asymmetric_friction", "rack", 0.9)
        f.parameters, f.indistinguishable_from = {"ratio": ratio}, list(tied)
        state_body_sizes([f], body, EPS_MODEL, p)
        return f

    truth, fitted = stated(229.46, 0.0203, 0.766), stated(67.4, 0.0992, 0.393)
    assert truth.parameters["ratio"] == pytest.approx(0.798, abs=0.005)
    assert fitted.parameters["ratio"] == pytest.approx(truth.parameters["ratio"], rel=0.01)
    assert "ONE-BODY SIZE" in fitted.evidence and "0.393" in fitted.evidence
    # a part named alone keeps its own size
    assert stated(67.4, 0.0992, 0.393, tied=()).parameters["ratio"] == 0.393
    # a Stribeck rise: the body's rise over the body's level
    p = EPS_MODEL.default_vector().copy()
    p[idx["rack.coulomb_n"]], p[idx["motor.coulomb_nm"]] = 200.0, 0.0
    p[idx["rack.stribeck_friction.static_to_coulomb_ratio"]] = 1.5
    f = _finding("stribeck_friction", "rack", 0.45)
    f.indistinguishable_from = ["motor"]
    state_body_sizes([f], body, EPS_MODEL, p)
    assert f.parameters["static_to_coulomb_ratio"] == pytest.approx(1.5)


def test_a_name_whose_body_twin_is_tied_or_not_ruled_out_is_at_most_even_odds():
    """Realistic rig 716: a rack presliding hysteresis named in the motor at 0.51 (57.7 % of
    the stage against the rack's 56.5 %, the motor the better in 85 % of the resamples). The
    resamples cannot see how the base fit split the body's levels, so the name is at most
    even odds against the rack; a look-alike of another effect, or a part that moves apart,
    leaves the confidence alone."""
    from mbst.discovery.acceptance import EVEN_ODDS
    from mbst.discovery.rounds.catalogue import proposal_finding
    from mbst.discovery.state import Proposal
    from mbst.systems.eps.model import EPS_MODEL

    w = np.sin(np.linspace(0, 20, 4000))

    def finding(rack_speed, alternatives, confidence=0.9):
        best = SimpleNamespace(key="presliding_hysteresis:motor", effect="presliding_hysteresis",
                               component="motor", stage="free_tie_rods", relative_gain=0.577,
                               aic_delta=-467.0, n_eff=545.0, tests=["a"], params=None)
        boot = {"confidence": confidence, "wins_share": 0.85, "explained_above_noise": 0.9,
                "resamples": 400, "gain_5_95_percent": [0.47, 0.64],
                "alternatives": [{"key": f"{e}:{c}", "effect": e, "component": c,
                                  "relative_gain": 0.565, "winner_better_share": 0.85}
                                 for e, c in alternatives]}
        state = SimpleNamespace(model=EPS_MODEL, p=EPS_MODEL.default_vector(), regions=[],
                                rounds=[],
                                residuals=[_residual("a", 16.0 / 0.0075 * w, rack_speed)])
        return proposal_finding(Proposal(best, None, {}, 0.5, [], boot), state, None, None)

    same = [("presliding_hysteresis", "rack")]
    f = finding(w, same)
    assert f.confidence == EVEN_ODDS and "COMPONENT UNDECIDED" in f.evidence
    # a tie (the parts named together) is the same question: the body at its confidence,
    # the part at even odds (realistic rig 905: a rack asymmetry named "motor (or rack)"
    # at 0.87)
    twin = SimpleNamespace(component="rack", relative_gain=0.574)
    best = SimpleNamespace(key="asymmetric_friction:motor", effect="asymmetric_friction",
                           component="motor", stage="free_tie_rods", relative_gain=0.577,
                           aic_delta=-467.0, n_eff=545.0, tests=["a"], params=None)
    boot = {"confidence": 0.87, "wins_share": 0.87, "explained_above_noise": 1.0,
            "resamples": 400, "gain_5_95_percent": [0.47, 0.64], "alternatives": []}
    state = SimpleNamespace(model=EPS_MODEL, p=EPS_MODEL.default_vector(), regions=[],
                            rounds=[],
                            residuals=[_residual("a", 16.0 / 0.0075 * w, w)])
    tied = proposal_finding(Proposal(best, None, {}, 0.5, [(twin, 0.9998)], boot), state,
                            None, None)
    assert tied.indistinguishable_from == ["rack"] and tied.confidence == EVEN_ODDS
    assert "body of motor and rack at 0.87" in tied.evidence
    alone = proposal_finding(Proposal(best, None, {}, 0.5, [], boot), state, None, None)
    assert alone.confidence == 0.87
    assert finding(w, same, confidence=0.3).confidence == 0.3
    assert finding(w, [("backlash", "rack_pinion")]).confidence == 0.9
    assert finding(np.cos(np.linspace(0, 33, 4000)), same).confidence == 0.9


def test_a_name_whose_size_ends_on_the_edge_of_its_range_is_doubted():
    """A clean realistic rig whose friction turns through zero speed ten times softer than
    the model's (bench smoothing 10, seed 2011): the free tie-rods' winner was rack damping
    ∝ |v|^0.20, the exponent's bound, at 0.70 (69.5 % of the stage, 100 % of the
    resamples). A form pushed to its edge is the nearest catalogue shape, not a measured
    size: the name is doubted and says so; inside its range it keeps its confidence."""
    from mbst.discovery.acceptance import DOUBTED_CONFIDENCE
    from mbst.discovery.rounds.catalogue import proposal_finding
    from mbst.discovery.state import Proposal
    from mbst.systems.eps.model import EPS_MODEL

    w = np.sin(np.linspace(0, 20, 4000))
    state = SimpleNamespace(model=EPS_MODEL, p=EPS_MODEL.default_vector(), regions=[],
                            rounds=[], residuals=[_residual("a", 16.0 / 0.0075 * w, w)])
    boot = {"confidence": 0.70, "wins_share": 1.0, "explained_above_noise": 0.7,
            "resamples": 400, "gain_5_95_percent": [0.617, 0.747], "alternatives": []}

    def finding(exponent: float):
        params = EPS_MODEL.default_vector()
        params[EPS_MODEL.param_index["rack.power_law_damping.exponent"]] = exponent
        best = SimpleNamespace(key="power_law_damping:rack", effect="power_law_damping",
                               component="rack", stage="free_tie_rods", relative_gain=0.695,
                               aic_delta=-281.0, n_eff=239.0, tests=["a"], params=params)
        return proposal_finding(Proposal(best, None, {}, 0.5, [], boot), state, None, None)

    edge = finding(0.2002)
    assert edge.confidence == DOUBTED_CONFIDENCE
    assert "SIZE ON THE EDGE OF ITS RANGE: exponent 0.2002 (range 0.2–2)" in edge.evidence
    inside = finding(0.55)
    assert inside.confidence == 0.70 and "EDGE" not in inside.evidence
    # a shape on its bound is not a strength cut short: the demo's tire Stribeck ends with
    # its velocity on the search bound and the ratio inside its range
    params = EPS_MODEL.default_vector()
    params[EPS_MODEL.param_index["tires.stribeck_friction.static_to_coulomb_ratio"]] = 2.1
    params[EPS_MODEL.param_index["tires.stribeck_friction.stribeck_velocity"]] = \
        EPS_MODEL.search_lower["tires.stribeck_friction.stribeck_velocity"]
    dip = SimpleNamespace(key="stribeck_friction:tires", effect="stribeck_friction",
                          component="tires", stage="tires_on_ground", relative_gain=0.99,
                          aic_delta=-900.0, n_eff=900.0, tests=["a"], params=params)
    assert proposal_finding(Proposal(dip, None, {}, 0.5, [], boot), state, None,
                            None).confidence == 0.70


def test_a_body_twin_within_the_winners_bootstrap_spread_is_named_beside_it():
    """Realistic rig 923 (known values as priors): a rack presliding named in the motor,
    26.9 % of the stage against the rack's 24.7 %, the motor the better in 97 % of the
    resamples, so no look-alike "not ruled out". A paired resample cannot move how the base
    fit split the body's levels; the rack's share lies inside the motor's own bootstrap
    spread (21.2-32.5 %), so the finding names both parts, at most even odds. A twin
    below that spread, one in a part that moves apart, or another effect stays out."""
    from mbst.discovery.acceptance import EVEN_ODDS, body_twins_within_reach
    from mbst.discovery.rounds.catalogue import proposal_finding
    from mbst.discovery.state import Proposal
    from mbst.systems.eps.model import EPS_MODEL

    w = np.sin(np.linspace(0, 20, 4000))
    apart = np.cos(np.linspace(0, 33, 4000))

    def cand(key, gain):
        effect, component = key.split(":")
        return SimpleNamespace(key=key, effect=effect, component=component,
                               stage="free_tie_rods", relative_gain=gain, aic_delta=-300.0,
                               n_eff=1054.0, tests=["a"], fell_back=False,
                               params=None)

    best = cand("presliding_hysteresis:motor", 0.269)
    boot = {"confidence": 0.9, "wins_share": 0.97, "explained_above_noise": 1.0,
            "resamples": 400, "gain_5_95_percent": [0.212, 0.325], "alternatives": []}

    def twins(rack_speed, *scores):
        residuals = {"a": _residual("a", 16.0 / 0.0075 * w, rack_speed)}
        return body_twins_within_reach(best, [best, *scores], boot, residuals, EPS_MODEL)

    rack = cand("presliding_hysteresis:rack", 0.247)
    assert [t["component"] for t in twins(w, rack)] == ["rack"]
    assert twins(w, cand("presliding_hysteresis:rack", 0.15)) == []
    # ... unless it clears the round's margins on its own (rig 904): one body's parts
    # differ in the model's law of each, not in what the data measure
    lone = cand("presliding_hysteresis:rack", 0.15)
    margins = {"key": lone.key, "component": "rack", "relative_gain": 0.15}
    assert body_twins_within_reach(best, [best, lone], boot, {"a": _residual(
        "a", 16.0 / 0.0075 * w, w)}, EPS_MODEL, (0.10, 10.4)) == [margins]
    assert body_twins_within_reach(best, [best, lone], boot, {"a": _residual(
        "a", 16.0 / 0.0075 * w, apart)}, EPS_MODEL, (0.10, 10.4)) == []
    assert twins(apart, rack) == []
    assert twins(w, cand("asymmetric_friction:rack", 0.26)) == []

    state = SimpleNamespace(model=EPS_MODEL, p=EPS_MODEL.default_vector(), regions=[],
                            rounds=[],
                            residuals=[_residual("a", 16.0 / 0.0075 * w, w)])
    for confidence, expected in ((0.9, EVEN_ODDS), (0.18, 0.18)):
        b = {**boot, "confidence": confidence, "body_twins": twins(w, rack)}
        f = proposal_finding(Proposal(best, rack, {}, 0.5, [], b), state, None, None)
        assert f.indistinguishable_from == ["rack"] and f.confidence == expected
        assert "COMPONENT UNDECIDED: rack moves as one body with motor" in f.evidence
    alone = proposal_finding(Proposal(best, rack, {}, 0.5, [], {**boot, "body_twins": []}),
                             state, None, None)
    assert alone.indistinguishable_from == [] and alone.confidence == 0.9


def test_a_stick_slip_name_the_base_fit_s_split_decided_is_undecided():
    """Realistic rig 702: a rack Stribeck (1.84) named in the motor at 0.96 by the stick-slip
    round; the base fit had put the rack's friction in the motor (rack 6.4 N for 317 N,
    motor 0.19 N·m for 0.019), so a rack rise scaled nothing. The finding names the rack
    beside the motor, at most even odds; a typical split, or parts that move apart, leave
    it alone."""
    from mbst.discovery.acceptance import EVEN_ODDS
    from mbst.discovery.rounds.stickslip import _split_undecided
    from mbst.systems.eps.model import EPS_MODEL

    w = np.sin(np.linspace(0, 20, 4000))
    idx = EPS_MODEL.param_index
    p = EPS_MODEL.default_vector().copy()
    p[idx["rack.coulomb_n"]], p[idx["motor.coulomb_nm"]] = 6.4, 0.19
    rec = {"candidates": [{"key": "stribeck_friction:motor", "stage": "free_tie_rods"},
                          {"key": "stribeck_friction:rack", "stage": "free_tie_rods"},
                          {"key": "stribeck_friction:steering_column",
                           "stage": "blocked_column"}]}
    atypical = {"rack.coulomb_n": 270.0, "motor.coulomb_nm": 0.03}

    def judged(rack_speed, reset):
        f = _finding("stribeck_friction", "motor", 0.96)
        state = SimpleNamespace(model=EPS_MODEL, p=p,
                                residuals=[_residual("a", 16.0 / 0.0075 * w, rack_speed)])
        _split_undecided(f, rec, state, reset)
        return f

    f = judged(w, atypical)
    assert f.indistinguishable_from == ["rack"] and f.confidence == EVEN_ODDS
    assert "COMPONENT UNDECIDED" in f.evidence and "rack.coulomb_n 6.4" in f.evidence
    assert judged(w, {}).confidence == 0.96
    assert judged(np.cos(np.linspace(0, 33, 4000)), atypical).indistinguishable_from == []


def test_the_resolution_step_predicts_against_the_model_the_structure_rounds_searched(
        monkeypatch):
    """Rig 921 (drawn like an independent simulator's: a 1.45° worm-gear backlash beside a
    rack stick-slip): the stick-slip round put a rack Stribeck term in after the structure
    rounds had stopped, and the resolution step, predicting against that model, stated the
    gap resolved "at or below 0.20°" while a 1.45° gap was missed. A size is resolved when
    the structure test would have named it, so the step predicts against the model the
    structure rounds last searched; without them, against the model as it stands."""
    import mbst.discovery.rounds.resolution as resolution
    from mbst.discovery.state import DiscoverSettings

    seen = []
    monkeypatch.setattr(resolution, "campaign_resolution",
                        lambda ids, p, *a, **k: seen.append(p) or [])
    searched, with_stribeck = np.zeros(3), np.ones(3)
    state = SimpleNamespace(ids=[], p=with_stribeck, p_searched=searched, scales={},
                            model_free_by_stage={}, settings=DiscoverSettings(),
                            accepted=["stribeck_friction:rack"], compensating=lambda: {},
                            timings={}, rounds=[], model=None)
    resolution.resolution_round(state)
    state.p_searched = None
    resolution.resolution_round(state)
    assert seen[0] is searched and seen[1] is with_stribeck


def _envelope_case(spread: float, seed: int = 0, worse: float = 0.01):
    """Per-sample envelope misfits of a stage (base, winner, a one-body look-alike): the
    base leaves 1 a sample; the winner all but what 40 stretches of 50 samples leave; the
    look-alike ``worse`` of the base more on the whole, stretch by stretch that ±
    ``spread``."""
    rng = np.random.default_rng(seed)
    n, stretch = 2000, 50
    winner = rng.uniform(0.0, 0.05, n // stretch)
    jitter = rng.standard_normal(n // stretch)
    rival = np.maximum(winner + worse + spread * (jitter - jitter.mean()), 0.0)
    rival += winner.mean() + worse - rival.mean()  # the look-alike stays the worse
    return np.stack([np.ones(n), np.repeat(winner, stretch), np.repeat(rival, stretch)])


@pytest.mark.parametrize("spread, worse, named_beside", [
    (0.0, 0.6, False), (0.08, 0.01, True), (0.0, 0.01, True)])
def test_a_stick_slip_look_alike_the_resamples_do_not_part_is_named_beside_it(
        monkeypatch, spread, worse, named_beside):
    """Rig 904: a rack Stribeck; the motor's removed 97 % of the envelope misfit, the
    rack's 94 %, and the motor was named alone (the misfits 4.7 and 8.8 units, outside a
    fixed factor of 1.25). A look-alike as good stretch by stretch give or take is named
    beside the winner and the name is at most even odds. One worse everywhere is too
    while it clears the round's margin itself: in one body the two parts differ in the
    model's law of each, not in what the data measure (rig 904 with the levels' split
    held: the motor's 99 %, the rack's 87 %, the motor named alone at 0.99). One worse
    everywhere and under the margin is not."""
    import mbst.discovery.rounds.stickslip as ss
    from mbst.discovery.state import Finding

    costs = _envelope_case(spread, worse=worse)
    env = SimpleNamespace(sample_misfits=lambda ps: costs)
    scores = [StickSlipScore(key=f"stribeck_friction:{c}", effect="stribeck_friction",
                             component=c, stage="free_tie_rods", misfit_base=1.0,
                             misfit=float(costs[i].mean()), params=np.zeros(2))
              for i, c in ((1, "motor"), (2, "rack"))]
    boot = ss.envelope_bootstrap(env, scores, np.zeros(2))
    assert boot["wins_share"] > 0.5  # the motor wins most resamples either way
    finding = Finding(effect="stribeck_friction", component="motor", parameters={},
                      confidence=0.97, evidence="", stage="free_tie_rods",
                      relative_gain=0.97, aic_delta=None, cv={})
    effects = {s.key: SimpleNamespace(effect=s.effect, component=s.component) for s in scores}
    state = SimpleNamespace(model=SimpleNamespace(effects=effects), residuals=[])
    monkeypatch.setattr(ss, "one_body_in_stage", lambda *a: True)
    ss._twins_within_reach(finding, {"bootstrap": boot}, state)
    assert (finding.indistinguishable_from == ["rack"]) is named_beside, boot
    assert (finding.confidence <= ss.EVEN_ODDS) is named_beside


def test_parts_the_base_fit_moved_apart_by_compensating_still_move_as_one_body():
    """Realistic rig 933 (a rack asymmetry beside a torsion-bar stop): the base fit softened
    the worm gear to its bound and put the rack's friction in the motor; motor and rack
    speeds then correlated at 0.9988, under the one-body threshold, and the asymmetry was
    named in the motor alone at 0.67 with the rack not ruled out. At the typical values
    of what the fit compensated with they move as one body, and the twin is named beside
    the winner at most even odds. Parts that move apart at both stay apart."""
    from mbst.discovery.acceptance import EVEN_ODDS, one_body_in_stage
    from mbst.discovery.rounds.catalogue import proposal_finding
    from mbst.discovery.state import Proposal
    from mbst.systems.eps.model import EPS_MODEL

    t = np.linspace(0, 20, 4000)
    w = np.sin(t)
    wobbly = w + 0.05 * np.sin(7.3 * t)  # correlation ~0.9988 with w
    soft = _residual("a", 16.0 / 0.0075 * w, wobbly)
    assert not one_body_in_stage("motor", "rack", "free_tie_rods", [soft], EPS_MODEL)
    soft.typical_speeds = {"motor_speed_rad_per_s": 16.0 / 0.0075 * w,
                           "rack_speed_m_per_s": w + 1e-4 * np.sin(7.3 * t)}
    assert one_body_in_stage("motor", "rack", "free_tie_rods", [soft], EPS_MODEL)
    apart = _residual("a", 16.0 / 0.0075 * w, np.cos(3.3 * t))
    apart.typical_speeds = {"motor_speed_rad_per_s": w, "rack_speed_m_per_s": np.cos(3.3 * t)}
    assert not one_body_in_stage("motor", "rack", "free_tie_rods", [apart], EPS_MODEL)

    best = SimpleNamespace(key="asymmetric_friction:motor", effect="asymmetric_friction",
                           component="motor", stage="free_tie_rods", relative_gain=0.759,
                           aic_delta=-1314.0, n_eff=924.0, tests=["a"], params=None)
    boot = {"confidence": 0.67, "wins_share": 0.85, "explained_above_noise": 0.78,
            "resamples": 400, "gain_5_95_percent": [0.733, 0.785],
            "alternatives": [{"key": "asymmetric_friction:rack", "effect": "asymmetric_friction",
                              "component": "rack", "relative_gain": 0.757,
                              "winner_better_share": 0.85}]}
    for residual, named in ((soft, ["rack"]), (apart, [])):
        state = SimpleNamespace(model=EPS_MODEL, p=EPS_MODEL.default_vector(), regions=[],
                                rounds=[],
                                residuals=[residual])
        f = proposal_finding(Proposal(best, None, {}, 0.5, [], boot), state, None, None)
        assert f.indistinguishable_from == named
        assert f.confidence == (EVEN_ODDS if named else 0.67)


def test_a_stick_slip_confidence_counts_the_share_of_resamples_the_winner_still_wins(
        monkeypatch):
    """The stick-slip name's confidence is its share of the envelope misfit × the share of
    tests it lowers × the share of resampled stretches it still wins: a winner the resamples
    doubt is worth less than its share says; without resamples the share stands."""
    import mbst.discovery.rounds.stickslip as ss

    def record(bootstrap):
        best = StickSlipScore("stribeck_friction:rack", "stribeck_friction", "rack",
                              "free_tie_rods", 100.0, 10.0, np.zeros(1),
                              per_test={"a": (50.0, 5.0), "b": (50.0, 5.0)},
                              bootstrap=bootstrap)
        monkeypatch.setattr(ss, "stick_slip_test",
                            lambda *a, **k: ({"free_tie_rods": 100.0}, [best]))
        return ss._stick_slip_record([], np.zeros(1), set(), [], {}, seed=0)[1]

    boot = {"wins_share": 0.6, "gain_5_95_percent": [0.85, 0.95], "resamples": 400,
            "block_samples": 10, "rivals": []}
    doubted = record(boot)
    assert doubted.confidence == pytest.approx(0.9 * 0.6)
    assert "60 % of 400 resamples" in doubted.evidence
    assert record({}).confidence == pytest.approx(0.9)


def test_the_stick_slip_figure_names_the_parts_the_answer_leaves_open():
    """Rig 904: the round accepted the motor's Stribeck term, the answer is "motor or rack";
    the figure's title says what the answer says, not the key the round put in."""
    from mbst.report.discovery_figures import _stick_slip_verdict

    rec = {"accepted": "stribeck_friction:motor"}
    f = _finding("stribeck_friction", "motor", 0.48)
    f.indistinguishable_from = ["rack"]
    title = _stick_slip_verdict(SimpleNamespace(findings=[f]), rec)
    assert title == "named stribeck_friction in motor or rack, confidence 0.48"
    assert _stick_slip_verdict(SimpleNamespace(findings=[]), rec) == \
        "accepted stribeck_friction:motor"
    assert _stick_slip_verdict(SimpleNamespace(findings=[f]), {"accepted": None}) == "no finding"
    declined = {"accepted": None, "rival_declined": [
        {"key": "stribeck_friction:rack", "rival": "torque_ripple:motor"}]}
    assert _stick_slip_verdict(SimpleNamespace(findings=[]), declined) == \
        "stribeck_friction:rack declined for torque_ripple:motor"


def test_a_stick_slip_name_on_the_edge_of_its_range_says_its_size_is_a_bound(monkeypatch):
    """A name whose fitted size lies on its search bound reports that size as a bound, not a
    measurement; one inside its range does not."""
    import mbst.discovery.rounds.stickslip as ss

    def record(at_bound):
        best = StickSlipScore("stribeck_friction:rack", "stribeck_friction", "rack",
                              "free_tie_rods", 100.0, 10.0, np.zeros(1),
                              per_test={"a": (50.0, 5.0), "b": (50.0, 5.0)},
                              at_bound=list(at_bound))
        monkeypatch.setattr(ss, "stick_slip_test",
                            lambda *a, **k: ({"free_tie_rods": 100.0}, [best]))
        return ss._stick_slip_record([], np.zeros(1), set(), [], {}, seed=0)[1]

    edge = record(["stribeck_velocity"]).evidence
    assert "stribeck_velocity on the edge of its search range" in edge
    assert "a bound, not a measurement" in edge
    assert "on the edge of its search range" not in record([]).evidence


def test_a_stick_slip_a_refitted_ripple_matches_is_not_named(monkeypatch):
    """A 20 mN·m motor cogging shook the drive as a stick-slip: rack Stribeck removed 91 % of
    the envelope misfit, the ripple refitted at the fast residual's order 90 % and 68 % of the
    output error. Within the round's tie of the envelope the output error decides: no name,
    the ripple on the record. A ripple that leaves more of the envelope is stood beside: the
    winner, scored again on what the ripple leaves, keeps its name where it clears the
    round's margin there and loses it where it does not (realistic rig 2601: 7.8 % beside a
    10 mN·m cogging). No ripple at all, or a check that fails (reported), leave the name."""
    import mbst.discovery.rounds.stickslip as ss
    from mbst.systems.eps.model import EPS_MODEL

    lock = SimpleNamespace(order=18)
    score = SimpleNamespace(params=np.ones(1), key="torque_ripple:motor", relative_gain=0.68,
                            aic_delta=-2107.0, headline={"sine_nm": 0.0155, "cosine_nm": 0.0})

    def envelope(gain):
        return type("Env", (), {"__init__": lambda self, *a: None,
                                "tests": [SimpleNamespace(time_s=np.zeros(10))],
                                "misfits": lambda self, ps: np.array([[100.0],
                                                                      [100.0 * (1 - gain)]])})

    def beside(gain):
        def score(env, spec, base, misfit_base):
            assert spec.key == "stribeck_friction:rack" and base is score_params
            assert list(misfit_base) == [100.0 * (1 - 0.80)]  # what the ripple leaves
            return StickSlipScore(spec.key, spec.effect, spec.component, "free_tie_rods",
                                  20.0, 20.0 * (1 - gain), base,
                                  per_test={"a": (10.0, 10.0 * (1 - gain)),
                                            "b": (10.0, 10.0 * (1 - gain))})
        return score

    score_params = score.params

    def run(ripple, gain=0.90, beside_gain=0.6):
        monkeypatch.setattr(ss, "score_candidate", beside(beside_gain))
        finding = _finding("stribeck_friction", "rack", 0.9)
        finding.relative_gain = 0.91
        rec = {"round": 2, "method": "stick_slip", "accepted": "stribeck_friction:rack"}
        monkeypatch.setattr(ss, "_stick_slip_record", lambda *a, **k: (rec, finding, np.ones(1)))
        monkeypatch.setattr(ss, "_split_undecided", lambda *a: None)
        monkeypatch.setattr(ss, "_twins_within_reach", lambda *a: None)
        monkeypatch.setattr(ss, "refit_at_lock", ripple)
        monkeypatch.setattr(ss, "StageEnvelope", envelope(gain))
        state = SimpleNamespace(
            room_for_more=lambda: True, compensating=lambda: {}, ids=[], p=np.zeros(1),
            accepted=[], rounds=[], findings=[], failures=[], timings={},
            settings=SimpleNamespace(identify=SimpleNamespace(seed=0)),
            refit_cost=lambda: None, model=SimpleNamespace(
                stage_tests=lambda s, ids: ids, ripple=EPS_MODEL.ripple,
                effects=EPS_MODEL.effects))
        ss.stick_slip_round(state)
        return state, rec

    state, rec = run(lambda *a, **k: (lock, None, score))
    assert not state.findings and rec["accepted"] is None
    gone = rec["rival_declined"][0]
    assert gone["rival"] == "torque_ripple:motor" and gone["rival_envelope_gain"] == 0.9
    assert "ripple of 15.5 mN·m at the motor, 18 periods per revolution" in gone["reason"]
    # past the tie: the winner beside the ripple decides
    assert run(lambda *a, **k: (lock, None, score), gain=0.80)[0].findings
    state, rec = run(lambda *a, **k: (lock, None, score), gain=0.80, beside_gain=0.078)
    assert not state.findings and rec["accepted"] is None
    assert "beside the ripple it removes 7.8 % of the envelope misfit the ripple leaves" \
        in rec["rival_declined"][0]["reason"]
    assert run(lambda *a, **k: None)[0].findings

    def broken(*a, **k):
        raise FloatingPointError("the ripple's twin diverged")

    state, _ = run(broken)
    assert state.findings and "ripple check" in state.failures[0]


@pytest.mark.parametrize("rack_gain, one_body, accepted, declined, undecided", [
    (0.65, True, None, False, True), (0.30, True, None, False, False),
    (0.65, False, None, False, False), (0.65, True, "stribeck_friction:rack", False, False),
    (0.65, True, None, True, False)])
def test_a_stribeck_name_whose_stage_still_shakes_for_another_part_is_undecided(
        monkeypatch, rack_gain, one_body, accepted, declined, undecided):
    """Realistic rig 1201: a rack Stribeck named in the motor at 0.39 by the output-error
    rounds (the rack's refit stalled on the sawtooth's phase). The stage kept 43.6 units
    of fast-envelope misfit after it, and a rack Stribeck removed 65 % of that: the part is
    undecided, at most even odds. Under the round's margin, or in a part that does not
    move with the named one, where the round named the other part itself (a finding of its
    own), or where a ripple matched the round's winner (the stage shakes with a rotating
    part), the name stands. The check runs where the findings are concluded: the
    output-error names are built there, after the stick-slip round (a check inside the
    round saw none of them, and rig 1201 kept its motor alone)."""
    import mbst.discovery.rounds.stickslip as ss

    finding = _finding("stribeck_friction", "motor", 0.9)
    finding.stage = "free_tie_rods"
    rec = {"round": 5, "method": "stick_slip", "accepted": accepted, "candidates": [
        {"key": "stribeck_friction:rack", "stage": "free_tie_rods", "misfit_base": 43.6,
         "relative_gain": rack_gain, "wins": 1, "tests": 3}]}
    if declined:
        rec["rival_declined"] = [{"key": "stribeck_friction:rack",
                                  "rival": "torque_ripple:motor"}]
    effects = {"stribeck_friction:rack": SimpleNamespace(effect="stribeck_friction",
                                                         component="rack")}
    import mbst.discovery.pipeline as pipeline

    state = SimpleNamespace(rounds=[{"round": 1, "accepted": None}, rec], residuals=[],
                            model=SimpleNamespace(effects=effects), proposals=["round 1"],
                            findings=[], p=np.zeros(1), failures=[])
    monkeypatch.setattr(ss, "one_body_in_stage", lambda *a: one_body)
    monkeypatch.setattr(pipeline, "proposal_finding", lambda *a: finding)
    monkeypatch.setattr(pipeline, "fold_one_body", lambda findings, *a: findings)
    monkeypatch.setattr(pipeline, "state_body_sizes", lambda *a: None)
    assert pipeline._named(state, None, None) == [finding]
    assert (finding.indistinguishable_from == ["rack"]) is undecided
    assert (finding.confidence <= ss.EVEN_ODDS) is undecided
    assert ("still shaking" in finding.evidence) is undecided


def test_a_stick_slip_gain_on_the_controls_is_measured_in_its_envelope_where_fit_falls():
    """A right stick-slip model out of phase scores a lower FIT on a held-out test than the
    smooth base; the report measures it in the envelope too, where it is far better (rig
    2102: control FIT 87.1 → 83.4 % with the rack Stribeck named, the true model 96.5 %)."""
    from mbst.core.metrics import fit_percent
    from mbst.discovery.rounds.stickslip import held_out_envelopes
    from mbst.report.discovery import stick_slip_held_out_lines

    ch = "steering_torque_nm"
    ctrl = _test(_rig(0.0, True, noise_seed=1))
    ctrl.id, ctrl.scenario, ctrl.time_s = "sine_ctrl", "free_tie_rods", np.zeros(4000)
    other = _test(_rig(0.0, False, noise_seed=2))
    other.id, other.scenario, other.time_s = "blocked_ctrl", "blocked_column", np.zeros(4000)
    smooth, shifted = _rig(0.0, False), _rig(0.5, True)
    twins = {"base": {"sine_ctrl": {ch: smooth}, "blocked_ctrl": {ch: smooth}},
             "extended": {"sine_ctrl": {ch: shifted}, "blocked_ctrl": {ch: smooth}},
             "sindy": {"sine_ctrl": {ch: smooth}}}
    model = SimpleNamespace(stage_tests=lambda stage, tests: [t for t in tests
                                                              if t.scenario == stage])
    stick_slip = SimpleNamespace(stage="free_tie_rods", cv={"criterion": "envelope misfit"})
    output_error = SimpleNamespace(stage="blocked_column", cv={"folds": 3})
    meas = ctrl.measured[ch]
    assert fit_percent(meas, shifted) < fit_percent(meas, smooth)
    out = held_out_envelopes([stick_slip, output_error], [ctrl, other], twins, model)
    assert list(out) == ["free_tie_rods"]  # only the stick-slip's stage, only its tests
    row = out["free_tie_rods"]
    assert row["tests"] == ["sine_ctrl"] and "sindy" not in row and "true" not in row
    assert row["base"] > MIN_BASE_MISFIT and row["extended"] < 0.2 * row["base"]
    text = " ".join(stick_slip_held_out_lines(out))
    assert f"base {row['base']:.1f}, extended {row['extended']:.1f}" in text
    assert "does not carry over" not in text
    # an extension that leaves more envelope misfit than the base is said to (rig 2102)
    swapped = {"free_tie_rods": {**row, "base": row["extended"], "extended": row["base"]}}
    assert "the Stribeck size fitted on the identification tests does not carry over" in \
        " ".join(stick_slip_held_out_lines(swapped))
    assert held_out_envelopes([output_error], [ctrl, other], twins, model) == {}
