"""The MBST loop on the bench (issue #33): discovery cannot decide → ``mbst plan --resolve``
→ the added tests run on the same rig → discovery on the union.

Run: ``python benchmarks/loop.py [--cases KEY ...] [--seed 1] [--keep DIR]`` (about four
minutes a case on 2 cores). Each case plants one effect on the compact plan, runs
discovery, designs the next tests, runs the campaign with them appended on the same bench
(same seed: the logged tests repeat exactly) and runs discovery again. Prints the
table of docs/loop.md; no assertion.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import NamedTuple

SENSORS = ("steering_angle_rad,steering_torque_nm,rack_position_m,tie_rod_force_left_n,"
           "tie_rod_force_right_n,motor_angle_rad")


class Case(NamedTuple):
    effect: str  # planted
    target: str | None = None  # the question asked beside discovery's own
    bench: tuple[str, ...] = ("--sensors", SENSORS)
    discover: tuple[str, ...] = ()
    seed: int | None = None  # a fixed rig (default: --seed)


CASES = {
    "stribeck_column": Case("stribeck_friction:steering_column"),
    "asymmetry_column": Case("asymmetric_friction:steering_column"),
    "power_law_column": Case("power_law_damping:steering_column"),
    "power_law_motor": Case("power_law_damping:motor"),
    # a production-size worm-gear backlash (eps-model.md: 0.1-0.6°), 0.35°, asked at 0.3°
    "backlash_0p35deg": Case("backlash:worm_gear:width_rad=0.0061",
                             "backlash:worm_gear:width_rad=0.0052"),
    # rival questions: on this realistic rig discovery names rack presliding with two
    # look-alikes it does not rule out (motor presliding, position-dependent rack friction)
    "rival_presliding_rack": Case("presliding_hysteresis:rack", bench=("--realistic",),
                                  discover=("--no-sparse", "--no-neural"), seed=104),
    # a production-size worm-gear backlash on a realistic rig (0.31°) that discovery named
    # presliding hysteresis in the motor at confidence 0.034 (benchmarks/README.md, seed 5)
    "backlash_realistic_500": Case("backlash:worm_gear", "backlash:worm_gear:width_rad=0.0052",
                                   bench=("--realistic",),
                                   discover=("--no-sparse", "--no-neural"), seed=500),
}


def mbst(*args: str) -> None:
    subprocess.run([sys.executable, "-m", "mbst", *args, "--quiet"], check=True)


def named(disc: Path) -> str:
    rec = json.loads((disc / "discovery.json").read_text())
    out = [f"{f['effect']} in {f['component']} ({f.get('confidence', 0):.2f})"
           + "".join(f", not ruled out: {a['effect']} in {a['component']}"
                     for a in f.get("alternatives") or [])
           for f in rec["findings"]]
    return "; ".join(out) or "nothing"


def one(tmp: Path, key: str, seed: int) -> dict:
    case = CASES[key]
    t0 = time.perf_counter()
    bench = ["--plan", "compact", "--seed", str(case.seed or seed), "--effect", case.effect,
             *case.bench]
    mbst("bench", "--out", str(tmp / "before"), *bench)
    mbst("discover", str(tmp / "before" / "campaign"), "--out", str(tmp / "before" / "disc"),
         *case.discover)
    extra = ["--target", case.target] if case.target else []
    mbst("plan", "--resolve", str(tmp / "before" / "disc"), "--out", str(tmp / "resolve"),
         *extra)
    mbst("bench", "--out", str(tmp / "after"), *bench,
         "--tests-from", str(tmp / "resolve" / "campaign.yaml"))
    mbst("discover", str(tmp / "after" / "campaign"), "--out", str(tmp / "after" / "disc"),
         *case.discover)
    design = json.loads((tmp / "resolve" / "resolve.json").read_text())
    spec = case.effect.split(":")[:2]
    q = next((r for r in design["questions"]
              if [r["effect"], r["component"]] == spec and not r["rival"]), None)
    rivals = [f"{r['rival']}: ΔAIC {r['aic_delta_before']:.0f} → {r['aic_delta_after']:.0f} "
              f"(needed −{r['aic_drop_needed']:.0f})"
              for r in design["questions"] if r["rival"]]
    return {"case": key, "planted": case.effect,
            "share": (q["share_before"], q["share_after"]) if q else None,
            "aic": (q["aic_delta_before"], q["aic_delta_after"]) if q else None,
            "rivals": "; ".join(rivals),
            "named_before": named(tmp / "before" / "disc"),
            "named_after": named(tmp / "after" / "disc"),
            "tests_added": len(design["added_tests"]),
            "time_added_s": design["budget"]["added_test_time_s"],
            "campaign_s": design["budget"]["campaign_test_time_s"],
            "wall_s": time.perf_counter() - t0}


def table(rows: list[dict]) -> str:
    lines = ["| planted | predicted share before → after | ΔAIC before → after | named before "
             "| named after | tests added | test time added |", "|---|---|---|---|---|---|---|"]
    for r in rows:
        sh = (f"{100 * r['share'][0]:.1f} → {100 * r['share'][1]:.1f} %" if r["share"]
              else "not asked")
        aic = f"{r['aic'][0]:.0f} → {r['aic'][1]:.0f}" if r["aic"] else "—"
        if r["rivals"]:
            aic = f"rivals: {r['rivals']}"
        lines.append(f"| {r['planted']} | {sh} | {aic} | {r['named_before']} | "
                     f"{r['named_after']} | {r['tests_added']} | {r['time_added_s']:.0f} s "
                     f"({100 * r['time_added_s'] / r['campaign_s']:.0f} %) |")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", nargs="*", default=list(CASES), choices=list(CASES))
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--keep", help="keep the campaigns and results in this folder")
    args = ap.parse_args()
    rows = []
    with tempfile.TemporaryDirectory(prefix="mbst-loop-") as scratch:
        root = Path(args.keep or scratch)
        for key in args.cases:
            rows.append(one(root / key, key, args.seed))
            print(f"{key}: {rows[-1]['named_before']} -> {rows[-1]['named_after']} "
                  f"({rows[-1]['wall_s']:.0f} s)", flush=True)
    print(table(rows))


if __name__ == "__main__":
    main()
