"""Known values as priors ``{value, sigma}`` and fixed known values the data contradict.

campaign-format.md: a ``known`` entry is a number (fixed) or a prior fitted with a
Gaussian term; its standard error includes the prior; a fitted value more than 3 σ
from its prior is reported, and so is a fixed value the data contradict.
"""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from mbst.identify.cascade import IdentifySettings, identify
from mbst.identify.priors import CONTRADICTED_SIGMA
from mbst.io.campaign import CampaignError, read_campaign
from mbst.plan.config import parse_plan
from mbst.systems.eps.bench import (
    DEFAULT_SENSORS,
    KNOWN,
    BenchRecipe,
    PlannedTest,
    compact_plan,
    run_bench,
)
from mbst.systems.eps.realism import BenchRealism

R_P = KNOWN["pinion_radius_m"]
RATIO = KNOWN["worm_gear_ratio"]


def _plan() -> list[PlannedTest]:
    sine = lambda a, f, c: {"kind": "sine", "amplitude_deg": a, "frequency_hz": f, "cycles": c}  # noqa: E731
    return [PlannedTest("s1_sine_1hz", "blocked_column", sine(5, 1.0, 3)),
            PlannedTest("s2_sine_0p5hz", "free_tie_rods", sine(30, 0.5, 2)),
            PlannedTest("s2_sine_1hz", "free_tie_rods", sine(20, 1.0, 3))]


def _campaign(tmp: Path, known: dict) -> Path:
    """A clean short bench campaign (motor angle logged) whose ``known:`` is replaced."""
    recipe = BenchRecipe(effects=[], plan=_plan(), name="priors",
                         sensors=(*DEFAULT_SENSORS, "motor_angle_rad"))
    camp = run_bench(tmp, recipe)
    doc = yaml.safe_load((camp / "campaign.yaml").read_text())
    doc["known"] = {**doc["known"], **known}
    (camp / "campaign.yaml").write_text(yaml.safe_dump(doc, sort_keys=False))
    return camp


def _checks(camp: Path) -> dict:
    result = identify(read_campaign(camp), IdentifySettings(), controls=False)
    return {c.name: c for c in result.known_checks}, result


def test_a_prior_is_read_and_written_back(tmp_path):
    camp = _campaign(tmp_path, {"pinion_radius_m": {"value": 8e-3, "sigma": 1e-3}})
    c = read_campaign(camp)
    assert c.known["pinion_radius_m"] == 8e-3 and c.priors == {"pinion_radius_m": 1e-3}
    assert c.known["worm_gear_ratio"] == RATIO and "worm_gear_ratio" not in c.priors


@pytest.mark.parametrize("entry, words", [
    ({"value": 8e-3}, "lacks sigma"),
    ({"value": 8e-3, "sigma": 0.0}, "must be > 0"),
    ({"value": "x", "sigma": 1e-3}, "not a number"),
    ({"value": 0.0, "sigma": 1e-3}, "non-zero centre"),
])
def test_a_bad_prior_is_refused_naming_the_key(tmp_path, entry, words):
    camp = _campaign(tmp_path, {"pinion_radius_m": entry})
    with pytest.raises(CampaignError) as err:
        read_campaign(camp)
    assert "pinion_radius_m" in str(err.value) and words in str(err.value)
    assert "campaign.yaml" in str(err.value)


def test_a_prior_is_fitted_and_a_wrong_fixed_value_is_reported(tmp_path):
    # the pinion radius written 8 % off with a loose prior: the rack travel pins it;
    # the gear ratio held fixed 5 % off: the motor angle contradicts it
    camp = _campaign(tmp_path, {"pinion_radius_m": {"value": 1.08 * R_P, "sigma": 0.2 * R_P},
                                "worm_gear_ratio": 1.05 * RATIO})
    checks, result = _checks(camp)
    radius = checks["pinion_radius_m"]
    assert radius.fitted == pytest.approx(R_P, rel=0.01)
    assert radius.std_error < 0.1 * radius.sigma  # the data, not the prior, decide it
    assert not radius.contradicted and radius.verdict == "consistent"
    ratio = checks["worm_gear_ratio"]
    assert ratio.sigma is None and ratio.contradicted and ratio.z < -CONTRADICTED_SIGMA
    assert ratio.verdict == "contradicted"
    assert ratio.fitted == pytest.approx(RATIO, rel=0.02)
    assert any("contradict known 'worm_gear_ratio'" in w for w in result.warnings)
    assert not any("pinion_radius_m" in w and "contradict" in w for w in result.warnings)


# ~12 s; CI keeps a wrong fixed value reported beside a fitted prior (the test above)
@pytest.mark.slow
def test_a_stated_value_of_a_fitted_parameter_is_held_and_checked(tmp_path):
    """campaign-format.md: a ``known`` number is held fixed. A torsion-bar stiffness stated
    20 % under the rig's was silently refitted (and the pre-identification's start written
    over it); now it is held as stated and the data's contradiction is reported."""
    from mbst.systems.eps.params import PARAM_INDEX

    k_t = BenchRecipe(effects=[]).true_params()[PARAM_INDEX["torsion_bar.stiffness_nm_per_rad"]]
    camp = _campaign(tmp_path, {"torsion_bar.stiffness_nm_per_rad": float(0.8 * k_t)})
    checks, result = _checks(camp)
    assert result.params[PARAM_INDEX["torsion_bar.stiffness_nm_per_rad"]] == 0.8 * k_t
    assert not any("torsion_bar.stiffness_nm_per_rad" in st.free for st in result.stages)
    stated = checks["torsion_bar.stiffness_nm_per_rad"]
    assert stated.contradicted and stated.fitted == pytest.approx(k_t, rel=0.02)
    assert any("contradict known 'torsion_bar.stiffness_nm_per_rad'" in w
               for w in result.warnings)


def test_exact_known_values_are_not_contradicted(tmp_path):
    checks, result = _checks(_campaign(tmp_path, {}))
    assert checks and not [c.name for c in checks.values() if c.contradicted]
    assert not any("contradict" in w for w in result.warnings)


@pytest.mark.slow
def test_a_tight_prior_the_data_refute_is_reported(tmp_path):
    camp = _campaign(tmp_path, {"pinion_radius_m": {"value": 1.08 * R_P, "sigma": 0.01 * R_P}})
    checks, result = _checks(camp)
    radius = checks["pinion_radius_m"]
    assert radius.contradicted and radius.z < -CONTRADICTED_SIGMA
    assert any("contradict known 'pinion_radius_m'" in w for w in result.warnings)


def test_the_planner_reads_a_prior_as_information_on_an_unknown():
    doc = yaml.safe_load(Path("config/plan.yaml").read_text())
    doc["known"]["motor_inertia_kgm2"] = {"value": 4.5e-5, "sigma": 0.45e-5}
    cfg = parse_plan(doc)
    prior = next(u for u in cfg.unknowns if u.name == "motor_inertia_kgm2")
    assert prior.prior_std_log == pytest.approx(0.1)
    assert "motor_inertia_kgm2" not in cfg.known
    assert cfg.stated_priors() == {"motor_inertia_kgm2": pytest.approx(0.45e-5)}
    assert cfg.campaign_known(KNOWN)["motor_inertia_kgm2"] == 4.5e-5


@pytest.mark.slow
def test_loose_priors_hold_the_direction_the_data_cannot_see(tmp_path):
    # gear ratio and motor inertia act through their product J·N² here (no motor angle):
    # written 15 % off as 20 % priors, the priors must decide along that valley. Weighed
    # against the sensor noise alone they did not (here the ratio went to 13.7 for 16.5)
    recipe = BenchRecipe(effects=[], plan=compact_plan(), name="loose-priors",
                         realism=BenchRealism(known_error=0.15, known_sigma=0.2))
    camp = run_bench(tmp_path, recipe)
    checks, result = _checks(camp)
    assert checks["worm_gear_ratio"].sigma is not None
    assert checks["worm_gear_ratio"].fitted == pytest.approx(RATIO, rel=0.1)
    assert checks["motor_inertia_kgm2"].fitted == pytest.approx(KNOWN["motor_inertia_kgm2"],
                                                                rel=0.2)
    assert not [c.name for c in checks.values() if c.contradicted]
