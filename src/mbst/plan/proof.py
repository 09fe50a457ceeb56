"""Proof that planning pays: planned vs naive campaign of equal cost on the bench.

Both campaigns are run on the virtual bench (the same rig, the same sensor
noise levels as the planning config), identified by the same cascade (the
stages and fitting of ``mbst.identify.cascade``, restricted to the plan's unknowns),
and compared on

- the relative errors of every unknown parameter against the bench truth;
- FIT % on a shared validation set: every control test of both campaigns
  (each model predicts every control, so neither is judged only on its own
  scenarios), averaged over the channels both campaigns logged (a model
  cannot know the offset of a sensor its campaign never had) that carry
  signal (the true model's FIT ≥ 50 %).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from mbst.identify.cascade import IdentifySettings, correlate, run_cascade
from mbst.io.campaign import TestSpec, read_campaign, write_campaign
from mbst.plan.config import PlanConfig
from mbst.plan.inputs import profile
from mbst.plan.selection import Plan
from mbst.plan.sensitivity import Sensitivity
from mbst.plan.sensors import INPUT_SENSOR, logged_channels, sensor_signals
from mbst.systems.eps import simulate as eps
from mbst.systems.eps.bench import KNOWN, BenchRecipe
from mbst.systems.eps.channels import SYSTEM_NAME
from mbst.systems.eps.model import EPS_MODEL
from mbst.systems.eps.params import PARAM_INDEX


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


TAU_S = IdentifySettings().tau_s  # the identification's default filter
# Both campaigns come from the model's own structure, so a stage that ends far above its
# noise is in a wrong basin of the friction cost surface, not short of an effect: restart.
PROOF_EXTRA_STARTS = 8
# a control channel the true model predicts worse than this is noise around an offset
SIGNAL_FIT_PERCENT = 50.0


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
    """``mbst identify``'s cascade restricted to the plan's unknowns.

    The plan assumes every other parameter known, so the proof holds them at the
    rig's values (``mbst identify`` would free the whole base model, which no plan
    of a subset of unknowns is meant to identify). Unknowns start at the centre
    of their ranges (pre-identification may move them, as in ``mbst identify``),
    offsets at zero.
    """
    t0 = time.perf_counter()
    p = p_true.copy()
    for u in cfg.unknowns:
        p[PARAM_INDEX[u.name]] = u.nominal
    for n in EPS_MODEL.offset_channels:
        p[PARAM_INDEX[n]] = 0.0
    # the ranges are what the planner knew before the campaign (its bits count from them);
    # its information is joint over all tests, hence the joint refit after the stages
    prior = ({u.name: (u.nominal, u.prior_std_log) for u in cfg.unknowns}
             if cfg.proof_range_prior else None)
    settings = IdentifySettings(tau_s=TAU_S, seed=seed, multistart=cfg.proof_multistart,
                                joint_refinement=cfg.proof_joint_refinement,
                                extra_starts=PROOF_EXTRA_STARTS, prior=prior)
    fit = run_cascade(camp, settings, base=p, only=set(cfg.unknown_names))
    std = {n: v for st in fit.stages for n, v in st.std_error.items()}
    return _Identified(fit.params, std, fit.prepared, fit.warnings, time.perf_counter() - t0)


def _identify(cfg: PlanConfig, sens: Sensitivity, plan: Plan, p_true: np.ndarray, seed: int,
              folder: Path, name: str) -> _Identified:
    tests = bench_tests(cfg, sens, plan, p_true, seed)
    camp_dir = write_campaign(folder / name, name=name, system=SYSTEM_NAME,
                              known=cfg.campaign_known(KNOWN), priors=cfg.stated_priors(),
                              tests=tests,
                              extra={"generated_by": "mbst plan (proof)", "seed": seed},
                              overwrite=True)
    return _cascade(cfg, read_campaign(camp_dir), p_true, seed)


def _rms_log_error(errors: pd.DataFrame, label: str) -> float:
    return float(np.sqrt(np.mean(np.log(
        np.maximum(errors[label].abs(), 1e-300) / errors["truth"].abs()) ** 2)))


def run_proof(cfg: PlanConfig, sens: Sensitivity, planned: Plan, naive: Plan, folder: Path,
              predicted: dict[str, np.ndarray] | None = None, progress: bool = False,
              promised: list[str] | None = None) -> ProofResult:
    """Bench both campaigns, identify both, compare errors and control FIT.

    Parameters
    ----------
    folder
        Where the two bench campaigns are written (``planned/``, ``naive/``).
    predicted
        Predicted relative std per unknown for ``planned`` and ``naive`` (centre
        of the ranges), reported beside the errors.
    promised
        The unknowns the plan predicts within the target everywhere in the
        ranges: the verdict compares the two campaigns on these. An unknown no
        affordable campaign identifies (the plan says so) ends wherever the
        input error pushes it, in either campaign, and would decide by chance.
    """
    p_true = proof_rig(cfg)
    results = {}
    for label, plan in (("planned", planned), ("naive", naive)):
        if progress:
            print(f"plan: proof — identifying the {label} campaign", flush=True)
        results[label] = _identify(cfg, sens, plan, p_true, cfg.proof_seed, folder, label)
    errors = _parameter_errors(cfg, results, p_true, predicted)
    fit = _control_fit(results, folder, p_true)
    summary = _comparison(errors, fit, results, folder)
    promised = list(cfg.unknown_names if promised is None else promised)
    summary.update(_verdict(errors, summary, results, promised, predicted is not None))
    return ProofResult(errors, fit, summary)


def _parameter_errors(cfg: PlanConfig, results: dict[str, _Identified], p_true: np.ndarray,
                      predicted: dict[str, np.ndarray] | None) -> pd.DataFrame:
    """Per unknown: the truth, each campaign's estimate, its relative error, the relative
    std the fit reports and (if given) the one the plan predicted."""
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
    return pd.DataFrame(rows)


def _control_fit(results: dict[str, _Identified], folder: Path, p_true: np.ndarray
                 ) -> pd.DataFrame:
    """FIT % of each model and the truth on the shared validation set (every control test of
    both campaigns), each channel marked whether the means compare it."""
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
    # a model knows a sensor's offset only if its campaign logged that sensor: the means
    # compare the channels both campaigns logged (else a never-seen current offset decides),
    # and only where the channel carries signal: the true model's own FIT is at least
    # SIGNAL_FIT_PERCENT (a blocked rack's position is its offset plus noise)
    logged = [{ch for pt in r.prepared.values() for ch in pt.measured} for r in results.values()]
    fit["compared"] = (fit["channel"].isin(set.intersection(*logged))
                       & (fit["truth_fit_percent"] >= SIGNAL_FIT_PERCENT))
    return fit


def _comparison(errors: pd.DataFrame, fit: pd.DataFrame, results: dict[str, _Identified],
                folder: Path) -> dict:
    """The summary's side-by-side figures: parameter errors, control FIT on the compared
    channels, wall time, tests and warnings of each campaign."""
    shared = fit[fit["compared"]]
    return {
        "median_relative_error": {lab: float(errors[f"{lab}_relative_error"].median())
                                  for lab in results},
        "max_relative_error": {lab: float(errors[f"{lab}_relative_error"].max())
                               for lab in results},
        "rms_log_error": {lab: _rms_log_error(errors, lab) for lab in results},
        "mean_control_fit_percent": {lab: float(shared[f"{lab}_fit_percent"].mean())
                                     for lab in (*results, "truth")},
        "compared_channels": sorted(set(shared["channel"])),
        "identification_wall_s": {lab: r.wall_s for lab, r in results.items()},
        "tests": {lab: len(read_campaign(folder / lab, load_data=False).tests)
                  for lab in results},
        "warnings": {lab: r.warnings for lab, r in results.items()},
    }


def _verdict(errors: pd.DataFrame, comparison: dict, results: dict[str, _Identified],
             promised: list[str], with_prediction: bool) -> dict:
    """The summary's verdict: errors on the promised unknowns, the prediction's check and
    whether planning pays (promised parameters and control FIT both better)."""
    kept = errors["parameter"].isin(promised)
    rms = {lab: _rms_log_error(errors[kept], lab) if kept.any() else 0.0 for lab in results}
    out = {"promised": promised, "rms_log_error_promised": rms}
    if with_prediction:
        # the check of the prediction: realised error within twice the predicted σ
        ok = errors["planned_relative_error"] <= 2.0 * errors["planned_predicted_relative_std"]
        out["confirmed_within_factor_two"] = sorted(errors.loc[ok, "parameter"])
    fit = comparison["mean_control_fit_percent"]
    out["planning_pays"] = bool(
        out["rms_log_error_promised"]["planned"] < out["rms_log_error_promised"]["naive"]
        and fit["planned"] > fit["naive"])
    return out


__all__ = ["INPUT_SENSOR", "ProofResult", "bench_tests", "campaign_tests", "run_proof"]
