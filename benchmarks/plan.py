"""Wall time of the planning analysis (issue 6 target: ≤ 2 min on 2 cores).

Run: ``python benchmarks/plan.py [config/plan.yaml] [--proof]``. Prints one row per stage
(sensitivity grid, greedy selection, effect observability, optionally the bench proof) and
ends with ``plan: <s> s analysis for <sensors>x<scenarios>x<inputs>``. The first call
compiles the simulator (numba cache); a short warm-up excludes it.
"""

from __future__ import annotations

import copy
import sys
import tempfile
import time
from pathlib import Path

from mbst.plan.config import load_plan
from mbst.plan.effects import effect_observability
from mbst.plan.proof import run_proof
from mbst.plan.selection import (
    add_controls,
    complete_for_cascade,
    complete_for_format,
    evaluate,
    greedy,
    naive_plan,
    plan_cost,
)
from mbst.plan.sensitivity import analyse


def main() -> None:
    args = [a for a in sys.argv[1:] if not a.startswith("--")]
    cfg = load_plan(args[0] if args else "config/plan.yaml")
    warm = copy.copy(cfg)
    warm.scenarios, warm.inputs, warm.effects_enabled = cfg.scenarios[:1], cfg.inputs[:1], False
    analyse(warm)  # compile
    rows = []
    t0 = time.perf_counter()
    sens = analyse(cfg)
    rows.append(("sensitivity grid", time.perf_counter() - t0, f"{sens.n_simulations} simulations"))
    rf = cfg.sample_rate_hz / cfg.analysis_rate_hz
    t1 = time.perf_counter()
    plan, steps, _ = greedy(cfg, sens, rf)
    plan = complete_for_cascade(cfg, sens, plan)
    plan = complete_for_format(sens, add_controls(cfg, sens, plan))
    rows.append(("greedy selection", time.perf_counter() - t1, f"{len(steps)} steps"))
    t2 = time.perf_counter()
    eff = effect_observability(cfg, sens, plan, rf)
    rows.append(("effect observability", time.perf_counter() - t2, f"{len(eff)} effects"))
    analysis = time.perf_counter() - t0
    if "--proof" in sys.argv:
        total = plan_cost(cfg, sens, plan.logged, plan.tests, plan.controls)["total"]
        t3 = time.perf_counter()
        planned_id = evaluate(cfg, sens, plan, rf)[1]
        promised = [n for n, ok in zip(cfg.unknown_names, planned_id.identifiable, strict=True)
                    if ok]
        with tempfile.TemporaryDirectory() as tmp:
            res = run_proof(cfg, sens, plan, naive_plan(cfg, sens, total), Path(tmp),
                            promised=promised)
        s = res.summary
        rows.append(("bench proof", time.perf_counter() - t3,
                     f"rms log error {s['rms_log_error']['planned']:.3g} vs "
                     f"{s['rms_log_error']['naive']:.3g} (promised "
                     f"{s['rms_log_error_promised']['planned']:.3g} vs "
                     f"{s['rms_log_error_promised']['naive']:.3g})"))
    print(f"{'stage':<22} {'wall s':>7}  detail")
    for name, wall, detail in rows:
        print(f"{name:<22} {wall:7.1f}  {detail}")
    grid = f"{len(cfg.sensors)}x{len(cfg.scenarios)}x{len(cfg.inputs)}"
    print(f"plan: {analysis:.1f} s analysis for {grid} (sensors x scenarios x inputs), "
          f"{cfg.sweep_points} sweep points")


if __name__ == "__main__":
    main()
