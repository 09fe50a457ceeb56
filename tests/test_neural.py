"""Physics + neural residual (mbst.discovery.evidence.neural) on seeded bench campaigns."""

from __future__ import annotations

import copy
import os

import numpy as np
import pytest
import torch

from mbst.core.metrics import fit_percent
from mbst.discovery.data import residual_data
from mbst.discovery.evidence.neural import NeuralResidual, explain, plot_learned
from mbst.systems.eps.library import EpsCandidateLibrary

# Measured on the seed-1 backlash campaign (worm-gear gap 0.035 rad): the free_tie_rods
# control torque goes from 86.4 % to 92.3–95.6 % FIT over training seeds 0, 1, 3 (default
# settings, ~25 s on 2 busy cores). 3 points is an honest floor, well above noise.
MIN_GAIN_POINTS = 3.0


def _residuals(identified):
    _, res = identified
    return [residual_data(pt, res.params, res.twins.get(pt.id)) for pt in res.prepared.values()]


@pytest.fixture(scope="module")
def backlash(demo_backlash_identified):
    return _residuals(demo_backlash_identified)


@pytest.fixture(scope="module")
def clean(demo_clean_identified):
    return _residuals(demo_clean_identified)


@pytest.fixture(scope="module")
def backlash_model(backlash):
    # half the product's 200 steps: the properties below hold from there (measured
    # 2026-11-28: control torque 85.4 -> 93.0 %), at half the training time in CI
    return NeuralResidual(seed=0, iterations=100).fit(backlash)


def _control_fits(model: NeuralResidual, tests) -> list[tuple[str, str, float, float]]:
    rows = []
    for t in tests:
        if t.role != "control":
            continue
        pred = model.predict(t)
        for ch in t.measured:
            rows.append((t.id, ch, fit_percent(t.measured[ch], t.simulated[ch]),
                         fit_percent(t.measured[ch], pred[ch])))
    return rows


def _print(title: str, rows) -> None:
    print(f"\n{title}: control FIT % base -> physics+neural")
    for tid, ch, base, neural in rows:
        print(f"  {tid:22s} {ch:22s} {base:6.2f} -> {neural:6.2f}")


def test_backlash_neural_residual_improves_held_out_control_torque(backlash, backlash_model):
    m = backlash_model
    print(f"\ntraining {m.train_seconds:.1f} s, loss {m.loss_history[0]:.3f} -> "
          f"{np.mean(m.loss_history[-10:]):.3f}")
    rows = _control_fits(m, backlash)
    _print("backlash", rows)
    assert rows, "the demo campaign has control tests"
    # the control test that shows the gap (torque FIT below 95 %) gains a real amount
    gapped = [r for r in rows if r[1] == "steering_torque_nm" and r[2] < 95.0]
    assert gapped
    for tid, _, base, neural in gapped:
        assert neural - base >= MIN_GAIN_POINTS, (tid, base, neural)
    # and no control channel gets worse
    for tid, ch, base, neural in rows:
        assert neural >= base - 0.5, (tid, ch, base, neural)
    assert len(m.loss_history) == m.iterations
    assert np.mean(m.loss_history[-10:]) < 0.7 * np.mean(m.loss_history[:10])


def test_predict_returns_the_measured_channels_full_length(backlash, backlash_model):
    batch = backlash_model.corrections(backlash)
    for t, corr_b in zip(backlash, batch):
        assert set(corr_b) == set(t.measured)
        for ch in t.measured:
            assert corr_b[ch].shape == t.measured[ch].shape
            assert np.all(np.isfinite(corr_b[ch]))
    # the one-test path gives what the batched one gives
    t = next(t for t in backlash if t.role == "control")
    pred = backlash_model.predict(t)
    assert set(pred) == set(t.measured)
    for ch in t.measured:
        np.testing.assert_allclose(pred[ch] - t.simulated[ch], batch[backlash.index(t)][ch],
                                   atol=1e-6 * np.std(t.measured[ch]))


def test_training_never_reads_control_tests(backlash):
    poisoned = []
    for t in backlash:
        if t.role == "control":
            t = copy.deepcopy(t)
            rng = np.random.default_rng(7)
            for d in (t.measured, t.simulated, t.states):
                for k in d:
                    d[k] = rng.normal(0.0, 1e6, d[k].shape)
            t.measured["steering_torque_nm"][::7] = np.nan
            t.states["extra_signal"] = np.full(len(t.time_s), 1e9)
        poisoned.append(t)
    a = NeuralResidual(iterations=4, seed=3).fit(backlash)
    b = NeuralResidual(iterations=4, seed=3).fit(poisoned)
    assert a.trained_on == b.trained_on
    assert all(t.role == "identification" for t in backlash if t.id in a.trained_on)
    for k, v in a.state_dict().items():
        assert torch.equal(v, b.state_dict()[k]), k
    assert a.gains == b.gains
    assert a.features == b.features
    assert a.loss_history == b.loss_history


# ~10 s; CI keeps the bench's and the sparse regression's same-seed checks
@pytest.mark.slow
def test_same_seed_same_model_other_seed_other_model(backlash):
    a = NeuralResidual(iterations=4, seed=11).fit(backlash)
    b = NeuralResidual(iterations=4, seed=11).fit(backlash)
    c = NeuralResidual(iterations=1, seed=12).fit(backlash)  # differs from its first step
    assert a.loss_history == b.loss_history
    for k, v in a.state_dict().items():
        assert torch.equal(v, b.state_dict()[k]), k
    assert any(not torch.equal(v, c.state_dict()[k]) for k, v in a.state_dict().items())
    t = next(t for t in backlash if t.role == "control")
    np.testing.assert_array_equal(a.predict(t)["steering_torque_nm"],
                                  b.predict(t)["steering_torque_nm"])


# ~35 s: under -m slow for CI's time; a clean campaign's silence is held in CI by the
# unexplained round's and the discovery clean-rig tests
@pytest.mark.slow
def test_clean_campaign_correction_stays_small(clean):
    m = NeuralResidual(seed=0).fit(clean)
    rows = _control_fits(m, clean)
    _print("clean", rows)
    assert rows
    for tid, ch, base, neural in rows:
        assert neural >= base - 0.5, (tid, ch, base, neural)
    # the correction stays at the size of the (noise-level) residual it was trained on
    for t in clean:
        corr = m.correction(t)
        for ch in t.measured:
            assert np.std(corr[ch]) <= 1.5 * np.std(t.residual(ch)) + 1e-12, (t.id, ch)


def test_explain_points_at_the_worm_gear_mesh(backlash, backlash_model):
    e = explain(backlash_model, backlash, EpsCandidateLibrary, "steering_torque_nm")
    print("\nstate dependence:", list(e["state_dependence"].items())[:4])
    print("ranking:", e["ranking"][:5], f"R² {e['variance_explained']:.2f}")
    assert set(e) >= {"state_dependence", "terms", "ranking", "variance_explained"}
    # (a) the learned correction depends most on the base model's mesh angle
    assert next(iter(e["state_dependence"])) == "worm_gear_mesh_angle_rad"
    assert all(not k.startswith("base:") for k, _ in e["ranking"])
    assert 0.0 <= e["nominal_share"] < 1.0
    assert sum(s for _, s in e["ranking"]) == pytest.approx(1.0)
    assert 0.0 < e["variance_explained"] <= 1.0
    for name, key, coef in e["terms"]:
        assert ":" in key and np.isfinite(coef) and coef != 0.0, name


@pytest.mark.xfail(strict=True, reason=(
    "since the base fit holds the motor's friction at the rack's x their typical ratio "
    "(2026-11-27) the reading ranks presliding in the motor and the rack first (0.15, 0.13) "
    "and worm-gear backlash outside its five leading effects: with the split free the base "
    "fit had compensated the gap with motor friction 4x its true level, and the learned "
    "correction then read as backlash"))
def test_explain_ranks_worm_gear_backlash_among_its_two_leading_effects(backlash,
                                                                         backlash_model):
    # first for training seeds 0, 1, 3 before the tie; second best the rack's presliding
    # hysteresis, whose lag over a small displacement looks alike once smoothed
    e = explain(backlash_model, backlash, EpsCandidateLibrary, "steering_torque_nm")
    assert "backlash:worm_gear" in [k for k, _ in e["ranking"][:2]]


def test_fit_refuses_a_campaign_without_identification_tests(backlash):
    controls = [t for t in backlash if t.role == "control"]
    with pytest.raises(ValueError, match="identification"):
        NeuralResidual(iterations=1).fit(controls)


def test_plot_learned_writes_a_png(backlash, backlash_model, tmp_path):
    path = tmp_path / "learned.png"
    plot_learned(backlash_model, backlash, path)
    assert path.stat().st_size > 20_000
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"



@pytest.mark.slow  # ~35 s (a spawned interpreter imports torch); CI's pipeline runs it
def test_the_network_trains_in_a_process_of_its_own_to_the_same_model(clean, caplog):
    """Beside the structure test the network trains in a spawned process (no interpreter
    lock shared with the refits), to the same model as here."""
    from concurrent.futures import ProcessPoolExecutor

    from mbst.discovery.evidence.collect import NeuralJob, neural_evidence
    from mbst.discovery.state import DiscoverSettings

    ident = [t for t in clean if t.role == "identification"][:2]  # small: a wiring test
    settings = DiscoverSettings(neural_iterations=2)
    with caplog.at_level("WARNING"):
        job = NeuralJob(ident, settings, EpsCandidateLibrary)
        assert isinstance(job._pool, ProcessPoolExecutor)
        # ... at a lower priority than the refits it runs beside
        assert job._pool.submit(os.nice, 0).result() >= min(os.nice(0) + 10, 19)
        model, ev = job.result()
    assert "trained in a thread" not in caplog.text  # the process did it, not the fallback
    here, ev_here = neural_evidence(ident, settings, EpsCandidateLibrary)
    assert model.loss_history == here.loss_history and model.gains == here.gains
    assert ev["ranking"] == ev_here["ranking"]


def test_the_network_trains_in_a_thread_where_no_process_can_take_it(monkeypatch, caplog):
    """Where the process cannot take the job (here: a training function that cannot be
    pickled; a calling script without the main guard, memory) it trains in a thread and
    the log says so: the evidence is never lost to the process."""
    from mbst.discovery.evidence import collect

    def train(id_res, settings, library):  # local: a spawned process cannot import it
        return "model", {"ranking": [["backlash:worm_gear", 1.0]], "of": id_res}

    monkeypatch.setattr(collect, "neural_evidence", train)
    with caplog.at_level("WARNING"):
        job = collect.NeuralJob(["t1"], collect.DiscoverSettings(), EpsCandidateLibrary)
        assert job.result() == ("model", {"ranking": [["backlash:worm_gear", 1.0]],
                                          "of": ["t1"]})
    assert "trained in a thread" in caplog.text
