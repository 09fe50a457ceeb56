"""Same answers before and after a change that should not change them.

Run the demo, demo-assist and EMPS campaigns through the ``mbst`` command and
keep what they answer, then compare two such records number by number::

    python benchmarks/same_answers.py record DIR      # bench + identify + discover
    python benchmarks/same_answers.py compare OLD NEW # prints a table, exit 1 on a difference

Only the command line is used, so a record made on an old checkout compares
with one made on a new checkout. Compared: ``params.json``, ``correlation.csv``
(identify), ``discovery.json``, ``comparison.csv``, ``structure_test.csv``,
``resolution.csv`` and ``benchmark.json`` (discover). Numbers must agree within
``--rtol`` (default 1e-9 relative); strings and keys exactly. Timings,
provenance (code version, paths) are left out: they differ run to run.
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
from pathlib import Path

import pandas as pd

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "real"

# campaign -> how its folder is made
CAMPAIGNS = {
    "demo": ["bench", "--effect", "backlash:worm_gear", "--seed", "0", "--plan", "demo"],
    "demo-assist": ["bench", "--effect", "backlash:worm_gear", "--seed", "0",
                    "--plan", "compact-assist", "--sensors",
                    "steering_angle_rad,steering_torque_nm,rack_position_m,"
                    "tie_rod_force_left_n,tie_rod_force_right_n,motor_current_a"],
    "emps": ["import", "emps", str(DATA / "emps")],
}
DISCOVER_EXTRA = {"emps": ["--min-aic-drop", "30", "--max-effects", "3"]}
# keys whose values are run-dependent by nature
VOLATILE = {"timings", "timings_s", "train_seconds", "provenance", "code_version", "campaign_dir", "wall_s", "created",
            "neural_s", "neural_wait_s", "seconds", "time_s", "elapsed_s"}
FILES = ("identify/params.json", "identify/correlation.csv", "discover/discovery.json",
         "discover/comparison.csv", "discover/structure_test.csv",
         "discover/resolution.csv", "discover/benchmark.json")


def _mbst(*args: str) -> None:
    print("+ mbst", " ".join(args), flush=True)
    subprocess.run(["mbst", *args], check=True)


def record(out: Path, names: list[str]) -> None:
    for name in names:
        root = out / name
        campaign = root / "campaign"
        make = CAMPAIGNS[name]
        if make[0] == "bench":
            _mbst(*make, "--out", str(root / "bench"))
            campaign = root / "bench" / "campaign"
        else:
            _mbst(*make, "--out", str(campaign))
        common = ["--tau", "0.005", "--seed", "0", "--quiet", "--multistart", "2"]
        _mbst("identify", str(campaign), "--out", str(root / "identify"), *common)
        _mbst("discover", str(campaign), "--out", str(root / "discover"), *common,
              *DISCOVER_EXTRA.get(name, []))


def _differences(a, b, path: str, rtol: float, out: list[str]) -> None:
    if isinstance(a, dict) and isinstance(b, dict):
        for k in sorted(set(a) | set(b)):
            if k in VOLATILE:
                continue
            if k not in a or k not in b:
                out.append(f"{path}.{k}: only in {'new' if k in b else 'old'}")
                continue
            _differences(a[k], b[k], f"{path}.{k}", rtol, out)
    elif isinstance(a, list) and isinstance(b, list):
        if len(a) != len(b):
            out.append(f"{path}: {len(a)} vs {len(b)} items")
            return
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            _differences(x, y, f"{path}[{i}]", rtol, out)
    elif isinstance(a, (int, float)) and isinstance(b, (int, float)) \
            and not isinstance(a, bool):
        if math.isnan(a) and math.isnan(b):
            return
        if not math.isclose(a, b, rel_tol=rtol, abs_tol=1e-300):
            out.append(f"{path}: {a!r} vs {b!r}")
    elif a != b:
        out.append(f"{path}: {a!r} vs {b!r}")


def _load(path: Path):
    if path.suffix == ".json":
        return json.loads(path.read_text())
    df = pd.read_csv(path)
    return {"columns": list(df.columns), "rows": df.to_dict(orient="records")}


def compare(old: Path, new: Path, rtol: float) -> int:
    failed = 0
    print("| campaign | file | result |\n|---|---|---|")
    for name in sorted(p.name for p in old.iterdir() if p.is_dir()):
        for rel in FILES:
            a, b = old / name / rel, new / name / rel
            if not a.exists() and not b.exists():
                continue
            if not (a.exists() and b.exists()):
                print(f"| {name} | {rel} | missing in {'new' if a.exists() else 'old'} |")
                failed += 1
                continue
            diffs: list[str] = []
            _differences(_load(a), _load(b), "", rtol, diffs)
            verdict = "equal" if not diffs else f"{len(diffs)} differ: " + "; ".join(diffs[:3])
            failed += bool(diffs)
            print(f"| {name} | {rel} | {verdict} |")
    print(f"same_answers: {'all equal' if not failed else f'{failed} files differ'}"
          f" (rtol {rtol:g})")
    return 1 if failed else 0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    rec = sub.add_parser("record")
    rec.add_argument("out", type=Path)
    rec.add_argument("--only", nargs="*", default=list(CAMPAIGNS), choices=list(CAMPAIGNS))
    cmp_ = sub.add_parser("compare")
    cmp_.add_argument("old", type=Path)
    cmp_.add_argument("new", type=Path)
    cmp_.add_argument("--rtol", type=float, default=1e-9)
    args = ap.parse_args()
    if args.cmd == "record":
        record(args.out, args.only)
    else:
        sys.exit(compare(args.old, args.new, args.rtol))


if __name__ == "__main__":
    main()
