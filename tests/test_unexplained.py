"""The unexplained round's signature search (discovery/signature.py) on residuals with a
planted structure that no catalogue effect has, and on coloured noise alone."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest

from mbst.core.filtering import exponential_filter
from mbst.core.sensors import coloured_noise
from mbst.discovery.data import TestResidual
from mbst.discovery.signature import describe_channel, learned_term

RATE_HZ = 500.0
TAU_S = 0.005
RATIO = 16.5  # motor turns per steering turn
CH = "steering_torque_nm"


def _test(i: int, amplitude_deg: float, freq_hz: float, seed: int, structure) -> TestResidual:
    """A sine test whose 'measured' torque is the twin plus ``structure`` and AR(1) noise."""
    dt = 1.0 / RATE_HZ
    t = np.arange(0.0, 3.0 / freq_hz, dt)
    angle = np.deg2rad(amplitude_deg) * np.sin(2 * np.pi * freq_hz * t)
    omega = np.gradient(angle, dt)
    motor = RATIO * angle
    clean = 2.0 * np.tanh(omega / 0.05) + 8.0 * angle  # friction plus a spring
    twin = exponential_filter(clean, dt, TAU_S)
    rng = np.random.default_rng([seed, i])
    raw = clean + structure(t, clean, motor) + coloured_noise(len(t), 0.02, 0.9, rng)
    return TestResidual(
        id=f"t{i}", scenario="free_tie_rods", role="identification", motor="off", dt_s=dt,
        time_s=t, angle_rad=angle, omega_rad_per_s=omega,
        measured={CH: exponential_filter(raw, dt, TAU_S)}, simulated={CH: twin},
        states={"motor_angle_rad": motor, "torsion_bar_torque_nm": clean}, tau_s=TAU_S)


def _campaign(structure, seed: int = 0, amplitudes_deg=(20, 30, 15, 40)) -> list[TestResidual]:
    plan = zip(amplitudes_deg, (0.25, 0.5, 0.8, 0.3), strict=True)
    return [_test(i, a, f, seed, structure) for i, (a, f) in enumerate(plan)]


def _lagged(lag_s: float):
    def structure(t, clean, motor):
        return np.interp(t - lag_s, t, clean) - clean
    return structure


def _describe(tests, min_share: float = 0.0):
    places = {t.id: k / max(len(tests) - 1, 1) - 0.5 for k, t in enumerate(tests)}
    return describe_channel(tests, CH, places, noise_rms=0.02 * 0.2,
                            input_name="steering_angle_rad", min_share=min_share)


def test_a_channel_that_lags_the_angle_is_described_as_a_lag_of_its_size():
    sig = _describe(_campaign(_lagged(0.012)))
    assert sig.structured, sig
    assert sig.best.group == f"lag:{CH}"
    assert sig.best.quantities()["lag_s"] == pytest.approx(0.012, rel=0.25)



def test_a_channel_ahead_of_its_twin_is_read_as_a_slow_model_not_a_sensor_delay():
    """A realistic clean rig's tie-rod forces ran 1 ms ahead of the twin: no sensor answers
    before its input, so the reading says the model is the slow one."""
    from mbst.discovery.rounds.unexplained import reading

    sig = _describe(_campaign(_lagged(-0.012)))
    assert sig.structured and sig.best.group == f"lag:{CH}"
    assert sig.best.quantities()["lag_s"] == pytest.approx(-0.012, rel=0.25)
    assert reading(sig).startswith(f"the model lags {CH} by 1")
    assert "sensor's delay" in reading(sig) and "faster than the model" in reading(sig)
    assert "lags the input that drives the model by 1" in reading(
        _describe(_campaign(_lagged(0.012))))


def test_a_slow_model_behind_a_delayed_sensor_names_that_sensor():
    """A 3-ms torque-sensor lag alone left a realistic clean rig's tie-rod forces 0.9 ms ahead
    of the twin (the stages fitted on the delayed torque, the true parameters leaving none):
    the finding led by the slow model names the sensor that reads behind its twin."""
    import dataclasses

    from mbst.discovery.rounds.unexplained import unexplained_finding

    ahead = dataclasses.replace(_describe(_campaign(_lagged(-0.012))),
                                channel="tie_rod_force_left_n")
    behind = _describe(_campaign(_lagged(0.004), seed=3))
    assert behind.above_chance > 0 and behind.best.group == f"lag:{CH}"
    finding = unexplained_finding([ahead], set(), [ahead, behind])
    reading = finding.signature["reading"]
    assert reading.startswith("the model lags tie_rod_force_left_n by 1")
    delay = re.search(rf"{CH} reads ([0-9.]+) ms behind its twin", reading)
    assert delay and float(delay.group(1)) == pytest.approx(4.0, rel=0.25), reading
    assert "delayed sensor" in reading
    assert finding.signature["reading"] in finding.evidence
    # no delayed sensor beside it (or one the model leads): the reading stays as it was
    alone = unexplained_finding([ahead], set(), [ahead])
    assert "delayed sensor" not in alone.signature["reading"]
    leading = dataclasses.replace(ahead, channel=CH)
    assert "delayed sensor" not in unexplained_finding(
        [ahead], set(), [ahead, leading]).signature["reading"]


def test_a_structure_at_one_place_is_not_read_as_a_ripple():
    """A rise at one motor angle (a rack friction at one position, left beside its name)
    is fitted by a low order over the narrow range the tests sweep; its term explains the
    residual on that side of the sweep and nothing on the other: no ripple (rig 911 got "22
    periods per revolution" at 0.68). A ripple of the same size keeps its reading."""
    one_place = _describe(_campaign(
        lambda t, clean, motor: 0.3 * np.exp(-((motor - 3.0) / 0.5) ** 2)))
    assert not one_place.best.group.startswith("periodic:"), one_place.best
    assert "one side of the tests' middle angle" in one_place.not_a_ripple
    from mbst.report.discovery import _verdict

    assert _verdict(one_place, 1.0).endswith("a structure at one place, not a ripple")
    ripple = _describe(_campaign(lambda t, clean, motor: 0.04 * np.sin(18 * motor)))
    assert ripple.best.group == "periodic:motor_angle_rad" and not ripple.not_a_ripple


def _after_each_reversal(size: float, time_s: float = 0.03):
    """A ringing transient after each reversal, in the time since it (a friction's
    transition the model lacks): it repeats with the motion, not with any angle's order."""
    def structure(t, clean, motor):
        direction = np.sign(np.gradient(motor, t))
        since = np.zeros_like(t)
        for k in range(1, len(t)):
            since[k] = 0.0 if direction[k] != direction[k - 1] else since[k - 1] + t[k] - t[k - 1]
        return size * direction * np.exp(-since / time_s) * np.sin(3 * since / time_s)
    return structure


@pytest.mark.parametrize("seed", [0, 1])
def test_a_structure_that_repeats_with_the_motion_is_not_read_as_a_ripple(seed):
    """Tests of one stroke repeat the motion, so every order of the motor angle predicts a
    transient after each reversal a little on held-out tests, which the phase-randomised
    copies do not (rig 1501, an unfitted column presliding: "47 periods per revolution",
    16 % held out, order 31 11 %, at 0.76). With no order standing out from the unrelated
    ones by the margin, it is no ripple; a ripple beside the same transient keeps its
    reading at its order."""
    def describe(structure):
        return _describe(_campaign(structure, seed, amplitudes_deg=(30, 30, 30, 30)),
                         min_share=0.10)

    transient = _after_each_reversal(0.6)
    sig = describe(transient)
    assert not sig.structured and not sig.best.group.startswith("periodic:"), sig
    assert "no one order stands out" in sig.not_a_ripple, sig.not_a_ripple
    ripple = describe(lambda t, clean, motor: transient(t, clean, motor)
                      + 0.05 * np.sin(18 * motor))
    assert ripple.structured and ripple.best.group == "periodic:motor_angle_rad", ripple
    assert ripple.best.harmonic == 18 and not ripple.not_a_ripple


def test_a_ripple_in_motor_angle_is_periodic_in_motor_angle_at_its_order():
    sig = _describe(_campaign(lambda t, clean, motor: 0.15 * np.sin(18 * motor)))
    assert sig.structured, sig
    assert sig.best.group == "periodic:motor_angle_rad"
    assert sig.best.harmonic == 18


def test_a_ripple_under_a_larger_slow_misfit_is_read_in_the_fast_part_at_its_order():
    """A cogging reaches the torque as an oscillation at N times the motor's speed beside
    whatever slow misfit the model leaves (the compact plan's 4 mN·m cogging read "order 1"
    on the whole residual). The whole residual here reads the slow part; its fast part
    (``rounds/ripple.py``) repeats with the motor angle at the ripple's order, and coloured
    noise alone repeats with nothing."""
    from mbst.discovery.rounds.ripple import strongest_lock

    def lock_of(tests):
        places = {t.id: k / (len(tests) - 1) - 0.5 for k, t in enumerate(tests)}
        return strongest_lock(tests, "motor_angle_rad", places, 0, "steering_angle_rad")

    tests = _campaign(lambda t, clean, motor: 0.3 * np.cos(motor / RATIO / 0.35)
                      + 0.02 * np.sin(18 * motor), seed=3)
    assert _describe(tests).best.group.startswith("polynomial:")
    lock = lock_of(tests)
    assert lock is not None and (lock.channel, lock.order) == (CH, 18), lock
    assert lock.signature.best.cv_share > 5 * lock.signature.chance_share
    for seed in range(3):
        assert lock_of(_campaign(lambda t, clean, motor: 0.0 * t, seed=seed)) is None


def test_a_ripple_that_predicts_less_than_the_margin_above_chance_is_not_a_structure():
    """The margin a catalogue effect must clear (10 % of what is left) holds for a
    signature too: a ripple 11 % of the residual (3 % by chance) is seen, and below it."""
    def strict(tests):
        return _describe(tests, min_share=0.10)

    tests = _campaign(lambda t, clean, motor: 0.012 * np.sin(18 * motor), seed=1)
    loose = _describe(tests)
    assert loose.structured and loose.best.group == "periodic:motor_angle_rad"
    sig = strict(tests)
    assert 0 < sig.above_chance < 0.10 and not sig.structured, sig
    assert strict(_campaign(lambda t, clean, motor: 0.05 * np.sin(18 * motor))).structured


def test_coloured_noise_alone_is_at_the_floor():
    for seed in range(3):
        sig = _describe(_campaign(lambda t, clean, motor: 0.0 * t, seed=seed))
        assert not sig.structured, (seed, sig.best, sig.chance_share)


def test_the_learned_term_predicts_a_test_it_was_not_fitted_on():
    tests = _campaign(_lagged(0.012))
    sig = _describe(tests[:3])
    held = tests[3]
    r = held.residual(CH)
    corrected = r - learned_term(held, sig, 0.5, "steering_angle_rad")
    assert np.std(corrected) < 0.5 * np.std(r)


# --------------------------------------------------------------------------------------
# Through the whole discovery: effects the catalogue does not hold, planted on the bench
# --------------------------------------------------------------------------------------
def _blocked_column_plan():
    from mbst.systems.eps.bench import PlannedTest

    sine = lambda a, f, c: {"kind": "sine", "amplitude_deg": a, "frequency_hz": f,  # noqa: E731
                            "cycles": c}
    return [PlannedTest("s1_sine_0p4hz", "blocked_column", sine(6, 0.4, 2)),
            PlannedTest("s1_sine_1hz", "blocked_column", sine(4, 1.0, 4)),
            PlannedTest("s1_sine_1p6hz", "blocked_column", sine(3, 1.6, 5)),
            PlannedTest("s1_sine_0p7hz_ctrl", "blocked_column", sine(5, 0.7, 3),
                        role="control")]


def _outside(tmp_path_factory, plan, **realism):
    from mbst.discovery.pipeline import DiscoverSettings, discover
    from mbst.io.campaign import read_campaign
    from mbst.systems.eps.bench import BenchRecipe, run_bench
    from mbst.systems.eps.realism import BenchRealism

    out = tmp_path_factory.mktemp("outside")
    camp = read_campaign(run_bench(out, BenchRecipe(effects=[], seed=2, plan=plan,
                                                    realism=BenchRealism(**realism))))
    return discover(camp, DiscoverSettings(max_effects=2, sparse=False, neural=False,
                                           resolution=False))


def _check_outside(result, kind: str, quantity: str) -> dict:
    """No confident catalogue name; an unexplained finding with the right signature, whose
    physics + learned correction beats the base on the held-out controls."""
    named = [f for f in result.findings if f.effect != "unexplained"]
    assert all(f.confidence < 0.5 for f in named), [(f.effect, f.confidence) for f in named]
    found = [f for f in result.findings if f.effect == "unexplained"]
    assert found, [(s.channel, s.best, s.chance_share) for s in result.signatures]
    sig = found[0].signature
    assert (sig["kind"], sig["quantity"]) == (kind, quantity), found[0].evidence
    means = result.comparison.groupby("model")["fit_percent"].mean()
    assert means["physics+learned"] > means["base"]
    assert sig["control_fit_gain_percent"] == pytest.approx(
        means["physics+learned"] - means["extended"], abs=1e-2)
    return sig


def test_a_torque_sensor_lag_is_described_not_named(tmp_path_factory):
    result = _outside(tmp_path_factory, _blocked_column_plan(), torque_lag_s=0.012)
    sizes = _check_outside(result, "lag", "steering_torque_nm")
    assert 0.004 < sizes["lag_s"] < 0.02


def test_the_unexplained_round_is_silent_on_a_clean_rig(tmp_path_factory):
    result = _outside(tmp_path_factory, _blocked_column_plan())
    assert not result.findings, [f.evidence for f in result.findings]
    assert result.signatures and not any(s.structured for s in result.signatures)


@pytest.mark.slow  # ~2.5 min
def test_friction_that_drifts_over_the_campaign_is_described_not_named(tmp_path_factory):
    """Coulomb levels falling 30 % as the rig warms (bench time constant 5 min) had a
    position-dependent rack friction named at 0.30 (22.5 % of the free-tie-rods stage;
    seed 1, 2026-11-27), and the generic library's drift group stayed under the noise floor.
    The drift of the levels over the running order, refitted as a rival, removes 76 %: an
    unexplained drift with its size, levels falling from the first test to the last."""
    from mbst.systems.eps.bench import compact_plan

    result = _outside(tmp_path_factory, compact_plan(), friction_drift=0.3)
    sig = _check_outside(result, "drift", "time")
    assert -0.3 < sig["change"] < -0.05, sig


@pytest.mark.slow
def test_motor_cogging_is_described_not_named(tmp_path_factory):
    """A 4 mN·m cogging read "periodic in motor angle, order 1" on the whole residual, its
    learned term below the base on the controls (99.00 against 99.18 %, seed 1); the fast
    residual reads the order, and the ripple refitted at it is the finding's size."""
    from mbst.systems.eps.bench import compact_plan

    result = _outside(tmp_path_factory, compact_plan(), cogging_nm=0.004)
    sig = _check_outside(result, "periodic", "motor_angle_rad")
    assert sig["refitted"] == "physics" and sig["periods_per_rev"] == 18, sig
    assert 0.002 < sig["amplitude"] < 0.008, sig


@pytest.mark.slow
def test_a_cogging_that_shakes_the_drive_is_not_named_stick_slip(tmp_path_factory):
    """A 20 mN·m cogging shakes the free-tie-rods rig as a stick-slip does: rack Stribeck
    friction was named by the envelope (91 % of its misfit; seed 1), its extension lowering
    the control FIT 97.8 → 96.3 %. The ripple refitted at the order the fast residual
    repeats with matches the envelope within the round's tie and clears the output-error
    margins, which a stick-slip cannot: no Stribeck name, the ripple described."""
    from mbst.systems.eps.bench import compact_plan

    result = _outside(tmp_path_factory, compact_plan(), cogging_nm=0.02)
    assert not [f for f in result.findings if f.effect != "unexplained"], result.findings
    sig = _check_outside(result, "periodic", "motor_angle_rad")
    assert sig["periods_per_rev"] == 18 and 0.01 < sig["amplitude"] < 0.03, sig


@pytest.mark.slow  # ~5 min
def test_a_cogging_beside_a_backlash_is_not_named_stick_slip(tmp_path_factory):
    """Realistic rig 2601 (drawn rig and sizes, coloured noise, a torque lag): a worm-gear
    backlash and a 10 mN·m cogging at 18 per revolution. The backlash was named; then rack
    Stribeck friction at 0.46, from 70 % of the fast envelope's misfit. The ripple at the
    order the fast residual reads (9) removed 59 % of it, past the round's tie, but beside
    that ripple the Stribeck removes 7.8 % of what is left: no Stribeck name, the ripple
    described in motor angle."""
    from mbst.discovery.pipeline import DiscoverSettings, discover
    from mbst.io.campaign import read_campaign
    from mbst.systems.eps.bench import BenchRecipe, compact_plan, run_bench
    from mbst.systems.eps.realism import BenchRealism

    out = tmp_path_factory.mktemp("rig2601")
    recipe = BenchRecipe(effects=["backlash:worm_gear"], seed=2601, plan=compact_plan(),
                         realism=BenchRealism.realistic(cogging_nm=0.01))
    camp = read_campaign(run_bench(out, recipe))
    truth = json.loads((out / "truth.json").read_text())
    result = discover(camp, DiscoverSettings(sparse=False, neural=False, resolution=False))
    first = result.findings[0]
    assert (first.effect, first.component) == ("backlash", "worm_gear"), first.evidence
    assert first.parameters["width_rad"] == pytest.approx(
        truth["effects"][0]["parameters"]["width_rad"], rel=0.2)
    assert not [f for f in result.findings if f.effect == "stribeck_friction"], \
        [f.evidence for f in result.findings]
    stick = next(r for r in result.rounds if r.get("method") == "stick_slip")
    assert "beside the ripple it removes" in stick["rival_declined"][0]["reason"], stick
    found = [f for f in result.findings if f.effect == "unexplained"]
    assert found and found[0].signature["quantity"] == "motor_angle_rad", \
        [f.evidence for f in result.findings]


@pytest.mark.slow  # ~1.5 min
def test_a_drift_no_winner_came_near_is_described(tmp_path_factory):
    """Realistic rig 2507 (drawn rig, coloured noise, a torque lag): the Coulomb levels fall
    30 % as the rig warms up, and nothing else. No catalogue candidate cleared the margin
    (best 6.9 %), so no round set the drift beside a winner, and the generic library's
    level per cut-out did not clear its chance: no finding at all. Screened at the extended
    model in each stage, the drift removes 37 % of the free tie-rods: an unexplained drift,
    levels falling from the first test to the last; no catalogue name."""
    from mbst.discovery.pipeline import DiscoverSettings, discover
    from mbst.io.campaign import read_campaign
    from mbst.systems.eps.bench import BenchRecipe, compact_plan, run_bench
    from mbst.systems.eps.realism import BenchRealism

    out = tmp_path_factory.mktemp("rig2507")
    recipe = BenchRecipe(effects=[], seed=2507, plan=compact_plan(),
                         realism=BenchRealism.realistic(friction_drift=0.3))
    result = discover(read_campaign(run_bench(out, recipe)),
                      DiscoverSettings(sparse=False, neural=False, resolution=False))
    assert not [f for f in result.findings if f.effect != "unexplained"], \
        [f.evidence for f in result.findings]
    drift = [f for f in result.findings if (f.signature or {}).get("kind") == "drift"]
    assert drift and drift[0].signature["quantity"] == "time", \
        [f.evidence for f in result.findings]
    assert -0.3 < drift[0].signature["change"] < -0.05, drift[0].signature
    means = result.comparison.groupby("model")["fit_percent"].mean()
    assert means["physics+learned"] > means["base"], means


def test_one_long_test_is_cut_into_stretches_for_its_held_out_folds():
    """EMPS has one identification run: contiguous stretches stand in for held-out tests."""
    one = [_test(0, 25, 0.3, 5, _lagged(0.010))]
    sig = _describe(one + [])  # a single test
    assert sig is not None and sig.structured
    assert sig.best.group == f"lag:{CH}"


def test_a_lag_read_downstream_is_refitted_as_a_sensors_lag_first(monkeypatch):
    """A 3-ms torque-sensor lag on a clean realistic rig (powered compact plan, seed 1302)
    declined no catalogue winner, and the finding read "the model lags tie_rod_force_left_n
    by 1.2 ms: the rig answers faster than the model ... not a sensor's delay" (0.80). Where
    the library reads a lag, the family's sensor lags are refitted as physics first
    (``lag_findings``), and what is left is read after them; where a declined rival already
    refitted a lag, or nothing reads as a lag, no lag is refitted."""
    import dataclasses
    from types import SimpleNamespace

    import mbst.discovery.rounds.unexplained as unexplained_mod
    from mbst.discovery.state import Finding

    ahead = dataclasses.replace(_describe(_campaign(_lagged(-0.012))),
                                channel="tie_rod_force_left_n")
    ripple = _describe(_campaign(lambda t, clean, motor: 0.1 * np.sin(18 * motor)))
    assert ahead.structured and ripple.structured and ripple.best.group.startswith("periodic")
    lag = Finding(effect="unexplained", component="", parameters={}, confidence=0.3,
                  evidence="a 2.8 ms lag", stage="tires_on_ground", relative_gain=0.29,
                  aic_delta=-67.0, cv={}, signature={"kind": "lag"})
    p0, p1 = np.zeros(2), np.ones(2)

    def run(first, rivals=()):
        calls, reads = [], {id(p0): first, id(p1): []}
        monkeypatch.setattr(unexplained_mod, "rival_findings", lambda state: (list(rivals), None))
        monkeypatch.setattr(unexplained_mod, "ripple_findings", lambda state, p: ([], None))
        monkeypatch.setattr(unexplained_mod, "drift_findings", lambda state, p: ([], None))
        monkeypatch.setattr(unexplained_mod, "_signatures",
                            lambda state, p, keep=True: reads[id(p)])
        monkeypatch.setattr(unexplained_mod, "lag_scores", lambda state, p: [("scored at", p)])
        monkeypatch.setattr(unexplained_mod, "lag_findings",
                            lambda state, scores, said: calls.append((scores[0][1], said))
                            or ([lag], p1))
        state = SimpleNamespace(p=p0, findings=[], signatures=None, rival_physics=None, rounds=[],
                                model=SimpleNamespace(param_specs=[]),
                                measure_floors=lambda why: None)
        unexplained_mod._describe(state)
        return state, calls

    state, calls = run([ahead])
    assert len(calls) == 1 and calls[0][0] is p0
    assert re.match(r"tie_rod_force_left_n reads -1[0-3]\.\d ms against its twin", calls[0][1])
    # the lag's physics is what the controls score, and nothing is left to describe
    assert state.findings == [lag] and state.rival_physics is p1 and state.signatures == []
    # a lag a declined rival refitted already, or a reading that is no lag: none refitted
    state, calls = run([ahead], rivals=[lag])
    assert calls == [] and [f.signature["kind"] for f in state.findings] == ["lag", "lag"]
    state, calls = run([ripple])
    assert calls == [] and [f.signature["kind"] for f in state.findings] == ["periodic"]


def test_a_lag_no_stage_clears_is_said_where_the_cascade_takes_the_reading(monkeypatch):
    """A clean realistic rig on the demo plan (seed 1216: a 3 ms torque-sensor lag, known
    values 15 % off) read "the model lags the tie-rod forces by 1.2 ms ... not a sensor's
    delay" (0.77): the torque lag removed 2.4 / 4.6 / 5.1 % of each stage, under the
    margin. Carried through the cascade it passed the campaign's likelihood-ratio test and
    left no reading. Such a lag is the finding where a lag reading vanishes with it and
    none appears; of several, the one that leaves the least structure."""
    import dataclasses
    from types import SimpleNamespace

    import mbst.discovery.rounds.unexplained as unexplained_mod
    from mbst.discovery.rounds.rival_findings import CascadeLag
    from mbst.discovery.structure import CandidateScore

    ahead = dataclasses.replace(_describe(_campaign(_lagged(-0.012))),
                                channel="tie_rod_force_left_n")
    torque = dataclasses.replace(ahead, channel="steering_torque_nm")
    quiet = [dataclasses.replace(s, chance_share=1.0) for s in (torque, ahead)]  # at chance
    ripple = dataclasses.replace(_describe(_campaign(
        lambda t, clean, motor: 0.1 * np.sin(18 * motor))), channel="rack_position_m")
    assert ahead.structured and ripple.structured
    p0, p1, p2, p3 = (np.full(2, v) for v in (0.0, 1.0, 2.0, 3.0))

    def trial(p, lag_s):
        score = CandidateScore(
            key="sensor_lag:steering_torque_nm", effect="sensor_lag",
            component="steering_torque_nm", stage="free_tie_rods", tests=[], free=["lag"],
            k_effect=1, cost_base=1.0, cost=0.954, n_eff=100.0, aic_delta=-3.0, params=p)
        return CascadeLag(score, p, 0.947, 1.0, -23.0, lag_s)

    def run(trials, reads):
        reads = {id(p0): [torque, ahead], **reads}
        monkeypatch.setattr(unexplained_mod, "rival_findings", lambda state: ([], None))
        monkeypatch.setattr(unexplained_mod, "ripple_findings", lambda state, p: ([], None))
        monkeypatch.setattr(unexplained_mod, "drift_findings", lambda state, p: ([], None))
        monkeypatch.setattr(unexplained_mod, "_signatures",
                            lambda state, p, keep=True: reads[id(p)])
        monkeypatch.setattr(unexplained_mod, "lag_scores",
                            lambda state, p: [(None, trial(p0, 0.003).score)])
        monkeypatch.setattr(unexplained_mod, "lag_findings", lambda state, scores, said: ([], None))
        monkeypatch.setattr(unexplained_mod, "lags_through_cascade",
                            lambda state, p, scores: trials)
        state = SimpleNamespace(p=p0, findings=[], signatures=None, rival_physics=None, rounds=[],
                                model=SimpleNamespace(param_specs=[]),
                                measure_floors=lambda why: None)
        unexplained_mod._describe(state)
        return state

    # the torque reading goes with both; the tie rods' only with the second
    state = run([trial(p1, 0.0022), trial(p2, 0.00305)],
                {id(p1): [quiet[0], ahead], id(p2): quiet})
    assert [f.signature["kind"] for f in state.findings] == ["lag"]
    lag = state.findings[0]
    assert lag.signature["lag_s"] == 0.00305 and lag.signature["through"] == "cascade"
    assert "3.1 ms lag of the steering_torque_nm sensor" in lag.evidence
    assert state.rival_physics is p2 and state.signatures == quiet
    assert lag.confidence == pytest.approx(unexplained_mod.signature_confidence(ahead))
    # a reading appears (the ripple), or none goes: the lag is not the finding, and the
    # reading says its sensor's lag was tried (no "check that sensor's filter" hint)
    for after in ([quiet[0], quiet[1], ripple], [torque, ahead]):
        state = run([trial(p3, 0.003)], {id(p3): after})
        assert state.rival_physics is None
        assert [f.signature["kind"] for f in state.findings] == ["lag"]  # the reading's own
        assert "through" not in state.findings[0].signature
        assert ("lag of each declared sensor (steering_torque_nm), refitted in every stage "
                "and carried through the cascade, does not take it") in state.findings[0].evidence
    # a channel reading behind its twin is no suspect once its sensor's lag took nothing
    behind = dataclasses.replace(_describe(_campaign(_lagged(0.004))),
                                 channel="steering_torque_nm")
    assert behind.best.quantities()["lag_s"] > 0 and behind.above_chance > 0
    state = run([trial(p3, 0.003)], {id(p0): [behind, ahead], id(p3): [behind, ahead]})
    assert "does not take it" in state.findings[0].evidence
    assert "delayed sensor there" not in state.findings[0].evidence


def test_structure_left_beside_stated_values_that_matched_a_winner_says_to_check_them(
        monkeypatch):
    """Known values 15 % off, no sensor lag (demo plan, seed 1216): round 1 declined a rack
    presliding because the stated values, let move, took 41.6 % of its stage, and the
    finding then read only "the model lags the tie-rod forces by 0.8 ms" (0.70). The
    finding now ends with the strongest such decline: check the stated values."""
    from types import SimpleNamespace

    import mbst.discovery.rounds.unexplained as unexplained_mod

    def gone(rival, share, reason):
        return {"rival": rival, "rival_relative_gain": share, "reason": reason}

    rounds = [{"round": 1, "rival_declined": [
        gone("stated_values:campaign", 0.416, "the wheel mass 64.2 → 73.8 (+15 %)"),
        gone("sensor_lag:steering_torque_nm", 0.6, "a lag")]},
        {"round": 2, "rival_declined": [gone("stated_values:campaign", 0.2, "smaller")]}]
    note = unexplained_mod.stated_values_note(rounds)
    assert "stated known values may carry it" in note and "wheel mass 64.2 → 73.8" in note
    assert unexplained_mod.stated_values_note([rounds[0] | {"rival_declined": [
        gone("sensor_lag:steering_torque_nm", 0.6, "a lag")]}]) == ""
    ripple = _describe(_campaign(lambda t, clean, motor: 0.1 * np.sin(18 * motor)))
    monkeypatch.setattr(unexplained_mod, "rival_findings", lambda state: ([], None))
    monkeypatch.setattr(unexplained_mod, "ripple_findings", lambda state, p: ([], None))
    monkeypatch.setattr(unexplained_mod, "drift_findings", lambda state, p: ([], None))
    monkeypatch.setattr(unexplained_mod, "_signatures", lambda state, p, keep=True: [ripple])
    state = SimpleNamespace(p=np.zeros(2), findings=[], signatures=None, rival_physics=None,
                            rounds=rounds, model=SimpleNamespace(param_specs=[]),
                            measure_floors=lambda why: None)
    unexplained_mod._describe(state)
    assert [f.effect for f in state.findings] == ["unexplained"]
    assert state.findings[0].evidence.endswith(note)


@pytest.mark.slow  # ~8 min
def test_a_sensor_lag_that_declined_no_winner_is_said_as_the_sensors(tmp_path_factory):
    """The powered compact plan, a clean realistic rig (seed 1302: drawn parameters, known
    values off, AR(1) noise, a 3 ms torque-sensor lag): no catalogue winner comes near the
    margins, so no round refits the lag, and the tie-rod forces read the model 1.2 ms slow
    (0.80, "not a sensor's delay"). The torque sensor's lag refitted as physics takes it:
    the one finding is that lag, at its size (2.8 ms)."""
    from mbst.discovery.pipeline import DiscoverSettings, discover
    from mbst.io.campaign import read_campaign
    from mbst.systems.eps.bench import BenchRecipe, compact_assist_plan, run_bench
    from mbst.systems.eps.realism import BenchRealism

    out = tmp_path_factory.mktemp("powered_lag")
    camp = read_campaign(run_bench(out, BenchRecipe(
        effects=[], seed=1302, plan=compact_assist_plan(), realism=BenchRealism.realistic())))
    result = discover(camp, DiscoverSettings(sparse=False, neural=False, resolution=False))
    assert [f.effect for f in result.findings] == ["unexplained"], result.findings
    sig = result.findings[0].signature
    assert (sig["kind"], sig["quantity"]) == ("lag", "steering_torque_nm"), sig
    assert 0.0015 < sig["lag_s"] < 0.0045, sig
    assert not any(s.structured for s in result.signatures)


@pytest.mark.slow
def test_a_variable_ratio_rack_is_described_not_named(tmp_path_factory):
    from mbst.systems.eps.bench import compact_plan

    result = _outside(tmp_path_factory, compact_plan(), rack_ratio_variation=0.2)
    named = [f for f in result.findings if f.effect != "unexplained"]
    assert all(f.confidence < 0.5 for f in named), [(f.effect, f.confidence) for f in named]
    found = [f for f in result.findings if f.effect == "unexplained"]
    assert found and found[0].signature["kind"] == "polynomial", result.findings


def test_a_catalogue_name_that_an_outside_signature_rivals_is_put_in_doubt():
    """judge_catalogue_names: a lag left in the torque rivals a name that removed less of
    the base residual than the lag predicts (capped below ½); one that removed more stays,
    partly explained; a name on a stage whose channels hold nothing left is confirmed."""
    from types import SimpleNamespace

    from mbst.discovery.rounds.unexplained import DOUBTED_CONFIDENCE, judge_catalogue_names
    from mbst.discovery.state import Finding

    lagged = _campaign(_lagged(0.012))
    clean = _campaign(lambda t, clean, motor: 0.0 * t)
    places = {t.id: k / (len(lagged) - 1) - 0.5 for k, t in enumerate(lagged)}

    def finding(gain: float, stage: str = "free_tie_rods") -> Finding:
        return Finding("presliding_hysteresis", "motor", {}, 0.9, "structure test", stage,
                       gain, -50.0, {})

    def state(residuals):
        sig = describe_channel(residuals, CH, places, 0.02 * 0.2,
                               input_name="steering_angle_rad")
        return SimpleNamespace(
            signatures=[sig], residuals=residuals, extended_residuals=residuals,
            campaign=SimpleNamespace(tests=residuals), settings=SimpleNamespace(
                identify=SimpleNamespace(seed=0)),
            model=SimpleNamespace(name="eps-column-assist"))

    rivalled, stronger = finding(0.2), finding(0.999)
    judge_catalogue_names([rivalled, stronger], state(lagged))
    assert rivalled.confirmation == "in doubt" and rivalled.confidence == DOUBTED_CONFIDENCE
    assert "IN DOUBT" in rivalled.evidence and "lag:" in rivalled.evidence
    assert stronger.confirmation == "partly explained" and stronger.confidence == 0.9
    alone = finding(0.2)
    judge_catalogue_names([alone], state(clean))
    assert alone.confirmation == "confirmed" and alone.confidence == 0.9


def test_a_phase_free_name_is_in_doubt_when_what_it_matched_repeats_with_the_motion():
    """A name from the stick-slip envelope (no output-error criterion, ``aic_delta`` None)
    whose extension leaves its stage's output error larger is in doubt when the base
    model's fast residual is locked to the motion (a 20 mN·m motor cogging was rack
    Stribeck at 0.90), and kept when it repeats from no test to the next, as a stick-slip's
    sawtooth, whose break-aways hang on the noise (realistic rig 202's true rack Stribeck
    was doubted to 0.45 without this). An extension that fits better is kept either way."""
    from types import SimpleNamespace

    from mbst.discovery.rounds.unexplained import DOUBTED_CONFIDENCE, judge_catalogue_names
    from mbst.discovery.state import Finding

    locked = _campaign(lambda t, clean, motor: 0.08 * np.sin(18 * motor))
    rng = np.random.default_rng(5)
    phases = iter(rng.uniform(0, 2 * np.pi, 8))
    # a fast oscillation whose phase is new in every test: nothing in the motion predicts it
    unlocked = _campaign(lambda t, clean, motor: 0.08 * np.sin(2 * np.pi * 9.0 * t
                                                                + next(phases)))
    worse = _campaign(lambda t, clean, motor: 0.3 * np.sin(2 * np.pi * 9.0 * t))
    places = {t.id: k / (len(locked) - 1) - 0.5 for k, t in enumerate(locked)}
    quiet = describe_channel(_campaign(lambda t, clean, motor: 0.0 * t), CH, places,
                             0.02 * 0.2, input_name="steering_angle_rad")
    assert not quiet.structured

    def judged(base, extended) -> Finding:
        f = Finding("stribeck_friction", "rack", {}, 0.9, "stick-slip envelope",
                    "free_tie_rods", 0.9, None, {})
        judge_catalogue_names([f], SimpleNamespace(
            signatures=[quiet], residuals=base, extended_residuals=extended,
            scales={CH: 1.0}, campaign=SimpleNamespace(tests=base), settings=SimpleNamespace(
                identify=SimpleNamespace(seed=0)),
            model=SimpleNamespace(name="eps-column-assist")))
        return f

    doubted = judged(locked, worse)
    assert doubted.confirmation == "in doubt" and doubted.confidence == DOUBTED_CONFIDENCE
    assert "phase-free" in doubted.evidence and "order 18 of motor_angle_rad" in doubted.evidence
    stick_slip = judged(unlocked, worse)
    assert stick_slip.confirmation == "confirmed" and stick_slip.confidence == 0.9
    assert "follows nothing in the motion" in stick_slip.evidence
    better = judged(worse, locked)
    assert better.confirmation == "confirmed" and better.confidence == 0.9


def test_the_input_noise_floor_is_what_the_true_model_leaves(tmp_path):
    """The model is driven by the measured steering angle, the rig by the true one: that
    noise through the model is part of every residual. On a campaign that logs the motor
    angle it is 2–5× (at least 1.5×) the motor angle sensor's own noise (× the worm-gear ratio), and a
    ripple of 1.1× the sensor noise was taken for structure (confidence 0.95)."""
    from mbst.identify.fitting import input_noise_floors, prepare_test, simulate_twin
    from mbst.io.campaign import read_campaign
    from mbst.systems.eps.bench import DEFAULT_SENSORS, BenchRecipe, compact_plan, run_bench

    recipe = BenchRecipe(effects=[], seed=1, plan=compact_plan()[2:4],
                         sensors=(*DEFAULT_SENSORS, "motor_angle_rad"))
    camp = read_campaign(run_bench(tmp_path, recipe))
    p = recipe.true_params()
    tests = [prepare_test(camp, s, 0.005) for s in camp.identification_tests()]
    input_noise_floors({t.id: camp.frame(t.id) for t in tests}, tests, p, "steering_angle_rad")
    for pt in tests:
        ch = "motor_angle_rad"
        left = float(np.std(pt.measured[ch] - simulate_twin(pt, p)[ch]))
        assert pt.input_floor[ch] > 1.5 * pt.noise[ch]
        assert pt.floor(ch) == pytest.approx(left, rel=0.35)


@pytest.mark.slow  # ~3 min
def test_a_clean_campaign_that_logs_the_motor_angle_gives_no_finding(tmp_path_factory):
    from mbst.discovery.pipeline import DiscoverSettings, discover
    from mbst.io.campaign import read_campaign
    from mbst.systems.eps.bench import DEFAULT_SENSORS, BenchRecipe, compact_plan, run_bench

    out = tmp_path_factory.mktemp("clean_motor_angle")
    camp = read_campaign(run_bench(out, BenchRecipe(
        effects=[], seed=1, plan=compact_plan(), sensors=(*DEFAULT_SENSORS, "motor_angle_rad"))))
    result = discover(camp, DiscoverSettings(neural=False, sparse=False))
    assert not [f for f in result.findings if f.effect == "unexplained"], \
        [f.evidence for f in result.findings]


def test_a_law_read_beside_a_stiffness_on_its_bound_says_so():
    """Realistic rigs 2402 (a motor cogging) and 2406 (a torque lag) read "rack position
    follows a polynomial in torsion-bar torque" at 0.66 and 0.69 beside the worm-gear
    stiffness on its lower bound, a compliance standing in for what the rig did. The
    finding says so; a stiffness inside its range, or a reading that is no law in a
    measured quantity, adds nothing."""
    from types import SimpleNamespace

    from mbst.discovery.rounds.unexplained import stiffness_on_bound_note
    from mbst.systems.eps.model import EPS_MODEL

    name = "worm_gear.stiffness_nm_per_rad"
    p = EPS_MODEL.vector_from({name: EPS_MODEL.spec(name).lower})
    state = SimpleNamespace(model=EPS_MODEL, p=p,
                            base=SimpleNamespace(preid={"upper": {}}, params=p),
                            model_free=lambda stage: [name, "rack.coulomb_n"])
    law = SimpleNamespace(best=SimpleNamespace(group="polynomial:torsion_bar_torque_nm",
                                               scenarios=("free_tie_rods",)))
    note = stiffness_on_bound_note(state, [law])
    assert f"{name} on its lower bound (1000 N·m/rad)" in note
    assert "a compliance the fit compensates with" in note
    ripple = SimpleNamespace(best=SimpleNamespace(group="periodic:motor_angle_rad",
                                                  scenarios=("free_tie_rods",)))
    assert stiffness_on_bound_note(state, [ripple]) == ""
    state.p = EPS_MODEL.vector_from({name: 8000.0})
    assert stiffness_on_bound_note(state, [law]) == ""
