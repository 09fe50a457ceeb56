"""Friction-damper figures of merit beside the makers' LuGre model.

For each control test: FIT, RMSE and NRMSE of the friction force, raw
(unfiltered) signals, over the window the makers scored their LuGre model on
(written with the test by the importer) and over the whole test; the
extended and the base model side by side, and the LuGre numbers as the
importer computed them from the published predictions.
FIT = 100·(1 − ‖F − F̂‖/‖F − mean F‖), NRMSE = RMSE / (max F − min F).
"""

from __future__ import annotations

import numpy as np

from mbst.core.metrics import error_scores
from mbst.systems.friction_damper.model import INTERNAL, simulate_batch

HYBRID = "physics+neural"
# the band's state in the physics replay, where the error left is counted: unloaded means
# under this share of the largest force the replay carries in that direction (its slip
# level: in the play or the soft start of the contact)
BAND_STATES = ("unloaded", "elastic", "slipping")
UNLOADED_SHARE = 0.1


def scores(y: np.ndarray, y_hat: np.ndarray) -> dict[str, float]:
    """FIT %, RMSE (N) and NRMSE of a force prediction, as benchmark.json writes them."""
    e = error_scores(y, y_hat)
    return {"fit_percent": round(e["fit_percent"], 3), "rmse_n": round(e["rmse"], 3),
            "nrmse": round(e["nrmse"], 5)}


def replay_run(pt, p: np.ndarray) -> dict:
    """A test replayed by the physics from its measured displacement, as a learner reads it
    (``discovery.evidence.hybrid``): raw force measured and simulated, the band's signals."""
    sim = simulate_batch(pt, p)[0]
    return {"id": pt.id, "role": pt.spec.role, "scenario": pt.spec.scenario,
            "motor": pt.spec.motor, "time_s": pt.time_s,
            "input": np.asarray(pt.input_signal, float),
            "measured": {"friction_force_n": np.asarray(pt.raw["friction_force_n"], float)},
            "simulated": {"friction_force_n": sim["friction_force_n"]},
            "states": {name: sim[f"internal.{name}"] for name in INTERNAL}}


def _hybrid(tests: list, p_ext: np.ndarray, learner) -> tuple[dict, dict[str, np.ndarray]]:
    """Physics + neural residual: trained on the identification tests only, then run over
    every control test from rest; its predictions by test and what it was."""
    runs = [replay_run(pt, p_ext) for pt in tests]
    out = learner(runs)
    controls = {r["id"] for r in runs if r["role"] == "control"}
    if controls & set(out["trained_on"]):
        raise ValueError("the hybrid's learner read a control test")
    predicted = {r["id"]: np.asarray(out["predicted"][r["id"]]["friction_force_n"], float)
                 for r in runs if r["id"] in controls}
    info = {"model": "extended physics + latent neural ODE on the force (torchdiffeq), "
                     "driven by the displacement, its rate and the replay's band force, "
                     "deflection and slip direction; trained on the identification tests only",
            "trained_on": out["trained_on"], "correction_gain": out["gains"],
            "train_seconds": round(out["train_seconds"], 1)}
    return info, predicted


def band_states(sim: dict[str, np.ndarray]) -> np.ndarray:
    """Index into ``BAND_STATES`` per sample of a replay (``simulate_batch`` output): the
    band (nearly) unloaded, loaded elastically, or slipping at its level."""
    band = sim["internal.band_force_n"]
    level = np.where(band >= 0.0, max(band.max(), 0.0), max(-band.min(), 0.0))
    slipping = sim["internal.band_slip_direction"] != 0.0
    return np.where(slipping, 2, np.where(np.abs(band) < UNLOADED_SHARE * level, 0, 1))


def error_shares(y: np.ndarray, fits: dict[str, np.ndarray], states: np.ndarray) -> dict:
    """Where each model's squared force error lies, by the band's state (shares of its
    total), beside the share of samples in each state."""
    out = {"samples": {s: round(float(np.mean(states == i)), 4)
                       for i, s in enumerate(BAND_STATES)}}
    for name, y_hat in fits.items():
        e2 = (y - y_hat) ** 2
        total = float(e2.sum()) or 1.0
        out[name] = {s: round(float(e2[states == i].sum()) / total, 4)
                     for i, s in enumerate(BAND_STATES)}
    return out


def _test_record(pt, models: dict[str, np.ndarray], extra: dict[str, np.ndarray]) -> dict:
    y = pt.raw["friction_force_n"]
    runs = dict(zip(models, simulate_batch(pt, np.stack(list(models.values()))), strict=True))
    sims = {name: run["friction_force_n"] for name, run in runs.items()}
    sims.update(extra)
    rec: dict = {"whole_test": {name: scores(y, yh) for name, yh in sims.items()}}
    pub = pt.spec.extra.get("published")
    if pub:
        a, b = pub["window_samples"]
        rec["window_samples"] = [a, b]
        rec["window"] = {name: scores(y[a:b + 1], yh[a:b + 1]) for name, yh in sims.items()}
        rec["window"]["published"] = {k: pub[k] for k in ("fit_percent", "rmse_n", "nrmse")}
        rec["published_model"] = pub.get("model", "published")
        states = band_states(runs["extended"])[a:b + 1]
        rec["error_by_band_state"] = error_shares(
            y[a:b + 1], {k: v[a:b + 1] for k, v in sims.items() if k != "base"}, states)
    return rec


def benchmark_record(base, p_ext: np.ndarray, learner=None) -> dict:
    """``benchmark.json``: extended and base model on every control test, beside the
    published model where the test carries its scores; with a ``learner`` (discovery's
    neural residual) also the physics + neural row, trained on identification tests."""
    model = base.model
    tests = [pt for pt in base.prepared.values() if "friction_force_n" in pt.raw]
    controls = [pt for pt in tests if pt.spec.role == "control"]
    rec: dict = {"format": "mbst-benchmark/1", "system": model.name}
    if not controls:
        rec["note"] = "no control test with a friction force: nothing to compare"
        return rec
    hybrid: dict[str, np.ndarray] = {}
    if learner is not None:
        try:
            rec["hybrid"], hybrid = _hybrid(tests, p_ext, learner)
        except Exception as exc:  # the learner costs its row only, never the table
            rec["hybrid"] = {"error": f"{type(exc).__name__}: {exc}"}
    models = {"extended": p_ext, "base": base.params}
    rec["tests"] = {pt.id: _test_record(pt, models, {HYBRID: hybrid[pt.id]} if hybrid else {})
                    for pt in controls}
    windowed = [r for r in rec["tests"].values() if "window" in r]
    if windowed:
        names = ("extended", *((HYBRID,) if hybrid else ()), "base", "published")
        rec["mean_window_fit_percent"] = {
            name: round(float(np.mean([r["window"][name]["fit_percent"] for r in windowed])), 3)
            for name in names}
        rec["extended_beats_published_on"] = [
            tid for tid, r in rec["tests"].items()
            if "window" in r and r["window"]["extended"]["fit_percent"]
            > r["window"]["published"]["fit_percent"]]
    rec["definitions"] = {
        "fit_percent": "100·(1−‖F−F̂‖/‖F−mean F‖), raw friction force, model driven by the "
                       "measured displacement, state from the first samples' force",
        "nrmse": "RMSE / (max F − min F) over the same samples",
        "window": "the samples the published model was scored on (importer: published/)",
        HYBRID: "the extended model plus a neural residual trained on the identification "
                "tests only, run over the whole control test from rest",
    }
    return rec
