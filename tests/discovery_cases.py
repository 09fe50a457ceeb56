"""Shared by the discovery test modules: the settings of a hidden-effect case, its run on
a seeded bench campaign, and the check of its first finding."""

from __future__ import annotations

import json

import pytest

from mbst.discovery.pipeline import DiscoverSettings, discover
from mbst.io.campaign import read_campaign
from mbst.systems.eps.bench import BenchRecipe, compact_plan, run_bench

SETTINGS = dict(max_effects=1, sparse=False, neural=False)

# Motor and rack move as one body in free tie-rods: the same effect in either removes
# the same share of the cost (asymmetric friction 89.25 vs 89.10 % with it in the
# motor, 99.31 vs 99.22 % in the rack; rack presliding 84.73 vs 84.79 % for the motor),
# so which one is named is a coin toss. The finding must name the effect and say that
# it cannot decide between the two (``indistinguishable_from``). A motor Dahl term is
# not mimicked by the rack's (28.0 %, no rack runner-up): named alone. A rack Stribeck
# makes the rig stick-slip, and the envelope test fits it in either part (motor 98 %, rack
# 92 % of the envelope misfit, seed 1): since stop 60 a one-body twin that clears the
# margins on its own is named beside the winner ("COMPONENT UNDECIDED", even odds), and
# this sweep (slow) still asked for the rack alone and the older "NOT DECIDED" wording
# (both failing at 5bae68e, found 2026-11-27).
ONE_BODY = {"asymmetric_friction:motor", "asymmetric_friction:rack",
            "presliding_hysteresis:rack", "stribeck_friction:rack"}


def run_case(tmp_path_factory, effects: list[str], seed: int = 1, plan=compact_plan, **kw):
    out = tmp_path_factory.mktemp("disc")
    camp = read_campaign(run_bench(out, BenchRecipe(effects=effects, seed=seed,
                                                    plan=plan() if plan else None)))
    truth = json.loads((out / "truth.json").read_text())
    return camp, truth, discover(camp, DiscoverSettings(**{**SETTINGS, **kw}))


def assert_first_finding(result, key: str, truth: dict) -> None:
    assert result.findings, f"nothing found; rounds: {result.rounds[0]['reason']}"
    f = result.findings[0]
    effect, component = key.split(":")
    assert f.effect == effect, f.evidence
    if key in ONE_BODY:
        assert sorted([f.component, *f.indistinguishable_from]) == ["motor", "rack"], f.evidence
        assert "NOT DECIDED" in f.evidence or "COMPONENT UNDECIDED" in f.evidence, f.evidence
    else:
        assert f.component == component, f.evidence
    if f.effect == "backlash":
        true_w = truth["effects"][0]["parameters"]["width_rad"]
        assert f.parameters["width_rad"] == pytest.approx(true_w, rel=0.2)


# a candidate row of a structure round, as discovery.json holds it
ROW = {"stage": "free_tie_rods", "fell_back": False}


def structure_axes(monkeypatch, rounds: list[dict], path):
    """The first axes of ``figures.structure_bars`` drawn for ``rounds`` (not saved)."""
    from types import SimpleNamespace

    import mbst.report.discovery_figures as figures

    drawn = []
    monkeypatch.setattr(figures.plots, "save_figure", lambda fig, out: drawn.append(fig))
    figures.structure_bars(SimpleNamespace(
        rounds=rounds, settings=SimpleNamespace(min_relative_gain=0.1)), path)
    return drawn[0].axes[0]
