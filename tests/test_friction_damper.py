"""The friction-damper family (issue #32): simulator, importer on slices of the real
files, and hidden effects on its own bench.

The real data set (../shared/data/real/friction-damper) is read in slices so the
tests stay fast; the whole campaign runs in the pipeline (config/friction-damper.yaml).
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest

from mbst.cli import main
from mbst.core.family import get_system
from mbst.discovery.pipeline import DiscoverSettings, discover
from mbst.identify.cascade import IdentifySettings, identify
from mbst.io.campaign import CampaignError, read_campaign
from mbst.report.discovery import windowed_benchmark_lines
from mbst.systems.friction_damper import model as M
from mbst.systems.friction_damper.bench import TRUE_BASE, run_friction_damper_bench
from mbst.systems.friction_damper.benchmark import HYBRID, benchmark_record
from mbst.systems.friction_damper.definition import FRICTION_DAMPER_MODEL
from mbst.systems.friction_damper.importer import (
    INCH_M,
    KIP_N,
    LB_N,
    import_friction_damper,
)

DATA_DIR = Path(os.environ.get(
    "MBST_FRICTION_DAMPER_DIR",
    Path(__file__).resolve().parents[2] / "shared/data/real/friction-damper"))
needs_data = pytest.mark.skipif(not (DATA_DIR / "earthquake").is_dir(),
                                reason=f"friction-damper data set not at {DATA_DIR}")
SLICE_ROWS = 4000


def _force(x: np.ndarray, **params) -> np.ndarray:
    p = FRICTION_DAMPER_MODEL.vector_from({**TRUE_BASE, "band.viscous_ns_per_m": 0.0,
                                           **params})
    return M.simulate_kernel(x, np.gradient(x, 1e-3), p[None], 0.0, 1e-3)[0][:, 0]


# --------------------------------------------------------------------------- simulator
def test_family_is_registered_with_its_model():
    fam = get_system("friction-damper")
    assert fam.model() is FRICTION_DAMPER_MODEL
    assert fam.required_channels("imposed_displacement") == [
        "time_s", "displacement_m", "friction_force_n"]


def test_band_slips_at_its_levels_and_the_play_carries_no_force():
    x = np.concatenate([np.linspace(0, 0.01, 2000), np.linspace(0.01, -0.01, 4000)])
    f = _force(x, **{"band.backlash.width_m": 2e-3, "band.asymmetric_friction.ratio": 1.4})
    fc = TRUE_BASE["band.coulomb_n"]
    assert f[1999] == pytest.approx(fc)  # slipping forward at the level
    assert f[-1] == pytest.approx(-1.4 * fc)  # and backward at the ratio's level
    # after the reversal the band unloads over F_c/k, then crosses the 2 mm play at zero
    back = 0.01 - x[2000:]
    unload = fc / TRUE_BASE["band.stiffness_n_per_m"]
    in_play = (back > unload + 1e-4) & (back < unload + 2e-3 - 1e-4)
    assert np.all(f[2000:][in_play] == 0.0)
    assert np.all(f[2000:][back < unload - 1e-4] > 0.0)


def test_contact_stiffening_keeps_the_force_at_one_millimetre():
    # the stiffness is the force per metre at 1 mm whatever the exponent
    x = np.linspace(0.0, 1e-3, 500)
    k = TRUE_BASE["band.stiffness_n_per_m"]
    for n in (1.0, 2.0):
        f = _force(x, **{"band.contact_stiffening.exponent": n, "band.coulomb_n": 1e6})
        assert f[-1] == pytest.approx(k * 1e-3, rel=1e-6)
        assert f[250] == pytest.approx(k * 1e-3 * (x[250] / 1e-3) ** n, rel=1e-6)


# --------------------------------------------------------------------------- importer
def _slice(src: Path, dst: Path, rows: int = SLICE_ROWS) -> None:
    doc = json.loads(src.read_text())
    doc["data"] = doc["data"][:rows]
    dst.parent.mkdir(parents=True, exist_ok=True)
    dst.write_text(json.dumps(doc))


@pytest.fixture(scope="module")
def sliced(tmp_path_factory) -> Path:
    """Two characterization files, one earthquake file and its LuGre window, cut short."""
    d = tmp_path_factory.mktemp("fd-data")
    for name in ("0.5Hz36lbtension1amplitude", "2Hz36lbtension0.5amplitude"):
        _slice(DATA_DIR / "characterization" / f"{name}.json",
               d / "characterization" / f"{name}.json")
    _slice(DATA_DIR / "earthquake" / "ImperialValleyDBE.json",
           d / "earthquake" / "ImperialValleyDBE.json", rows=7700)
    (d / "published").mkdir()
    (d / "published" / "lugre_ImperialValleyDBE.csv").write_text(
        (DATA_DIR / "published" / "lugre_ImperialValleyDBE.csv").read_text())
    return d


@needs_data
def test_import_converts_to_si_and_holds_out_the_earthquake(sliced, tmp_path):
    camp = read_campaign(import_friction_damper(sliced, tmp_path / "c"))
    roles = {t.id: t.role for t in camp.tests}
    assert roles == {"0p5Hz36lbtension1amplitude": "identification",
                     "2Hz36lbtension0p5amplitude": "identification",
                     "ImperialValleyDBE": "control"}
    raw = np.asarray(json.loads(
        (sliced / "earthquake" / "ImperialValleyDBE.json").read_text())["data"])
    df = camp.frame("ImperialValleyDBE")
    np.testing.assert_allclose(df["displacement_m"], raw[:, 1] * INCH_M)
    np.testing.assert_allclose(df["friction_force_n"], raw[:, 2] * KIP_N)
    sine = camp.test("0p5Hz36lbtension1amplitude").input
    assert sine["kind"] == "sine" and sine["amplitude_m"] == pytest.approx(0.0254)
    # the makers' LuGre scored on its window as the data set's README states it
    pub = camp.test("ImperialValleyDBE").extra["published"]
    assert pub["window_samples"] == [3072, 7679]  # README: 3072–7680, end exclusive
    assert pub["fit_percent"] == pytest.approx(56.0, abs=0.05)
    assert pub["rmse_n"] == pytest.approx(2041, abs=1)


@needs_data
def test_import_control_glob_picks_the_held_out_tests(sliced, tmp_path):
    assert main(["import", "friction-damper", str(sliced), "--out", str(tmp_path / "c"),
                 "--control", "2Hz*", "--quiet"]) == 0
    camp = read_campaign(tmp_path / "c")
    assert [t.id for t in camp.tests if t.role == "control"] == ["2Hz36lbtension0p5amplitude"]
    with pytest.raises(CampaignError, match="no test matches"):
        import_friction_damper(sliced, tmp_path / "d", control="0.1Hz*")
    assert not (tmp_path / "d").exists()
    # the sine tests alone and no --control: the error says what to pass, not "None"
    sines = tmp_path / "sines"
    shutil.copytree(sliced / "characterization", sines / "characterization")
    with pytest.raises(CampaignError, match="no earthquake test.*--control '1Hz\\*'"):
        import_friction_damper(sines, tmp_path / "e")
    assert not (tmp_path / "e").exists()


@needs_data
def test_import_reads_the_data_sets_own_layouts(sliced, tmp_path):
    """Folders as the makers publish them ("characterization datasets", "earthquake
    profiles"), dataset 1's names without an amplitude and dataset 4's eight columns
    (two actuator positions before the forces)."""
    d = tmp_path / "published-layout"
    (d / "characterization datasets").mkdir(parents=True)
    (d / "earthquake profiles").mkdir()
    src = sliced / "characterization" / "0.5Hz36lbtension1amplitude.json"
    (d / "characterization datasets" / "0.5Hz20lbtension.json").write_bytes(src.read_bytes())
    doc = json.loads((sliced / "earthquake" / "ImperialValleyDBE.json").read_text())
    raw = np.asarray(doc["data"])
    doc["data"] = np.column_stack([raw[:, :4], raw[:, 1:3], raw[:, 4:]]).tolist()
    (d / "earthquake profiles" / "ImperialValleyDBE.json").write_text(json.dumps(doc))
    camp = read_campaign(import_friction_damper(d, tmp_path / "c"))
    assert {t.id: t.role for t in camp.tests} == {"0p5Hz20lbtension": "identification",
                                                  "ImperialValleyDBE": "control"}
    sine = camp.test("0p5Hz20lbtension")
    disp = camp.frame("0p5Hz20lbtension")["displacement_m"]
    assert sine.input["kind"] == "sine" and sine.input["frequency_hz"] == 0.5
    assert sine.input["amplitude_m"] == pytest.approx(0.5 * np.ptp(disp), abs=1e-6)
    df = camp.frame("ImperialValleyDBE")
    np.testing.assert_allclose(df["actuator_position_1_m"], raw[:, 1] * INCH_M)
    np.testing.assert_allclose(df["actuator_force_1_n"], raw[:, 4] * LB_N)
    # files directly in the folder identify; --control picks the held-out ones
    flat = tmp_path / "flat"
    flat.mkdir()
    for f in (sliced / "characterization").glob("*.json"):
        (flat / f.name).write_bytes(f.read_bytes())
    camp = read_campaign(import_friction_damper(flat, tmp_path / "f", control="2Hz*"))
    assert sorted(t.role for t in camp.tests) == ["control", "identification"]


@needs_data
def test_import_says_when_the_band_tensions_differ(sliced, tmp_path, caplog):
    d = tmp_path / "tensions"
    (d / "characterization").mkdir(parents=True)
    for f in (sliced / "characterization").glob("*.json"):
        (d / "characterization" / f.name).write_bytes(f.read_bytes())
    src = sliced / "characterization" / "2Hz36lbtension0.5amplitude.json"
    doc = json.loads(src.read_text())
    data = np.asarray(doc["data"])
    data[:, 2] *= 0.8  # a lower tension: less force (the same data would be refused)
    (d / "characterization" / "2Hz30lbtension0.5amplitude.json").write_text(
        json.dumps({**doc, "data": data.tolist()}))
    camp = read_campaign(import_friction_damper(d, tmp_path / "c", control="2Hz36*"))
    assert "band tensions of 30, 36 lb" in camp.extra["notes"]
    assert "one tension at a time" in caplog.text


@needs_data
def test_import_refuses_a_duplicate_naming_both_files(sliced, tmp_path):
    d = tmp_path / "dup"
    for sub in ("characterization", "earthquake"):
        for f in (sliced / sub).glob("*.json"):
            (d / sub).mkdir(parents=True, exist_ok=True)
            (d / sub / f.name).write_bytes(f.read_bytes())
    # the public data set's 30 lb earthquake files are byte copies of the 36 lb ones
    (d / "earthquake" / "ImperialValleyDBE30lb.json").write_bytes(
        (d / "earthquake" / "ImperialValleyDBE.json").read_bytes())
    with pytest.raises(CampaignError) as err:
        import_friction_damper(d, tmp_path / "c")
    assert "ImperialValleyDBE.json" in str(err.value)
    assert "ImperialValleyDBE30lb.json" in str(err.value)
    assert not (tmp_path / "c").exists()
    # one name in two folders (other data): refused, both files named
    (d / "earthquake" / "ImperialValleyDBE30lb.json").unlink()
    doc = json.loads((d / "earthquake" / "ImperialValleyDBE.json").read_text())
    doc["data"] = doc["data"][:5000]
    (d / "characterization" / "ImperialValleyDBE.json").write_text(json.dumps(doc))
    with pytest.raises(CampaignError, match="test name of .*characterization.*rename"):
        import_friction_damper(d, tmp_path / "c")


@needs_data
def test_import_checks_the_declared_units(sliced, tmp_path):
    d = tmp_path / "units"
    src = sliced / "characterization" / "2Hz36lbtension0.5amplitude.json"
    doc = json.loads(src.read_text())
    doc["displacement units"] = "mm"
    (d / "characterization").mkdir(parents=True)
    (d / "characterization" / src.name).write_text(json.dumps(doc))
    with pytest.raises(CampaignError, match="'displacement units' is 'mm', expected 'in'"):
        import_friction_damper(d, tmp_path / "c")


# --------------------------------------------------------------------------- benchmark
def _oracle(runs: list[dict], cheat: bool = False) -> dict:
    """A learner that knows every measured force: its row must score 100 % FIT, and
    one that says it trained on a control must cost the row, not the table."""
    trained = [r["id"] for r in runs if cheat or r["role"] == "identification"]
    return {"predicted": {r["id"]: dict(r["measured"]) for r in runs}, "gains": {"force": 1.0},
            "trained_on": trained, "train_seconds": 0.0}


@needs_data
def test_benchmark_scores_the_hybrid_on_the_makers_windows(sliced, tmp_path):
    camp = read_campaign(import_friction_damper(sliced, tmp_path / "c"))
    base = identify(camp, IdentifySettings(multistart=1), controls=False, check_known=False)
    rec = benchmark_record(base, base.params, learner=_oracle)
    window = rec["tests"]["ImperialValleyDBE"]["window"]
    assert window[HYBRID]["fit_percent"] == pytest.approx(100.0)
    assert window["published"]["fit_percent"] == pytest.approx(56.0, abs=0.05)
    assert window["extended"] == window["base"]  # the same parameters, the same numbers
    shares = rec["tests"]["ImperialValleyDBE"]["error_by_band_state"]
    for model in ("samples", "extended"):
        assert sum(shares[model].values()) == pytest.approx(1.0, abs=1e-3)
    assert rec["mean_window_fit_percent"][HYBRID] == pytest.approx(100.0)
    text = "\n".join(windowed_benchmark_lines(rec))
    assert "| ImperialValleyDBE | 3072–7679 |" in text and "100.0 / 0 /" in text

    cheat = benchmark_record(base, base.params, learner=lambda runs: _oracle(runs, cheat=True))
    assert "read a control test" in cheat["hybrid"]["error"]
    assert HYBRID not in cheat["tests"]["ImperialValleyDBE"]["window"]
    assert "not computed" in "\n".join(windowed_benchmark_lines(cheat))


# --------------------------------------------------------------------------- bench
def _discover(tmp_path: Path, effects: dict, seed: int):
    camp = read_campaign(run_friction_damper_bench(tmp_path, effects, seed=seed))
    # the physics + neural row is the benchmark's (test below), not the finding's
    return discover(camp, DiscoverSettings(max_effects=2, neural=False))


def test_hidden_play_is_named_with_its_width(tmp_path):
    result = _discover(tmp_path, {"band.backlash.width_m": 1.2e-3}, seed=3)
    assert [(f.effect, f.component) for f in result.findings][:1] == [("backlash", "band")]
    assert result.findings[0].parameters["width_m"] == pytest.approx(1.2e-3, rel=0.2)


def test_clean_damper_gives_an_empty_answer(tmp_path):
    assert _discover(tmp_path, {}, seed=4).findings == []


@pytest.mark.slow  # ~10 s; CI keeps the planted play and the clean damper
def test_two_planted_effects_are_both_named_and_both_kept(tmp_path):
    """A play and an asymmetric level: named one after the other, and the backward check
    (each earlier effect taken out of the final model) keeps the first — it is needed."""
    camp = read_campaign(run_friction_damper_bench(
        tmp_path, {"band.backlash.width_m": 1.2e-3, "band.asymmetric_friction.ratio": 1.35},
        seed=6))
    result = discover(camp, DiscoverSettings(max_effects=3, neural=False))
    named = {f.effect: f.parameters for f in result.findings}
    assert named.keys() == {"backlash", "asymmetric_friction"}
    assert named["backlash"]["width_m"] == pytest.approx(1.2e-3, rel=0.1)
    assert named["asymmetric_friction"]["ratio"] == pytest.approx(1.35, rel=0.05)
    (backward,) = [r for r in result.rounds if r.get("kind") == "backward"]
    assert [r["needed"] for r in backward["checked"]] == [True] and not backward["dropped"]


@pytest.mark.parametrize("planted", [
    ("band.asymmetric_friction.ratio", 1.35, "asymmetric_friction", "ratio"),
    ("band.contact_stiffening.exponent", 1.7, "contact_stiffening", "exponent"),
    ("band.force_relaxation.rate_per_s", 0.8, "force_relaxation", "rate_per_s"),
])
def test_hidden_damper_effect_is_named(tmp_path, planted):
    name, size, effect, headline = planted
    result = _discover(tmp_path, {name: size}, seed=5)
    assert [(f.effect, f.component) for f in result.findings][:1] == [(effect, "band")]
    assert result.findings[0].parameters[headline] == pytest.approx(size, rel=0.15)
