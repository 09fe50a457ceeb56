"""Power assist (issue #8): identified curve per mode and damping per speed vs the truth.

Run: ``python benchmarks/assist.py`` (compact seed 001 layout, ~1 min) or
``python benchmarks/assist.py --full`` (seed 001's layout at 0.01 Hz, several
minutes). Targets: c1, c2, c3 within 5 %, damping per speed within 10 %,
control FIT within 1 point of the true model. Prints one table; no assertion.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from mbst.identify.cascade import IdentifySettings, correlate, identify
from mbst.io.campaign import read_campaign
from mbst.systems.eps import assist as eps_assist
from mbst.systems.eps.bench import (
    DEFAULT_SENSORS,
    BenchRecipe,
    assist_plan,
    compact_assist_plan,
    run_bench,
)


def one(tmp: Path, label: str, recipe: BenchRecipe) -> None:
    camp = read_campaign(run_bench(tmp / label, recipe))
    truth = recipe.model().as_dict(recipe.true_params())
    t0 = time.perf_counter()
    res = identify(camp, IdentifySettings())
    wall = time.perf_counter() - t0
    model, p = res.model, res.params
    print(f"\n{label}: identify {wall:.1f} s")
    print(f"{'parameter':<44} {'identified':>11} {'true':>9} {'error %':>8}")
    for n in model.param_index:
        if n.startswith("assist.") and n.count(".") == 2:
            v, tv = p[model.param_index[n]], truth[n]
            print(f"{n:<44} {v:11.4g} {tv:9.4g} {100 * (v / tv - 1):+8.1f}")
    grid = np.linspace(0.5, 6.0, 60)
    for mode, c_true in recipe.curves().items():
        c = {q: p[model.param_index[f"assist.{mode}.{q}"]] for q in c_true}
        err = eps_assist.characteristic(grid, c) / eps_assist.characteristic(grid, c_true) - 1
        print(f"curve {mode}: max |A(T) error| over 0.5–6 N·m {100 * np.max(np.abs(err)):.1f} %")
    controls = [res.prepared[s.id] for s in camp.control_tests()]
    tc, _ = correlate(controls, model.vector_from(truth))
    m = res.correlation.merge(tc, on=["test", "channel"], suffixes=("", "_true"))
    d = (m.fit_percent - m.fit_percent_true)
    print(f"control FIT minus true model's: worst {d.min():+.2f} points "
          f"(mean FIT {m.fit_percent.mean():.2f} %)")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--full", action="store_true", help="seed 001's layout at 0.01 Hz")
    args = ap.parse_args()
    plan = assist_plan() if args.full else compact_assist_plan()
    with tempfile.TemporaryDirectory() as tmp:
        for label, sensors in (("no current sensor", DEFAULT_SENSORS),
                               ("with motor_current_a", DEFAULT_SENSORS + ("motor_current_a",))):
            one(Path(tmp), label.replace(" ", "_"),
                BenchRecipe(effects=[], plan=plan, name="assist", sensors=sensors))


if __name__ == "__main__":
    main()
