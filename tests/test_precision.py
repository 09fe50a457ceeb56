"""How precisely the tests measure a named effect's size (``discovery/precision.py``)."""

from __future__ import annotations

import pytest

from mbst.discovery.precision import SizePrecision, _state, effect_precision
from mbst.discovery.state import Finding
from mbst.discovery.structure import StageScorer
from mbst.identify.fitting import channel_scales, precision_at, prepare_test
from mbst.io.campaign import read_campaign
from mbst.report.discovery import _size_text
from mbst.systems.eps.bench import BenchRecipe, compact_plan, run_bench
from mbst.systems.eps.model import EPS_MODEL

KEY = "position_dependent_friction:rack"
STAGE = "free_tie_rods"


def _precision_at_truth(tmp_path, position_m: float) -> SizePrecision:
    """The compact plan's free tie-rods stage with a rack friction bump of amplitude 1 at
    ``position_m``, judged at the true rig (the rack travels ±5.5 mm there)."""
    recipe = BenchRecipe(effects=[f"{KEY}:position_m={position_m},amplitude=1.0"], seed=3,
                         plan=compact_plan())
    camp = read_campaign(run_bench(tmp_path, recipe))
    tests = [prepare_test(camp, s, 0.005) for s in camp.identification_tests()
             if s.scenario == STAGE]
    p = recipe.true_params()
    spec = EPS_MODEL.effects[KEY]
    scorer = StageScorer(tests, STAGE, p, channel_scales(tests),
                         free=[*EPS_MODEL.stage_free()[STAGE], *spec.free])
    free = list(scorer.stage_free)
    values = {h: float(p[EPS_MODEL.param_index[n]]) for h, n in spec.headline.items()}
    return effect_precision(precision_at(scorer.problem(free, p), p), free, spec, values,
                            EPS_MODEL)


@pytest.mark.parametrize("position_m, measured", [(0.01, True), (0.03, False)])
def test_a_size_the_tests_do_not_pin_is_stated_as_not_measured(tmp_path, position_m, measured):
    """A bump whose flank lies in the tested travel is measured; one whose centre lies two
    widths past its end shows only as a tail, whose height trades off with its place."""
    prec = _precision_at_truth(tmp_path, position_m)
    if measured:
        assert prec.not_measured == {}
        assert prec.std_error["amplitude"] < 0.1
    else:
        partner = prec.not_measured["amplitude"]
        assert partner is not None and partner[0] == "rack.position_dependent_friction.position_m"
        assert abs(partner[1]) >= 0.95
        assert prec.std_error["amplitude"] > 0.5
    # a place is stated with its error, never judged as a size
    assert "position_m" in prec.std_error and "position_m" not in prec.not_measured


def test_a_finding_whose_size_is_not_measured_says_so_everywhere():
    f = Finding("position_dependent_friction", "rack", {"position_m": 0.0233, "amplitude": 3.28},
                0.26, "structure test: …", STAGE, 0.38, -186.0, {})
    _state(f, SizePrecision({"position_m": 0.0022, "amplitude": 2.75},
                            {"amplitude": ("rack.position_dependent_friction.position_m", 0.998)}))
    assert "SIZE NOT MEASURED: amplitude 3.28 has a standard error of 2.75" in f.evidence
    assert "together with rack.position_dependent_friction.position_m (correlation 0.998)" \
        in f.evidence
    rec = f.record()
    assert rec["size_not_measured"] == ["amplitude"]
    assert rec["size_std_error"] == {"position_m": 0.0022, "amplitude": 2.75}
    assert _size_text(f, "amplitude", 3.28) == "amplitude = 3.28 (± 2.8: not measured)"
    assert _size_text(f, "position_m", 0.0233) == "position_m = 0.0233"
