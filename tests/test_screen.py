"""The linearised screen that picks what a later structure round rescores (rounds/screen.py).

An effect masked by a larger one shows only once that one is in; the screen must see it
against the model as it stands, and see nothing on a campaign that lacks it.
"""

from __future__ import annotations

from types import SimpleNamespace

import pytest

from mbst.discovery.acceptance import EVIDENCE_SHARE_OF_MARGIN
from mbst.discovery.rounds import catalogue
from mbst.discovery.rounds.screen import ScreenScore, screen_stage
from mbst.discovery.state import DiscoverSettings
from mbst.discovery.structure import CandidateScore, StageScorer
from mbst.identify.fitting import channel_scales, prepare_test
from mbst.io.campaign import read_campaign
from mbst.report.discovery import screened_out_lines
from mbst.systems.eps.bench import BenchRecipe, compact_plan, run_bench
from mbst.systems.eps.model import EPS_MODEL

STAGE = "free_tie_rods"
EVIDENCE = EVIDENCE_SHARE_OF_MARGIN * 0.10


def _stage(tmp_path, effects: list[str]) -> tuple[StageScorer, list]:
    """The compact plan's free tie-rods stage at the true rig with ``effects`` off: the
    base model a fit would start from, refitted as a round's base."""
    recipe = BenchRecipe(effects=effects, seed=3, plan=compact_plan())
    camp = read_campaign(run_bench(tmp_path, recipe))
    tests = [prepare_test(camp, s, 0.005) for s in camp.identification_tests()
             if s.scenario == STAGE]
    p = recipe.true_params()
    for key in effects:
        for n in EPS_MODEL.effects[key].free:
            p[EPS_MODEL.param_index[n]] = EPS_MODEL.spec(n).default
    scorer = StageScorer(tests, STAGE, p, channel_scales(tests))
    specs = [s for s in EPS_MODEL.catalogue if s.component in ("rack", "motor", "worm_gear")
             and s.key != "stribeck_friction:motor"]
    return scorer, screen_stage(scorer, specs, scorer.base_refit()[0])


@pytest.mark.parametrize("effects", [
    # ~14 s each; CI keeps the screen's clean rig and its later round, and the pipeline's
    # demo (the structure test's own positive case)
    pytest.param(["asymmetric_friction:rack"], marks=pytest.mark.slow),
    pytest.param(["position_dependent_friction:rack"], marks=pytest.mark.slow)])
def test_the_screen_sees_an_effect_the_model_lacks(tmp_path, effects):
    scorer, screened = _stage(tmp_path, effects)
    gain = {s.key: s.predicted_gain for s in screened}
    planted = effects[0]
    assert gain[planted] > 0.3, gain
    # the motor is one body with the rack here: its asymmetry is the rack's look-alike
    others = {k: g for k, g in gain.items() if k.split(":")[0] != planted.split(":")[0]}
    assert max(others.values()) < gain[planted] / 2, gain


def test_the_screen_sees_nothing_on_a_rig_without_an_effect(tmp_path):
    _, screened = _stage(tmp_path, [])
    assert max(s.predicted_gain for s in screened) < EVIDENCE, screened


def test_the_next_round_rescores_what_the_screen_passes_not_what_showed_evidence(monkeypatch):
    """The old rule rescored only what showed evidence in the round before; a masked effect
    never had. The screen's verdict decides both ways."""
    def score(key: str, gain: float) -> CandidateScore:
        effect, component = key.split(":")
        return CandidateScore(key, effect, component, STAGE, [], [], 1, 1.0, 1.0 - gain,
                              1000.0, -50.0, params=None)

    last = [score("backlash:worm_gear", 0.9), score("presliding_hysteresis:motor", 0.6)]
    verdict = [ScreenScore("position_dependent_friction:rack", STAGE, 0.4, {}),
               ScreenScore("presliding_hysteresis:motor", STAGE, 0.001, {}),
               ScreenScore("asymmetric_friction:rack", STAGE, EVIDENCE * 0.9, {})]
    monkeypatch.setattr(catalogue, "screen", lambda state, scores, make, scorers: verdict)

    state = SimpleNamespace(settings=DiscoverSettings(), failures=[])
    rec = {"round": 1}
    nxt = catalogue._next_candidates(state, last, rec)
    assert nxt.shortlist == {"position_dependent_friction:rack"}
    assert rec["screen"]["predicted_gain"]["presliding_hysteresis:motor"] == 0.001


def test_the_first_round_refits_what_the_screen_puts_above_a_tenth_of_the_margin(monkeypatch):
    """The first round's screen spares the refits of candidates predicted to remove almost
    nothing; it asks a fifth of the later rounds' share, as the first-order estimate
    undershoots most against a base that lacks the effect. A screen that fails costs the
    saving only: every candidate is refitted, and the failure is said."""
    needed = catalogue.FIRST_ROUND_SHARE_OF_MARGIN * 0.10
    verdict = [ScreenScore("backlash:worm_gear", STAGE, 0.9, {}),
               ScreenScore("stribeck_friction:rack", STAGE, needed * 1.1, {}),
               ScreenScore("power_law_damping:motor", STAGE, needed * 0.9, {})]
    monkeypatch.setattr(catalogue, "screen", lambda state, scores, make, scorers: verdict)
    state = SimpleNamespace(settings=DiscoverSettings(), failures=[])
    nxt, record = catalogue._first_round(state)
    assert nxt.shortlist == {"backlash:worm_gear", "stribeck_friction:rack"}
    assert record["needed"] == pytest.approx(needed)
    assert record["predicted_gain"]["power_law_damping:motor"] == round(needed * 0.9, 5)
    rnd = {"round": 1, "shortlist_screen": record,
           "candidates": [{"key": "backlash:worm_gear"}, {"key": "stribeck_friction:rack"}]}
    line = " ".join(screened_out_lines([rnd]))
    assert "refitted 2 of 3 candidates" in line and "power_law_damping:motor" in line
    # a first round the screen leaves nothing to refit is at the catalogue's noise floor
    assert "noise floor" in catalogue._nothing_to_refit(set(), record)
    assert "can act" in catalogue._nothing_to_refit(set(), {**record, "predicted_gain": {}})

    def broken(state, scores, make, scorers):
        raise FloatingPointError("a stage twin diverged")

    monkeypatch.setattr(catalogue, "screen", broken)
    assert catalogue._first_round(state) == (None, None)
    assert "round 1 screen: FloatingPointError" in state.failures[-1]


def test_the_first_rounds_shortlist_and_its_scorers_reach_the_refits(monkeypatch):
    """The round refits the screen's shortlist with the stage scorers the screen built
    (their base refits done), not the whole catalogue, and keeps the screen's record."""
    record = {"predicted_gain": {"backlash:worm_gear": 0.2, "power_law_damping:motor": 0.0},
              "needed": 0.01, "wall_s": 1.0}
    built = {STAGE: object()}
    monkeypatch.setattr(catalogue, "_first_round",
                        lambda state: (catalogue.NextRound({"backlash:worm_gear"}, built),
                                       record))
    asked = []

    def refits(state, rnd, shortlist, bar, scorers):
        asked.append((shortlist, dict(scorers)))
        return []

    monkeypatch.setattr(catalogue, "_screen", refits)
    state = SimpleNamespace(settings=DiscoverSettings(), rounds=[])
    assert catalogue._one_round(state, 0, None, None) is None
    assert asked == [({"backlash:worm_gear"}, built)]
    assert state.rounds[0]["shortlist_screen"] is record
    assert "noise floor" in state.rounds[0]["reason"]
    # a screen that failed leaves the round the whole catalogue
    monkeypatch.setattr(catalogue, "_first_round", lambda state: (None, None))
    catalogue._one_round(state, 0, None, None)
    assert asked[-1] == (None, {}) and "shortlist_screen" not in state.rounds[-1]


@pytest.mark.slow  # ~10 s; CI keeps the screen's own cases above
def test_a_later_round_refits_the_effects_already_accepted_with_its_candidates(tmp_path):
    """A round-1 winner fitted without the effect still missing absorbs part of it
    (realistic rig 120: a rack asymmetry at 1.75 for a true 1.20 beside a 0.49° worm-gear
    backlash). Held there in round 2 it kept the gap's candidate at 0.16° and 6.9 % of the
    stage; refitted with the candidate, as the extension fits it, the gap is found.
    Here: the plain bench's rack asymmetry (1.2) and worm-gear gap (0.0085 rad), the
    asymmetry accepted at 1.75 — the later round's scorer must free it."""
    from mbst.discovery.state import DiscoveryState
    from mbst.identify.fitting import channel_scales

    recipe = BenchRecipe(effects=["asymmetric_friction:rack:ratio=1.2",
                                  "backlash:worm_gear:width_rad=0.0085"],
                         seed=3, plan=compact_plan())
    camp = read_campaign(run_bench(tmp_path, recipe))
    ids = [prepare_test(camp, s, 0.005) for s in camp.identification_tests()]
    ratio, width = "rack.asymmetric_friction.ratio", "worm_gear.backlash.width_rad"
    p = recipe.true_params()
    p[EPS_MODEL.param_index[width]] = EPS_MODEL.spec(width).default  # not found yet
    p[EPS_MODEL.param_index[ratio]] = 1.75  # accepted in round 1, too large
    state = SimpleNamespace(
        settings=DiscoverSettings(), model=EPS_MODEL, ids=ids, p=p, scales=channel_scales(ids),
        base=SimpleNamespace(preid={"upper": {}}, params=p), compensating=dict,
        cascade_free={STAGE: EPS_MODEL.stage_free()[STAGE]}, extra_free={STAGE: (ratio,)})
    state.model_free = lambda stage: DiscoveryState.model_free(state, stage)
    scorer = catalogue.stage_scorer(state, STAGE)
    assert ratio in scorer.stage_free
    # its fits' work is counted at the base model's step, not the model's as it stands
    assert scorer.work_reference is state.base.params
    gap = scorer.score(EPS_MODEL.effects["backlash:worm_gear"], 1000.0, max_nfev=5)
    # measured 2026-11-26: 61.9 % of the stage and the ratio back at 1.27; held at 1.75,
    # 9.7 % at a width of 0.0034 rad
    assert gap.relative_gain > 0.4, gap
    assert gap.params[EPS_MODEL.param_index[ratio]] == pytest.approx(1.2, rel=0.1)
