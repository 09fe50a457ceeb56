"""How far the base model's fit stands from its noise floor, one bench reality at a time.

``discovery.md`` states per stage the cost the fit leaves over the cost its noise floor
would leave (``stage_cost_over_noise_floor``): near 1 the model explains the data down
to the sensors' noise. This prints that ratio for a clean compact campaign on the plain
bench, on the realistic bench (``mbst bench --realistic``) and on the realistic bench
with each reality taken out in turn, so a ratio well above 1 can be traced to what
causes it (the floor counts each sensor's fast noise; noise that wanders does not).

    python benchmarks/noise_floor.py [--seeds 4 5] [--out benchmarks/results/noise_floor.csv]

Each row runs the base fit and the resolution step only (``max_effects=0``, no
sparse, neural or stick-slip evidence): about 25 s a row on 2 cores.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import pandas as pd

from mbst.discovery.pipeline import DiscoverSettings, discover
from mbst.io.campaign import read_campaign
from mbst.systems.eps.bench import BenchRecipe, compact_plan, run_bench
from mbst.systems.eps.realism import BenchRealism

# each reality of BenchRealism.realistic() and the setting that takes it out
WITHOUT = {
    "noise white": {"noise_ar1": 0.0},
    "no torque lag": {"torque_lag_s": 0.0},
    "known values exact": {"known_error": 0.0},
    "identification's kernel": {"oversample": 1, "smoothing": 1.0},
    "no quantisation": {"quantise": False},
    "no offset drift": {"offset_drift": 0.0},
    "plan as written": {"plan_jitter": 0.0},
}


def variants() -> dict[str, BenchRealism]:
    full = BenchRealism.realistic()
    return {"plain bench": BenchRealism(), "realistic": full,
            **{f"realistic, {k}": replace(full, **v) for k, v in WITHOUT.items()}}


def floor_ratios(realism: BenchRealism, seed: int, work: Path, tag: int) -> dict[str, float]:
    out = work / f"campaign-{seed}-{tag}"
    camp = read_campaign(run_bench(out, BenchRecipe(effects=[], seed=seed, plan=compact_plan(),
                                                    realism=realism, name="floor")))
    result = discover(camp, DiscoverSettings(max_effects=0, sparse=False, neural=False,
                                             stick_slip=False))
    return {r.stage: r.stage_over_floor for r in result.resolution
            if r.stage is not None and r.stage_over_floor is not None}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[4])
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/noise_floor.csv"))
    args = ap.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for seed in args.seeds:
            for i, (name, realism) in enumerate(variants().items()):
                t0 = time.perf_counter()
                ratios = floor_ratios(realism, seed, Path(tmp), i)
                rows.append({"seed": seed, "bench": name, **ratios,
                             "seconds": round(time.perf_counter() - t0, 1)})
                print(rows[-1], flush=True)
    table = pd.DataFrame(rows)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    table.to_csv(args.out, index=False)
    print("\nfit cost over noise-floor cost, clean compact campaign:\n")
    print(table.to_string(index=False, float_format=lambda v: f"{v:.2f}"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
