"""The answer says which fitted parameters ended on a bound, and what the named effects did
to them (mbst.report.bounds)."""

from __future__ import annotations

import numpy as np

from mbst.report.bounds import bound_lines, parameters_on_bounds
from mbst.systems.eps.model import EPS_MODEL

GEAR = "worm_gear.stiffness_nm_per_rad"
RACK = "rack.coulomb_n"


def _at(**values: float) -> np.ndarray:
    p = EPS_MODEL.default_vector().copy()
    for name, v in values.items():
        p[EPS_MODEL.param_index[name.replace("__", ".")]] = v
    return p


def test_a_stiffness_the_extension_leaves_on_its_bound_is_said_not_the_rigs():
    lower = EPS_MODEL.spec(GEAR).lower
    base = _at(worm_gear__stiffness_nm_per_rad=lower)
    free = [GEAR, RACK, GEAR]
    # realistic rig 2301: the backlash named, the gear still on its lower bound
    rows = parameters_on_bounds(EPS_MODEL, free, base, base.copy())
    assert [(r["parameter"], r["base_on"], r["extended_on"]) for r in rows] == \
        [(GEAR, "lower", "lower")]
    text = "\n".join(bound_lines(rows, extended=True))
    assert "still on it with the named effects in" in text and "not the rig's" in text
    # the demo: the backlash released it
    released = parameters_on_bounds(EPS_MODEL, free, base, _at(worm_gear__stiffness_nm_per_rad=7879))
    assert "released by the extension" in "\n".join(bound_lines(released, extended=True))
    # an effect that trades against a level the base fit had inside its range
    upper = {RACK: 300.0}
    driven = parameters_on_bounds(EPS_MODEL, [RACK], _at(rack__coulomb_n=250.0),
                                  _at(rack__coulomb_n=300.0), upper)
    assert driven[0]["bounds"][1] == 300.0 and driven[0]["extended_on"] == "upper"
    assert "driven to it by the extension" in "\n".join(bound_lines(driven, extended=True))
    # from one bound to the other
    other = parameters_on_bounds(EPS_MODEL, free, base,
                                 _at(worm_gear__stiffness_nm_per_rad=EPS_MODEL.spec(GEAR).upper))
    assert (other[0]["base_on"], other[0]["extended_on"]) == ("lower", "upper")
    assert "to its other bound" in "\n".join(bound_lines(other, extended=True))
    # no finding: the identify step's reading; nothing on a bound, no section
    assert "may lack an effect" in "\n".join(bound_lines(rows, extended=False))
    assert parameters_on_bounds(EPS_MODEL, free, _at(), _at()) == []
    assert bound_lines([], extended=True) == []
