"""Valid but unusual campaigns: does `mbst discover` always answer, and the same answer?

    python benchmarks/odd_campaigns.py [--seed 700] [--fast] [--keep DIR]

One realistic bench campaign (compact plan, a worm-gear backlash drawn from production to
worn) is rewritten the ways an independent simulator or a data-acquisition export may write
a valid campaign (campaign-format.md): parquet files, time not starting at zero with
shuffled and extra columns and unknown keys, test ids with spaces and dots and other input
kinds, one test logged at a quarter of the rate, no control test, one cut-out only, a still
control test and a 0.24-s fragment of a sine. `mbst discover` runs on each through the CLI
(``--fast``: without the sparse and neural evidence). Printed: one row per variant — exit
code, whether discovery.json was written, the findings with their confidence, the listed
failures and the wall time. Variants that only rewrite the same data (parquet, time offset,
odd ids) must give the original's answer.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import pandas as pd
import yaml

Variant = Callable[[Path, dict], None]


def _tests(doc: dict, scenario: str | None = None) -> list[dict]:
    return [t for t in doc["tests"] if scenario is None or t["scenario"] == scenario]


def as_parquet(d: Path, doc: dict) -> None:
    for t in doc["tests"]:
        f = d / t["file"]
        pd.read_csv(f).to_parquet(f.with_suffix(".parquet"))
        f.unlink()
        t["file"] = t["file"].replace(".csv", ".parquet")


def time_offset(d: Path, doc: dict) -> None:
    """Clock not from zero, columns reversed, a channel nobody asked for, unknown keys."""
    for i, t in enumerate(doc["tests"]):
        f = d / t["file"]
        df = pd.read_csv(f)
        df["time_s"] += 100.0 + 7.3 * i
        df["bridge_temp_c"] = 21.5
        df[list(reversed(df.columns))].to_csv(f, index=False)
        t["operator"] = "anna"
    doc["rig_id"] = "B7"


def odd_ids(d: Path, doc: dict) -> None:
    for t in doc["tests"]:
        t["id"] = t["id"].replace("_", " ") + " v1.2"
    doc["tests"][2]["input"] = {"kind": "random", "rms_deg": 20}
    doc["tests"][4]["input"] = {"kind": "recorded", "source": "road log 17"}


def mixed_rate(d: Path, doc: dict) -> None:
    f = d / doc["tests"][3]["file"]
    pd.read_csv(f).iloc[::4].to_csv(f, index=False)


def no_control(d: Path, doc: dict) -> None:
    for t in doc["tests"]:
        t["role"] = "identification"


def free_tie_rods_only(d: Path, doc: dict) -> None:
    doc["tests"] = _tests(doc, "free_tie_rods")


def blocked_column_only(d: Path, doc: dict) -> None:
    doc["tests"] = _tests(doc, "blocked_column")
    doc["tests"][-1]["role"] = "control"


def still_and_fragment(d: Path, doc: dict) -> None:
    """A control test that barely moves, and the first 0.24 s of a sine as a test."""
    ctrl = doc["tests"][-1]
    still = {**ctrl, "id": "still_ctrl", "file": "tests/still_ctrl.csv"}
    df = pd.read_csv(d / ctrl["file"]).iloc[:600].copy()
    df["steering_angle_rad"] = df["steering_angle_rad"].iloc[0]
    df.to_csv(d / still["file"], index=False)
    src = _tests(doc, "free_tie_rods")[0]
    fragment = {**src, "id": "fragment", "file": "tests/fragment.csv"}
    pd.read_csv(d / src["file"]).iloc[:120].to_csv(d / fragment["file"], index=False)
    doc["tests"] += [still, fragment]


VARIANTS: dict[str, tuple[Variant | None, bool]] = {
    # name: (rewrite, same data as the original)
    "original": (None, True),
    "parquet": (as_parquet, True),
    "time_offset": (time_offset, True),
    "odd_ids": (odd_ids, True),
    "mixed_rate": (mixed_rate, False),
    "no_control": (no_control, False),
    "free_tie_rods_only": (free_tie_rods_only, False),
    "blocked_column_only": (blocked_column_only, False),
    "still_and_fragment": (still_and_fragment, False),
}


def mbst(*args: str) -> int:
    return subprocess.run([sys.executable, "-m", "mbst", *args, "--quiet"],
                          stdout=subprocess.DEVNULL, stderr=subprocess.PIPE).returncode


def run(root: Path, seed: int, fast: bool) -> list[dict]:
    if mbst("bench", "--realistic", "--plan", "compact", "--seed", str(seed),
            "--effect", "backlash:worm_gear", "--out", str(root / "bench")):
        raise SystemExit("the bench failed")
    truth = json.loads((root / "bench" / "truth.json").read_text())["effects"]
    print(f"planted: {truth}")
    rows = []
    for name, (rewrite, same) in VARIANTS.items():
        d = root / name
        shutil.copytree(root / "bench" / "campaign", d)
        doc = yaml.safe_load((d / "campaign.yaml").read_text())
        if rewrite is not None:
            rewrite(d, doc)
        (d / "campaign.yaml").write_text(yaml.safe_dump(doc, sort_keys=False))
        t0 = time.perf_counter()
        rc = mbst("discover", str(d), "--out", str(root / f"{name}.out"),
                  *(("--no-sparse", "--no-neural") if fast else ()))
        path = root / f"{name}.out" / "discovery.json"
        rec = json.loads(path.read_text()) if path.exists() else {}
        rows.append({
            "variant": name, "same_data": same, "rc": rc, "written": path.exists(),
            "findings": "; ".join(f"{f['effect']}:{f['component']} {f['confidence']:.3f}"
                                  for f in rec.get("findings", [])) or "—",
            "failures": len(rec.get("failures", [])),
            "wall_s": round(time.perf_counter() - t0, 1)})
        print(rows[-1], flush=True)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=700)
    ap.add_argument("--fast", action="store_true", help="no sparse and neural evidence")
    ap.add_argument("--keep", help="keep the campaigns and results in this folder")
    args = ap.parse_args()
    if args.keep:
        root = Path(args.keep)
        root.mkdir(parents=True, exist_ok=False)
        rows = run(root, args.seed, args.fast)
    else:
        with tempfile.TemporaryDirectory() as tmp:
            rows = run(Path(tmp), args.seed, args.fast)
    df = pd.DataFrame(rows)
    print("| " + " | ".join(df.columns) + " |")
    print("|" + "---|" * len(df.columns))
    for r in df.itertuples(index=False):
        print("| " + " | ".join(str(v) for v in r) + " |")
    same = df[df["same_data"]]["findings"]
    print(f"answered (discovery.json written, exit 0): {int((df['written'] & (df['rc'] == 0)).sum())}"
          f"/{len(df)}; the same data gave the same answer: {same.nunique() == 1}")


if __name__ == "__main__":
    main()
