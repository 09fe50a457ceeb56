"""Wall time of the whole identification cascade on the demo campaign.

Run: ``python benchmarks/identify.py``. Target: ≤ 30 s on a 2-core machine.
The first run compiles the simulator (numba cache); it is excluded.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

from mbst.identify.cascade import IdentifySettings, identify
from mbst.io.campaign import read_campaign
from mbst.systems.eps.bench import BenchRecipe, run_bench


def main() -> None:
    with tempfile.TemporaryDirectory() as tmp:
        rows = []
        for label, effects in (("clean", []), ("demo (worm-gear backlash)", None)):
            recipe = BenchRecipe() if effects is None else BenchRecipe(effects=effects)
            camp = read_campaign(run_bench(Path(tmp) / label.split()[0], recipe))
            identify(camp, IdentifySettings(max_nfev=2, multistart=1))  # warm-up: compile
            t0 = time.perf_counter()
            res = identify(camp, IdentifySettings())
            wall = time.perf_counter() - t0
            fits = res.correlation.groupby("test").fit_percent.min()
            rows.append((label, wall, len(res.stages), fits.to_dict()))
    print(f"{'campaign':<28} {'wall s':>7} {'stages':>6}  worst control FIT % per test")
    for label, wall, n, fits in rows:
        f = ", ".join(f"{k} {v:.1f}" for k, v in fits.items())
        print(f"{label:<28} {wall:7.1f} {n:6d}  {f}")
    print(f"identify: {rows[-1][1]:.1f} s per demo campaign")


if __name__ == "__main__":
    main()
