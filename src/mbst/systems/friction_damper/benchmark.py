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
from mbst.systems.friction_damper.model import simulate_batch


def scores(y: np.ndarray, y_hat: np.ndarray) -> dict[str, float]:
    """FIT %, RMSE (N) and NRMSE of a force prediction, as benchmark.json writes them."""
    e = error_scores(y, y_hat)
    return {"fit_percent": round(e["fit_percent"], 3), "rmse_n": round(e["rmse"], 3),
            "nrmse": round(e["nrmse"], 5)}


def _test_record(pt, models: dict[str, np.ndarray]) -> dict:
    y = pt.raw["friction_force_n"]
    sims = {name: simulate_batch(pt, p)[0]["friction_force_n"] for name, p in models.items()}
    rec: dict = {"whole_test": {name: scores(y, yh) for name, yh in sims.items()}}
    pub = pt.spec.extra.get("published")
    if pub:
        a, b = pub["window_samples"]
        rec["window_samples"] = [a, b]
        rec["window"] = {name: scores(y[a:b + 1], yh[a:b + 1]) for name, yh in sims.items()}
        rec["window"]["published"] = {k: pub[k] for k in ("fit_percent", "rmse_n", "nrmse")}
        rec["published_model"] = pub.get("model", "published")
    return rec


def benchmark_record(base, p_ext: np.ndarray, learner=None) -> dict:
    """``benchmark.json``: extended and base model on every control test, beside the
    published model where the test carries its scores (``learner``: not used yet)."""
    model = base.model
    controls = [pt for pt in base.prepared.values() if pt.spec.role == "control"
                and "friction_force_n" in pt.raw]
    rec: dict = {"format": "mbst-benchmark/1", "system": model.name}
    if not controls:
        rec["note"] = "no control test with a friction force: nothing to compare"
        return rec
    models = {"extended": p_ext, "base": base.params}
    rec["tests"] = {pt.id: _test_record(pt, models) for pt in controls}
    windowed = [r for r in rec["tests"].values() if "window" in r]
    if windowed:
        rec["mean_window_fit_percent"] = {
            name: round(float(np.mean([r["window"][name]["fit_percent"] for r in windowed])), 3)
            for name in ("extended", "base", "published")}
        rec["extended_beats_published_on"] = [
            tid for tid, r in rec["tests"].items()
            if "window" in r and r["window"]["extended"]["fit_percent"]
            > r["window"]["published"]["fit_percent"]]
    rec["definitions"] = {
        "fit_percent": "100·(1−‖F−F̂‖/‖F−mean F‖), raw friction force, model driven by the "
                       "measured displacement, state from the first samples' force",
        "nrmse": "RMSE / (max F − min F) over the same samples",
        "window": "the samples the published model was scored on (importer: published/)",
    }
    return rec
