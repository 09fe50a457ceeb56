"""``mbst plan``: analysis → selection → effects → proof → outputs, written atomically."""

from __future__ import annotations

import contextlib
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

from mbst.io.outputs import atomic_output_dir
from mbst.plan.config import PlanConfig
from mbst.plan.effects import effect_observability
from mbst.plan.information import Identifiability
from mbst.plan.proof import ProofResult, run_proof
from mbst.plan.selection import (
    Plan,
    Step,
    add_controls,
    complete_for_cascade,
    complete_for_format,
    evaluate,
    greedy,
    naive_plan,
    plan_cost,
)
from mbst.plan.sensitivity import Sensitivity, analyse


@dataclass
class PlanResult:
    sensitivity: Sensitivity
    plan: Plan
    steps: list[Step]
    notes: list[str]
    naive: Plan
    planned_id: Identifiability
    naive_id: Identifiability
    effects: list[dict]
    rankings: dict = field(default_factory=dict)
    proof: ProofResult | None = None
    record: dict = field(default_factory=dict)

    def summary(self) -> str:
        r = self.record
        pl = r["planned"]
        lines = [f"planned '{r['name']}' in {r['timing']['total_s']:.1f} s "
                 f"(analysis {r['timing']['analysis_s']:.1f} s, "
                 f"{self.sensitivity.n_simulations} simulations)",
                 f"  sensors   {', '.join(pl['sensors'])}"
                 + (f" (+ format: {', '.join(pl['format_required_sensors'])})"
                    if pl["format_required_sensors"] else ""),
                 "  tests     " + ", ".join(f"{t['scenario']}/{t['input']}" for t in pl["tests"]),
                 "  controls  " + (", ".join(f"{t['scenario']}/{t['input']}"
                                             for t in pl["controls"]) or "none"),
                 f"  cost      {pl['cost']['total']:.2f} (identification "
                 f"{pl['cost']['identification']:.2f}); worst predicted relative std "
                 f"{max(r['planned_identifiability']['worst_relative_std']):.3g} "
                 f"(naive {max(r['naive_identifiability']['worst_relative_std']):.3g})"]
        if self.proof is not None:
            s = self.proof.summary
            lines.append(f"  bench     rms log error planned {s['rms_log_error']['planned']:.3g} "
                         f"vs naive {s['rms_log_error']['naive']:.3g} (on the "
                         f"{len(s['promised'])} promised: "
                         f"{s['rms_log_error_promised']['planned']:.3g} vs "
                         f"{s['rms_log_error_promised']['naive']:.3g}); mean control FIT "
                         f"{s['mean_control_fit_percent']['planned']:.2f} % vs "
                         f"{s['mean_control_fit_percent']['naive']:.2f} %; planning pays: "
                         f"{'yes' if s['planning_pays'] else 'no'}")
        for n in self.notes:
            lines.append(f"  note: {n}")
        return "\n".join(lines)


def _id_record(idf: Identifiability, names: list[str]) -> dict:
    combos = []
    for c in idf.combinations:
        rec = {"parameter": names[c["index"]], "relative_std": c["relative_std"],
               "partners": {names[i]: r for i, r in c["partners"].items()}}
        if "exponents" in c:
            rec["exponents"] = {names[i]: x for i, x in c["exponents"].items()}
            rec["combination_relative_std"] = c["combination_relative_std"]
        combos.append(rec)
    return {"worst_relative_std": idf.worst_relative_std,
            "centre_relative_std": idf.relative_std[0],
            "identifiable": idf.identifiable, "all_identifiable": bool(idf.identifiable.all()),
            "condition_number": idf.condition_number,
            "max_abs_correlation": idf.max_abs_correlation(), "bits": idf.bits,
            "above_target": combos}


def plan_campaign(cfg: PlanConfig, progress: bool = False, proof: bool | None = None,
                  proof_dir: Path | None = None) -> PlanResult:
    """Run the whole planning; nothing is written except the proof's bench campaigns.

    Parameters
    ----------
    cfg
        Validated planning config.
    progress
        tqdm bar and stage messages.
    proof
        Run the bench proof (default: the config's ``proof.enabled``).
    proof_dir
        Where the proof's two bench campaigns go (a temporary folder if omitted).
    """
    from mbst.plan.report import describe_plan, ranking_tables

    t0 = time.perf_counter()
    rf = cfg.sample_rate_hz / cfg.analysis_rate_hz
    sens = analyse(cfg, progress=progress)
    t1 = time.perf_counter()
    plan, steps, notes = greedy(cfg, sens, rf)
    plan = complete_for_cascade(cfg, sens, plan)
    plan = complete_for_format(sens, add_controls(cfg, sens, plan))
    t2 = time.perf_counter()
    total = plan_cost(cfg, sens, plan.logged, plan.tests, plan.controls)["total"]
    naive = naive_plan(cfg, sens, total)
    _, planned_id = evaluate(cfg, sens, plan, rf)
    _, naive_id = evaluate(cfg, sens, naive, rf)
    effects = effect_observability(cfg, sens, plan, rf)
    res = PlanResult(sens, plan, steps, notes, naive, planned_id, naive_id, effects)
    res.rankings = ranking_tables(cfg, sens, plan, rf)
    if cfg.proof_enabled if proof is None else proof:
        predicted = {"planned": planned_id.relative_std[0], "naive": naive_id.relative_std[0]}
        promised = [n for n, ok in zip(cfg.unknown_names, planned_id.identifiable, strict=True)
                    if ok]
        with (tempfile.TemporaryDirectory(prefix="mbst-plan-proof-") if proof_dir is None
              else contextlib.nullcontext(proof_dir)) as where:
            res.proof = run_proof(cfg, sens, plan, naive, Path(where), predicted, progress,
                                  promised)
    t3 = time.perf_counter()
    res.record = {
        "format": "mbst-plan-result/1",
        "name": cfg.name,
        "config": cfg.path,
        "seed": cfg.seed,
        "unknowns": cfg.unknown_names,
        "target_relative_std": cfg.target_relative_std,
        "budget": cfg.budget,
        "planned": describe_plan(cfg, sens, plan),
        "naive": describe_plan(cfg, sens, naive),
        "planned_identifiability": _id_record(planned_id, cfg.unknown_names),
        "naive_identifiability": _id_record(naive_id, cfg.unknown_names),
        "selection_path": [vars(s) for s in steps],
        "notes": notes,
        "effects": effects,
        "proof": res.proof.summary if res.proof is not None else None,
        "timing": {"analysis_s": t1 - t0, "selection_s": t2 - t1,
                   "proof_s": (t3 - t2) if res.proof is not None else 0.0,
                   "total_s": t3 - t0, "simulations": sens.n_simulations},
    }
    return res


def run_plan(cfg: PlanConfig, out_dir: str | Path, progress: bool = False,
             proof: bool | None = None) -> PlanResult:
    """``mbst plan``: plan and write everything into ``out_dir`` atomically."""
    from mbst.plan.report import write_all

    res = plan_campaign(cfg, progress=progress, proof=proof)
    with atomic_output_dir(out_dir) as tmp:
        write_all(tmp, cfg, res)
    return res
