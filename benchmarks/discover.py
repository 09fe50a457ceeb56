"""Wall time and outcome of discovery per campaign; calibration of the acceptance margin.

Run: ``python benchmarks/discover.py`` (``--quick`` for the compact plan only,
``--demo`` for the demo plan only).
Target: ≤ 3 min per demo campaign on a 2-core machine. The table also prints,
for clean campaigns, the largest share of a stage's residual cost any catalogue
candidate removes: the acceptance margin (``discover.min_relative_gain``, 0.10)
must sit above it. The stick-slip column is the base model's misfit of the fast
envelope, worst stage (``stickslip.MIN_BASE_MISFIT``, 2.0, must sit above it on
clean campaigns and below it where Stribeck makes the rig stick-slip). A second
table gives the time of the resolution step and the catalogue pairs it predicts
the campaign's tests would not show at their realistic size.
"""

from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path

from mbst.discovery.pipeline import DiscoverSettings, discover
from mbst.io.campaign import read_campaign
from mbst.systems.eps.bench import BenchRecipe, compact_plan, run_bench

CASES = (
    ("demo: worm-gear backlash", ["backlash:worm_gear"], 0, None),
    ("demo: clean", [], 0, None),
    ("compact: clean seed 1", [], 1, compact_plan),
    ("compact: clean seed 2", [], 2, compact_plan),
    ("compact: torsion-bar limit stop", ["stiffness_limit_stop:torsion_bar"], 1, compact_plan),
    ("compact: motor Stribeck", ["stribeck_friction:motor"], 1, compact_plan),
    ("compact: rack Stribeck", ["stribeck_friction:rack"], 1, compact_plan),
)


def main() -> None:
    quick, demo_only = "--quick" in sys.argv, "--demo" in sys.argv
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for i, (label, effects, seed, plan) in enumerate(CASES):
            if (quick and plan is None) or (demo_only and plan is not None):
                continue
            recipe = BenchRecipe(effects=effects, seed=seed, plan=plan() if plan else None)
            camp = read_campaign(run_bench(Path(tmp) / str(i), recipe))
            full = plan is None
            t0 = time.perf_counter()
            res = discover(camp, DiscoverSettings(sparse=full, neural=full))
            wall = time.perf_counter() - t0
            found = ", ".join(f"{f.effect}:{f.component}" for f in res.findings) or "none"
            best_clean = max((c["relative_gain"] for r in res.rounds for c in r["candidates"]
                              if r.get("method") != "stick_slip"),
                             default=0.0) if not effects else float("nan")
            stick = max((v for r in res.rounds for v in r.get("base_misfit", {}).values()),
                        default=float("nan"))
            means = res.comparison.groupby("model")["fit_percent"].mean()
            blind = [r.key for r in res.resolution if r.sizes and r.resolved_from != 1.0]
            rows.append((label, wall, found, best_clean, stick, means.get("base", float("nan")),
                         means.get("extended", float("nan")), means.get("true", float("nan")),
                         res.timings.get("resolution_s", 0.0), blind))
    print(f"{'campaign':<34} {'wall s':>7}  {'clean max gain':>14}  {'stick-slip':>10}  "
          f"{'FIT base/ext/true':>19}  findings")
    for label, wall, found, best, stick, b, e, t, _, _ in rows:
        print(f"{label:<34} {wall:7.1f}  {best:14.3f}  {stick:10.2f}  "
              f"{b:5.1f} /{e:5.1f} /{t:5.1f}  {found}")
    # what an empty answer would not cover (discovery step 6, resolution.py)
    print(f"\n{'campaign':<34} {'resolution s':>12}  not resolved at the realistic size")
    for label, *_, res_s, blind in rows:
        print(f"{label:<34} {res_s:12.1f}  {', '.join(blind) or 'none'}")
    demo = [r for r in rows if r[0].startswith("demo: worm")]
    if demo:
        print(f"discover: {demo[0][1]:.1f} s per demo campaign")


if __name__ == "__main__":
    main()
