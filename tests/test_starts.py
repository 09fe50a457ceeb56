"""Where the structure test starts a candidate's refit (``StageScorer.score``)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from mbst.discovery.restarts import compensating_parameters
from mbst.discovery.structure import StageScorer, start_grid
from mbst.identify.fitting import channel_scales, prepare_test
from mbst.io.campaign import read_campaign
from mbst.systems.eps.bench import BenchRecipe, compact_plan, run_bench
from mbst.systems.eps.realism import BenchRealism

STAGE = "free_tie_rods"
PRESLIDING = "presliding_hysteresis:motor"
STRIBECK = ("rack.stribeck_friction.static_to_coulomb_ratio",
            "rack.stribeck_friction.stribeck_velocity")
# realistic rig 2512's model as discovery left it after round 1 named the rack Stribeck:
# the motor's Coulomb level 2.2x the truth (0.0358 N·m for 0.0166) and a soft, damped gear
# (9690 N·m/rad for 24 450, 9.2 N·m·s/rad for 2.8) stood in for its motor presliding
ROUND_2 = Path(__file__).parent / "data" / "rig2512_round2.json"


# ~90 s: a realistic campaign and two refits of a loaded stage
@pytest.mark.slow
def test_a_presliding_the_stage_stood_in_for_is_refitted_from_a_weaker_start(tmp_path):
    """Inserted into a stage bent to stand in for it, the motor's Dahl term fits 8-12x
    worse than the base at every grid size (σ 0.6, 2, 6 N·m/rad); from them alone its
    refit ended at the base (0.0) and discovery missed the planted σ 5.6 beside a rack
    Stribeck. From a weaker σ it grows while the stage lets go, and clears the relevance
    margin here (15.7 %, σ 57). Fragile: with the sizes rounded to four digits the same
    start ends at 0.0 too, and in discovery's own round 2 the pre-identification's upper
    bounds change the fit's scaling and it stalls at 6.1 % (benchmarks/README, stop 85)."""
    recipe = BenchRecipe(
        # rig 2512's drawn sizes to the digit: the refit's reach is that fragile (below)
        effects=["presliding_hysteresis:motor:stiffness=5.6278871262837775",
                 "stribeck_friction:rack:static_to_coulomb_ratio=1.8872941376730152,"
                 "stribeck_velocity=0.0015238145555424402"],
        seed=2512, plan=compact_plan(), realism=BenchRealism.realistic())
    out = run_bench(tmp_path, recipe)
    camp = read_campaign(out)
    ids = [prepare_test(camp, s, 0.005) for s in camp.identification_tests()]
    tests = [pt for pt, s in zip(ids, camp.identification_tests(), strict=True)
             if s.scenario == STAGE]
    model = tests[0].model
    p = model.vector_from(json.loads(ROUND_2.read_text())["params"])
    # as the rounds build it (``catalogue.stage_scorer``): what the fit inflated restarts
    # at its typical value too
    reset = compensating_parameters(p, [n for _, st in model.cascade for n in st], model)
    # weighed as the rounds weigh it: the scales of every identification test
    scorer = StageScorer(tests, STAGE, p, channel_scales(ids), max_nfev=15, reset=reset,
                         free=[*model.stage_free()[STAGE], *STRIBECK], evidence_gain=0.05)
    spec = model.effects[PRESLIDING]
    _, grid_cost = scorer._grid(scorer.base_refit()[0], start_grid(spec, model), spec)
    assert np.all(grid_cost > 5 * scorer.base_refit()[1])  # the stage stands in for it
    screened = scorer.score(spec, 900.0, max_nfev=5)
    refined = scorer.score(spec, 900.0, start=screened)
    assert refined.relative_gain >= 0.10, refined.relative_gain
    # a Dahl term, not its stiff end (the base): weaker than the truth, as the stage keeps
    # part of what it stood in for (57 N·m/rad measured)
    assert refined.headline["stiffness"] < 100.0, refined.headline
