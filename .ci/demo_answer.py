"""CI: the main job's answer on every bench campaign it ran, against the bench's truth.

The README's first command runs discovery on the built-in demo (a planted worm-gear
backlash). This reads what that run wrote, ``results/<campaign>/discover/discovery.json``,
beside the bench's ``truth.json``, and fails unless each planted effect is named in its
component (or a part it moves as one body with) at its size within 20 %, no other
catalogue effect is named with confidence >= 0.5, and the extended model beats the base on
the held-out controls. On a clean bench campaign no catalogue effect may be named at
confidence >= 0.5 (#31's bar: a low-confidence name says itself that it is unsure).

The same case under pytest (``tests/test_discover.py``, compact plan) is marked slow: CI
checks the pipeline's own run instead of repeating it.

Usage: python .ci/demo_answer.py [RESULTS_DIR]   (default: results)
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

SIZE_TOLERANCE = 0.20


def _problems(truth: dict, discovery: dict) -> list[str]:
    found = [f for f in discovery["findings"] if f["effect"] != "unexplained"]
    problems = []
    for planted in truth["effects"]:
        where = {planted["component"]}
        match = [f for f in found if f["effect"] == planted["effect"]
                 and where & {f["component"], *f.get("indistinguishable_from", [])}]
        if not match:
            problems.append(f"{planted['effect']} in {planted['component']} not named")
            continue
        for name, true in planted["parameters"].items():
            got = match[0]["parameters"].get(name)
            if got is None or abs(got - true) > SIZE_TOLERANCE * abs(true):
                problems.append(f"{planted['effect']}.{name}: {got} named, {true} planted")
    planted_keys = {(e["effect"], e["component"]) for e in truth["effects"]}
    for f in found:
        if (f["effect"], f["component"]) not in planted_keys and f["confidence"] >= 0.5:
            problems.append(f"{f['effect']} in {f['component']} named at confidence "
                            f"{f['confidence']} but not planted")
    gain = discovery["gain"]["control_fit_percent_mean"]
    if truth["effects"] and not gain > 0:
        problems.append(f"control FIT gain of the extended model {gain} (must be > 0)")
    return problems


def main(results: Path) -> int:
    checked, failed = 0, 0
    for truth_file in sorted(results.glob("*/bench/truth.json")):
        campaign = truth_file.parent.parent
        disc_file = campaign / "discover" / "discovery.json"
        if not disc_file.exists():
            continue
        truth = json.loads(truth_file.read_text())
        problems = _problems(truth, json.loads(disc_file.read_text()))
        checked += 1
        planted = ", ".join(f"{e['effect']}:{e['component']}" for e in truth["effects"])
        print(f"{campaign.name}: planted [{planted}] -> "
              f"{'ok' if not problems else '; '.join(problems)}")
        failed += bool(problems)
    if checked == 0:
        print(f"no bench campaign with a discovery under {results}/", file=sys.stderr)
        return 1
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main(Path(sys.argv[1] if len(sys.argv) > 1 else "results")))
