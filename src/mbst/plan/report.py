"""What ``mbst plan`` writes: campaign skeleton, ranking tables, plan.json, plan.md."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import yaml

from mbst.io.campaign import FORMAT as CAMPAIGN_FORMAT
from mbst.io.outputs import atomic_text, write_json, write_markdown
from mbst.plan.config import PlanConfig
from mbst.plan.information import (
    PARTNER_CORRELATION,
    fisher,
    identifiability,
    input_error_term,
    prior_information,
)
from mbst.plan.proof import campaign_tests
from mbst.plan.selection import Plan, Step, plan_cost
from mbst.plan.sensitivity import Sensitivity
from mbst.plan.sensors import SENSORS, logged_channels
from mbst.systems.eps.bench import KNOWN
from mbst.systems.eps.channels import SYSTEM_NAME


def campaign_skeleton(cfg: PlanConfig, sens: Sensitivity, plan: Plan) -> dict:
    """campaign.yaml of the plan: tests with scenario, input, motor, role; no data yet."""
    tests = []
    for tid, c, role in campaign_tests(sens, plan):
        cell = sens.cells[c]
        tests.append({"id": tid, "file": f"tests/{tid}.csv", "scenario": cell.scenario,
                      "input": dict(cell.input), "motor": cell.motor, "role": role,
                      "channels": logged_channels(cell.scenario, plan.logged)})
    priors = cfg.stated_priors()
    return {
        "format": CAMPAIGN_FORMAT,
        "name": cfg.name,
        "system": SYSTEM_NAME,
        "known": {k: ({"value": v, "sigma": priors[k]} if k in priors else v)
                  for k, v in cfg.campaign_known(KNOWN).items()},
        "planned_by": "mbst plan",
        "sensors": plan.logged,
        "tests": tests,
    }


def sensitivity_table(sens: Sensitivity) -> pd.DataFrame:
    """Long table: per cell, sensor and unknown — local sensitivity over the sweep and swing."""
    rows = []
    for c, cell in enumerate(sens.cells):
        for s, sn in enumerate(sens.sensors):
            for p, pn in enumerate(sens.unknowns):
                loc = sens.rms[:, c, s, p]
                rows.append({"scenario": cell.scenario_id, "input": cell.input_id, "sensor": sn,
                             "parameter": pn, "sensitivity_centre": loc[0],
                             "sensitivity_min": loc.min(), "sensitivity_max": loc.max(),
                             "swing": sens.swing[c, s, p]})
    return pd.DataFrame(rows)


def _bits(cfg, sens, sensors, counts, rf) -> tuple[float, int]:
    f = fisher(sens, sensors, counts, rf)
    idf = identifiability(f, cfg.target_relative_std, prior_information(cfg),
                          input_error_term(sens, sensors, counts, rf))
    return idf.bits, int(idf.identifiable.sum())


def ranking_tables(cfg: PlanConfig, sens: Sensitivity, plan: Plan, rf: float
                   ) -> dict[str, pd.DataFrame]:
    """Sensors, scenarios and inputs ranked by information (alone, over the grid) per cost."""
    cc = len(sens.cells)
    everything = np.ones(cc)
    mand = [s.name for s in cfg.sensors if s.mandatory]
    chosen_cells = set(plan.tests)
    out = {}
    rows = []
    for s in cfg.sensors:
        bits, n_id = _bits(cfg, sens, list(dict.fromkeys(mand + [s.name])), everything, rf)
        seen = sum(bool((sens.swing[:, sens.sensors.index(s.name), p] >= 1.0).any())
                   for p in range(len(sens.unknowns)))
        rows.append({"sensor": s.name, "cost": s.cost, "noise": s.noise,
                     "bits_alone_all_tests": bits, "bits_per_cost": bits / max(s.cost, 1e-9),
                     "parameters_seen": seen, "identifiable_alone": n_id,
                     "campaign_channel": SENSORS[s.name].campaign_channel,
                     "selected": s.name in plan.sensors, "logged": s.name in plan.logged})
    out["sensor_ranking"] = pd.DataFrame(rows).sort_values(
        ["bits_per_cost", "sensor"], ascending=[False, True])
    rows = []
    all_sensors = [s.name for s in cfg.sensors]
    for sc in cfg.scenarios:
        counts = np.array([cell.scenario_id == sc.id for cell in sens.cells], float)
        bits, n_id = _bits(cfg, sens, all_sensors, counts, rf)
        cost = sc.cost + sum(i.cost for i in cfg.inputs)
        rows.append({"scenario": sc.id, "setup_cost": sc.cost, "bits_all_inputs": bits,
                     "bits_per_cost": bits / max(cost, 1e-9), "identifiable_alone": n_id,
                     "selected": any(sens.cells[c].scenario_id == sc.id for c in chosen_cells)})
    out["scenario_ranking"] = pd.DataFrame(rows).sort_values(
        ["bits_per_cost", "scenario"], ascending=[False, True])
    rows = []
    for inp in cfg.inputs:
        counts = np.array([cell.input_id == inp.id for cell in sens.cells], float)
        bits, n_id = _bits(cfg, sens, all_sensors, counts, rf)
        rows.append({"input": inp.id, "kind": inp.kind, "cost": inp.cost,
                     "bits_all_scenarios": bits, "identifiable_alone": n_id,
                     "selected_in": " ".join(sens.cells[c].scenario_id for c in sorted(chosen_cells)
                                             if sens.cells[c].input_id == inp.id)})
    out["input_ranking"] = pd.DataFrame(rows).sort_values(
        ["bits_all_scenarios", "input"], ascending=[False, True])
    rows = []
    for c, cell in enumerate(sens.cells):
        counts = np.zeros(cc)
        counts[c] = 1
        bits, n_id = _bits(cfg, sens, all_sensors, counts, rf)
        cost = cfg.scenario(cell.scenario_id).cost + cfg.input(cell.input_id).cost
        rows.append({"scenario": cell.scenario_id, "input": cell.input_id, "bits_all_sensors": bits,
                     "cost": cost, "identifiable_alone": n_id,
                     "selected": c in chosen_cells, "control": c in plan.controls})
    out["test_ranking"] = pd.DataFrame(rows).sort_values(
        ["bits_all_sensors", "scenario", "input"], ascending=[False, True, True])
    return out


def write_csv(path: Path, df: pd.DataFrame) -> None:
    with atomic_text(path, newline="") as fh:
        df.to_csv(fh, index=False, float_format="%.6g")


def write_yaml(path: Path, doc: dict) -> None:
    with atomic_text(path) as fh:
        fh.write("# written by `mbst plan`: the planned campaign, before any data exists.\n"
                 "# Run it, log each test to its `file:`, then `mbst check` and `mbst identify`.\n")
        yaml.safe_dump(doc, fh, sort_keys=False, default_flow_style=None, width=100)


def describe_plan(cfg: PlanConfig, sens: Sensitivity, plan: Plan) -> dict:
    cost = plan_cost(cfg, sens, plan.logged, plan.tests, plan.controls)
    return {
        "sensors": plan.sensors,
        "format_required_sensors": plan.required,
        "tests_added_for_the_cascade": plan.added_for_cascade,
        "scenarios": list(dict.fromkeys(sens.cells[c].scenario_id for c in sorted(plan.tests))),
        "tests": [{"scenario": sens.cells[c].scenario_id, "input": sens.cells[c].input_id,
                   "repetitions": n} for c, n in sorted(plan.tests.items())],
        "controls": [{"scenario": sens.cells[c].scenario_id, "input": sens.cells[c].input_id}
                     for c in plan.controls],
        "cost": cost,
        "cost_selected_only": plan_cost(cfg, sens, plan.sensors, plan.tests)["identification"],
    }


def markdown(cfg: PlanConfig, res) -> str:
    """plan.md: what was chosen, why, what it predicts, what the bench says."""
    sens = res.sensitivity
    d = res.record
    lines = _chosen_plan_lines(cfg, sens, d)
    lines += _greedy_path_lines(res.steps, res.notes)
    lines += _identifiability_lines(cfg, sens, d)
    if res.effects:
        lines += _effects_lines(res.effects)
    if res.proof is not None:
        lines += _proof_lines(cfg, res.proof.summary)
    lines += _FILES_SECTION
    return "\n".join(lines)


def _chosen_plan_lines(cfg: PlanConfig, sens: Sensitivity, d: dict) -> list[str]:
    """Title, the size of the analysis, and the plan chosen: sensors, tests, cost, verdict."""
    pl = d["planned"]
    return [f"# Campaign plan `{cfg.name}`", "",
            f"Analysis: {len(sens.sensors)} sensors × {len(cfg.scenarios)} scenarios × "
            f"{len(cfg.inputs)} inputs, {len(sens.unknowns)} unknowns swept at "
            f"{len(sens.points)} points, {sens.n_simulations} simulations in "
            f"{sens.wall_s:.1f} s (selection {d['timing']['selection_s']:.2f} s).", "",
            "## Chosen plan", "",
            f"- sensors: {', '.join(pl['sensors'])}"
            + (f" (+ required by the campaign format: {', '.join(pl['format_required_sensors'])})"
               if pl["format_required_sensors"] else ""),
            f"- scenarios: {', '.join(pl['scenarios'])}",
            "- identification tests: " + ", ".join(
                f"{t['scenario']}/{t['input']}" + (f" ×{t['repetitions']}"
                                                   if t["repetitions"] > 1 else "")
                for t in pl["tests"]),
            "- control tests: " + (", ".join(f"{t['scenario']}/{t['input']}"
                                             for t in pl["controls"]) or "none"),
            f"- cost: {pl['cost']['total']:.2f} in all (identification {pl['cost']['identification']:.2f}"
            f", budget {cfg.budget:g}); every unknown at ≤ {100 * cfg.target_relative_std:g} % "
            f"predicted: {'yes' if d['planned_identifiability']['all_identifiable'] else 'NO'}",
            "", "Greedy path (selection_path.csv, figures/information_vs_cost.png):", ""]


def _greedy_path_lines(steps: list[Step], notes: list[str]) -> list[str]:
    """The selection's steps, numbered, then its notes (why it stopped where it did)."""
    lines = [f"{k}. {st.move} — cost {st.cost:.2f}, {st.bits:.0f} bits, worst σ "
             f"{st.worst_relative_std:.3g}, {st.n_identifiable} identifiable"
             for k, st in enumerate(steps)]
    return lines + [f"- note: {n}" for n in notes]


def _identifiability_lines(cfg: PlanConfig, sens: Sensitivity, d: dict) -> list[str]:
    """Predicted σ of each unknown, planned beside naive, what the plan leaves above the
    target, and the two campaigns' conditioning."""
    planned, naive = d["planned_identifiability"], d["naive_identifiability"]
    nv = d["naive"]
    lines = ["", "## Predicted identifiability (relative standard error, worst over the sweep)",
             "", "| parameter | planned | naive |", "|---|---|---|"]
    for p, a, b in zip(sens.unknowns, planned["worst_relative_std"],
                       naive["worst_relative_std"], strict=True):
        lines.append(f"| {p} | {a:.3g} | {b:.3g} |")
    above = planned.get("above_target", [])
    if above:
        lines += _above_target_lines(cfg, above)
    return lines + [
        "", f"Planned: condition number {planned['condition_number']:.3g}"
        f", largest |correlation| {planned['max_abs_correlation']:.3f} (correlation.csv).",
        f"Naive ({nv['tests'][0]['scenario']}/{nv['tests'][0]['input']} ×"
        f"{nv['tests'][0]['repetitions']}, sensors {', '.join(nv['sensors'])}; cost "
        f"{nv['cost']['total']:.2f}): {sum(naive['identifiable'])} of "
        f"{len(sens.unknowns)} identifiable.", ""]


def _above_target_lines(cfg: PlanConfig, above: list[dict]) -> list[str]:
    """The unknowns left above the target, each with the combination the plan does pin down."""
    lines = ["", f"Unknowns the plan leaves above {100 * cfg.target_relative_std:g} %, and "
             "what it does pin down: the best-determined product θ_a·θ_b^x of each with "
             "the other unknown above the target most correlated with it (|r| ≥ "
             f"{PARTNER_CORRELATION:g}, at its worst sweep point; for two terms of one sum "
             "x is the ratio of their shares). A small σ there means the tests see the "
             "two only together: fix one (a datasheet, a separate test) or lump them.",
             "",
             "| unknown | σ | correlated with (r) | identified combination | its σ |",
             "|---|---|---|---|---|"]
    return lines + [_combination_row(c) for c in above]


def _combination_row(c: dict) -> str:
    """One unknown above the target: its σ, its partners and their identified product."""
    partners = ", ".join(f"`{n}` ({r:+.2f})" for n, r in c["partners"].items()) or "–"
    if "exponents" in c:
        combo = " · ".join(f"{n}^{x:.2g}" if abs(x - 1) > 1e-9 else n
                           for n, x in c["exponents"].items())
        sig = f"{c['combination_relative_std']:.3g}"
    else:
        combo, sig = "– (no partner above the target)", "–"
    return (f"| `{c['parameter']}` | {c['relative_std']:.3g} | {partners} | "
            f"{combo} | {sig} |")


def _effects_lines(effects: list[dict]) -> list[str]:
    """Per catalogue effect: its look-alike and the cheapest test and sensors that separate
    the two (``effects.csv``)."""
    lines = ["## Effects: cheapest sensors and test that separate each from its look-alike",
             "", "| effect | look-alike (cos²) | separated at defaults | by the plan | "
             "cheapest test | sensors | cost |", "|---|---|---|---|---|---|---|"]
    for r in effects:
        test = (f"{r['cheapest_scenario']}/{r['cheapest_input']}"
                if r["cheapest_scenario"] else "none in the grid")
        lines.append(f"| {r['effect']} | {r['look_alike']} ({r['similarity_at_defaults']:.2f})"
                     f" | {'yes' if r['separated_at_defaults'] else 'no'} | "
                     f"{'yes' if r.get('separated_by_plan') else 'no'} | {test} | "
                     f"{r['cheapest_sensors']} | {r['cheapest_cost']:.2f} |")
    return lines + [""]


def _proof_lines(cfg: PlanConfig, s: dict) -> list[str]:
    """The bench proof's summary: planned beside naive on errors, control FIT and time."""
    return ["## Proof on the virtual bench (planned vs naive, equal cost)", "",
            "| | planned | naive |", "|---|---|---|",
            f"| median relative parameter error | {s['median_relative_error']['planned']:.3g}"
            f" | {s['median_relative_error']['naive']:.3g} |",
            f"| largest relative parameter error | {s['max_relative_error']['planned']:.3g} | "
            f"{s['max_relative_error']['naive']:.3g} |",
            f"| rms log error, all unknowns | {s['rms_log_error']['planned']:.3g} | "
            f"{s['rms_log_error']['naive']:.3g} |",
            f"| rms log error, the {len(s['promised'])} the plan promises (σ ≤ target) | "
            f"{s['rms_log_error_promised']['planned']:.3g} | "
            f"{s['rms_log_error_promised']['naive']:.3g} |",
            f"| mean FIT % on all controls (signal channels both logged) | "
            f"{s['mean_control_fit_percent']['planned']:.2f} | "
            f"{s['mean_control_fit_percent']['naive']:.2f} |",
            f"| identification wall time s | {s['identification_wall_s']['planned']:.1f} | "
            f"{s['identification_wall_s']['naive']:.1f} |", "",
            f"True model on the same controls: {s['mean_control_fit_percent']['truth']:.2f} %"
            f" (channels {', '.join(f'`{c}`' for c in s['compared_channels'])})."
            f" Within twice the predicted σ on the bench: "
            f"{len(s.get('confirmed_within_factor_two', []))} of {len(cfg.unknowns)} "
            f"unknowns. Planning pays (promised parameters and control FIT): "
            f"**{'yes' if s['planning_pays'] else 'no'}** "
            "(proof_errors.csv, proof_fit.csv).", ""]


# the closing section of plan.md: every file ``write_all`` writes
_FILES_SECTION = (
    "## Files", "",
    "- `campaign.yaml`: the planned campaign (skeleton: no data yet)",
    "- `plan.json`: everything above, machine-readable",
    "- `sensitivity.csv`, `sensor_ranking.csv`, `scenario_ranking.csv`, "
    "`input_ranking.csv`, `test_ranking.csv`, `selection_path.csv`, "
    "`identifiability.csv`, `correlation.csv`, `effects.csv`",
    "- `figures/sensitivity_heatmap.png`, `figures/information_vs_cost.png`, "
    "`figures/frequency_comparison.png`", "")


def write_all(out: Path, cfg: PlanConfig, res) -> None:
    """Every output of ``mbst plan`` into ``out`` (a temporary folder of atomic_output_dir)."""
    from mbst.plan import figures

    sens = res.sensitivity
    write_yaml(out / "campaign.yaml", campaign_skeleton(cfg, sens, res.plan))
    write_csv(out / "sensitivity.csv", sensitivity_table(sens))
    for name, df in res.rankings.items():
        write_csv(out / f"{name}.csv", df)
    write_csv(out / "selection_path.csv", pd.DataFrame([vars(s) for s in res.steps]))
    ident = pd.DataFrame({
        "parameter": sens.unknowns,
        "low": [u.low for u in cfg.unknowns], "high": [u.high for u in cfg.unknowns],
        "planned_relative_std_centre": res.planned_id.relative_std[0],
        "planned_relative_std_worst": res.planned_id.worst_relative_std,
        "naive_relative_std_centre": res.naive_id.relative_std[0],
        "naive_relative_std_worst": res.naive_id.worst_relative_std,
    })
    write_csv(out / "identifiability.csv", ident)
    corr = pd.DataFrame(res.planned_id.correlation, columns=sens.unknowns)
    corr.insert(0, "parameter", sens.unknowns)
    write_csv(out / "correlation.csv", corr)
    if res.effects:
        write_csv(out / "effects.csv", pd.DataFrame(res.effects))
    if res.proof is not None:
        write_csv(out / "proof_errors.csv", res.proof.errors)
        write_csv(out / "proof_fit.csv", res.proof.fit)
    figdir = out / "figures"
    figures.sensitivity_heatmap(sens, cfg, figdir / "sensitivity_heatmap.png")
    naive_pt = (res.record["naive"]["cost"]["identification"], res.naive_id.bits,
                float(res.naive_id.worst_relative_std.max()))
    figures.information_vs_cost(res.steps, naive_pt, cfg.target_relative_std,
                                figdir / "information_vs_cost.png")
    res.record["frequency_comparison_gap_sigma"] = figures.frequency_comparison(
        cfg, figdir / "frequency_comparison.png")
    write_json(out / "plan.json", res.record)
    write_markdown(out / "plan.md", markdown(cfg, res))
