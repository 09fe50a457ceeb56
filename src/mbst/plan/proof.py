"""Proof that planning pays: planned vs naive campaign of equal cost on the bench.

Both campaigns are run on the virtual bench (the same rig, the same sensor
noise levels as the planning config), identified by the same cascade (the
stages and fitting of ``mbst.identify``, restricted to the plan's unknowns),
and compared on

- the relative errors of every unknown parameter against the bench truth;
- FIT % on a shared validation set: every control test of both campaigns
  (each model predicts every control, so neither is judged only on its own
  scenarios).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from mbst.bench import KNOWN, BenchRecipe
from mbst.campaign import TestSpec, read_campaign, write_campaign
from mbst.fitting import FitProblem, channel_scales, prepare_test, solve
from mbst.identify import IdentifySettings, correlate
from mbst.plan.config import PlanConfig
from mbst.plan.inputs import profile
from mbst.plan.selection import Plan
from mbst.plan.sensitivity import Sensitivity
from mbst.plan.sensors import INPUT_SENSOR, logged_channels, sensor_signals
from mbst.systems import eps
from mbst.systems.eps_channels import SYSTEM_NAME
from mbst.systems.eps_params import PARAM_INDEX


def campaign_tests(sens: Sensitivity, plan: Plan) -> list[tuple[str, int, str]]:
    """(test id, cell, role) of every test of a plan, in cell order, controls last."""
    out = []
    for c in sorted(plan.tests):
        cell = sens.cells[c]
        for r in range(plan.tests[c]):
            suffix = f"_r{r + 1}" if plan.tests[c] > 1 else ""
            out.append((f"{cell.scenario_id}_{cell.input_id}{suffix}", c, "identification"))
    for c in plan.controls:
        cell = sens.cells[c]
        out.append((f"{cell.scenario_id}_{cell.input_id}_ctrl", c, "control"))
    return out


try:  # the EPS family's cascade (moved out of identify.py by the model-definition refactor)
    from mbst.systems.eps_model import CASCADE, OFFSET_CHANNEL
except ImportError:  # pragma: no cover - older layout
    from mbst.identify import CASCADE, OFFSET_CHANNEL

TAU_S = IdentifySettings().tau_s  # the identification's default filter


def bench_tests(cfg: PlanConfig, sens: Sensitivity, plan: Plan, p_true: np.ndarray,
                seed: int) -> list[tuple[TestSpec, pd.DataFrame]]:
    """Noisy logged tests of a plan on the virtual rig ``p_true`` (deterministic in seed)."""
    noise = {s.name: s.noise for s in cfg.sensors}
    out = []
    for i, (tid, c, role) in enumerate(campaign_tests(sens, plan)):
        cell = sens.cells[c]
        rng = np.random.default_rng([seed, i])
        t, ang = profile(cell.input, cfg.sample_rate_hz)
        raw = eps.simulate_raw(cell.scenario, cell.motor, t, ang, p_true)
        sig = sensor_signals(raw, p_true, cell.scenario, ang)
        cols = {"time_s": t}
        for ch in logged_channels(cell.scenario, plan.logged):
            cols[ch] = sig[ch] + noise.get(ch, 0.0) * rng.standard_normal(len(t))
        spec = TestSpec(id=tid, file=f"tests/{tid}.csv", scenario=cell.scenario,
                        input=dict(cell.input), motor=cell.motor, role=role)
        out.append((spec, pd.DataFrame(cols)))
    return out


@dataclass
class ProofResult:
    errors: pd.DataFrame  # parameter, truth, planned, naive, rel errors, predicted std
    fit: pd.DataFrame  # test, channel, planned, naive, truth FIT %
    summary: dict


def proof_rig(cfg: PlanConfig) -> np.ndarray:
    """The bench rig of the proof: unknowns drawn uniformly in ln θ over their ranges.

    Drawn (seeded by ``proof.seed``), not the model defaults the identification
    starts from: a parameter that a campaign cannot see would otherwise look
    well identified merely because the start was right.
    """
    p = BenchRecipe(effects=list(cfg.proof_effects), seed=cfg.proof_seed).true_params()
    for k, v in cfg.known.items():
        p[PARAM_INDEX[k]] = v
    rng = np.random.default_rng([cfg.proof_seed, 7])
    for u in cfg.unknowns:
        p[PARAM_INDEX[u.name]] = float(np.exp(rng.uniform(np.log(u.low), np.log(u.high))))
    return p


@dataclass
class _Identified:
    params: np.ndarray
    std_error: dict[str, float]
    prepared: dict
    warnings: list[str]
    wall_s: float


def _cascade(cfg: PlanConfig, camp, p_true: np.ndarray, seed: int) -> _Identified:
    """The identification cascade (``mbst.identify.CASCADE`` order) over the plan's unknowns.

    The plan assumes every other parameter known, so the proof fixes them at the
    rig's values (``mbst identify`` would free the whole base model, which no plan
    of a subset of unknowns is meant to identify). Unknowns start at the centre
    of their ranges, offsets at zero; each stage frees the unknowns its scenario
    isolates (plus those of skipped stages) and the offsets of new channels.
    """
    t0 = time.perf_counter()
    unknown = cfg.unknown_names
    in_cascade = {n for _, iso in CASCADE for n in iso}
    prepared = {s.id: prepare_test(camp, s, TAU_S) for s in camp.tests}
    ids = [prepared[s.id] for s in camp.identification_tests()]
    scales = channel_scales(ids)
    p = p_true.copy()
    for u in cfg.unknowns:
        p[PARAM_INDEX[u.name]] = u.nominal
    for n in OFFSET_CHANNEL:
        p[PARAM_INDEX[n]] = 0.0
    rng = np.random.default_rng([seed, 11])
    fixed: set[str] = set()
    carried = [n for n in unknown if n not in in_cascade]
    std: dict[str, float] = {}
    warnings: list[str] = []
    for scenario, isolates in CASCADE:
        tests = [pt for pt in ids if pt.scenario == scenario]
        wanted = carried + [n for n in isolates if n in unknown and n not in fixed]
        if not tests:
            carried = wanted
            continue
        chans = {ch for pt in tests for ch in pt.measured}
        free = list(dict.fromkeys(wanted + [n for n, ch in OFFSET_CHANNEL.items()
                                            if ch in chans and n not in fixed]))
        carried = []
        if not free:
            continue
        prob = FitProblem(tests, {pt.id: list(pt.measured) for pt in tests}, free, p, scales,
                          decimate=2)
        starts = [p.copy()]
        for _ in range(cfg.proof_multistart - 1):
            q = p.copy()
            for n in free:
                if not n.startswith("offset."):
                    q[PARAM_INDEX[n]] *= float(np.exp(rng.uniform(-0.5, 0.5)))
            starts.append(q)
        fr = solve(prob, starts, max_nfev=40)
        p = fr.p
        fixed.update(free)
        std.update(fr.std_error)
    warnings += [f"'{n}' not identified: no test of a scenario that informs it" for n in carried]
    return _Identified(p, std, prepared, warnings, time.perf_counter() - t0)


def _identify(cfg: PlanConfig, sens: Sensitivity, plan: Plan, p_true: np.ndarray, seed: int,
              folder: Path, name: str) -> _Identified:
    tests = bench_tests(cfg, sens, plan, p_true, seed)
    camp_dir = write_campaign(folder / name, name=name, system=SYSTEM_NAME,
                              known=dict(cfg.known or KNOWN), tests=tests,
                              extra={"generated_by": "mbst plan (proof)", "seed": seed},
                              overwrite=True)
    return _cascade(cfg, read_campaign(camp_dir), p_true, seed)


def run_proof(cfg: PlanConfig, sens: Sensitivity, planned: Plan, naive: Plan, folder: Path,
              predicted: dict[str, np.ndarray] | None = None, progress: bool = False
              ) -> ProofResult:
    """Bench both campaigns, identify both, compare errors and control FIT.

    Parameters
    ----------
    folder
        Where the two bench campaigns are written (``planned/``, ``naive/``).
    predicted
        Predicted relative std per unknown for ``planned`` and ``naive`` (centre
        of the ranges), reported beside the errors.
    """
    p_true = proof_rig(cfg)
    results = {}
    for label, plan in (("planned", planned), ("naive", naive)):
        if progress:
            print(f"plan: proof — identifying the {label} campaign", flush=True)
        results[label] = _identify(cfg, sens, plan, p_true, cfg.proof_seed, folder, label)
    rows = []
    for k, u in enumerate(cfg.unknowns):
        i = PARAM_INDEX[u.name]
        row = {"parameter": u.name, "truth": p_true[i]}
        for label, res in results.items():
            row[label] = res.params[i]
            row[f"{label}_relative_error"] = abs(res.params[i] - p_true[i]) / abs(p_true[i])
            std = res.std_error.get(u.name, float("nan"))
            row[f"{label}_reported_relative_std"] = std / abs(res.params[i]) if (
                res.params[i] != 0) else float("nan")
            if predicted is not None:
                row[f"{label}_predicted_relative_std"] = float(predicted[label][k])
        rows.append(row)
    errors = pd.DataFrame(rows)

    # shared validation: every control test of both campaigns, predicted by both models
    fit_rows = []
    for owner, res in results.items():
        controls = [res.prepared[s.id] for s in
                    read_campaign(folder / owner, load_data=False).control_tests()]
        per_model = {lab: correlate(controls, r.params)[0] for lab, r in results.items()}
        per_model["truth"] = correlate(controls, p_true)[0]
        base = per_model["planned"][["test", "channel"]].copy()
        base["campaign"] = owner
        for lab, df in per_model.items():
            base[f"{lab}_fit_percent"] = df["fit_percent"].to_numpy()
        fit_rows.append(base)
    fit = pd.concat(fit_rows, ignore_index=True)
    summary = {
        "median_relative_error": {lab: float(errors[f"{lab}_relative_error"].median())
                                  for lab in results},
        "max_relative_error": {lab: float(errors[f"{lab}_relative_error"].max())
                               for lab in results},
        "rms_log_error": {lab: float(np.sqrt(np.mean(np.log(
            np.maximum(errors[lab].abs(), 1e-300) / errors["truth"].abs()) ** 2)))
            for lab in results},
        "mean_control_fit_percent": {lab: float(fit[f"{lab}_fit_percent"].mean())
                                     for lab in (*results, "truth")},
        "identification_wall_s": {lab: r.wall_s for lab, r in results.items()},
        "tests": {lab: len(read_campaign(folder / lab, load_data=False).tests)
                  for lab in results},
        "warnings": {lab: r.warnings for lab, r in results.items()},
    }
    summary["planning_pays"] = bool(
        summary["rms_log_error"]["planned"] < summary["rms_log_error"]["naive"]
        and summary["mean_control_fit_percent"]["planned"]
        > summary["mean_control_fit_percent"]["naive"])
    return ProofResult(errors, fit, summary)


__all__ = ["INPUT_SENSOR", "ProofResult", "bench_tests", "campaign_tests", "run_proof"]
