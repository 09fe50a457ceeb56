"""What ``mbst identify`` writes: parameters, correlation tables, figures and the page."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mbst.identify.cascade import HELD_STAGE, IdentifyResult, IdentifySettings, identify
from mbst.identify.record import fit_record
from mbst.io.campaign import Campaign
from mbst.io.outputs import atomic_output_dir, write_json, write_markdown
from mbst.report import plots
from mbst.report.families import family_report


def params_record(result: IdentifyResult, settings: IdentifySettings) -> dict:
    """``params.json``: values, bounds, std errors, stage and flags of every parameter."""
    stage_of, std, at_bound, ident = {}, {}, {}, {}
    for st in result.stages:
        for n in st.free:
            stage_of[n] = st.scenario
            std[n] = st.std_error[n]
            at_bound[n] = st.at_bound[n]
            ident[n] = st.identifiable[n]
    for n, sd in result.preid.get("held", {}).items():
        stage_of.setdefault(n, HELD_STAGE)
        std.setdefault(n, sd)
        at_bound.setdefault(n, False)
        ident.setdefault(n, bool(np.isfinite(sd)))
    params = {}
    for i, spec in enumerate(result.model.param_specs):
        if spec.kind == "effect" and spec.name not in stage_of:
            continue
        params[spec.name] = {
            "value": float(result.params[i]),
            "unit": spec.unit,
            "kind": spec.kind,
            "component": spec.component,
            "lower": spec.lower,
            "upper": spec.upper,
            "std_error": std.get(spec.name),
            "stage": stage_of.get(spec.name, "known" if spec.kind == "known" else "fixed"),
            "at_bound": at_bound.get(spec.name, False),
            "identifiable": ident.get(spec.name),
        }
    for check in result.known_checks:
        if check.name in params:
            params[check.name]["stated"] = check.record()
    return {
        "format": "mbst-params/1",
        "campaign": result.campaign,
        "settings": {"tau_s": settings.tau_s, "seed": settings.seed,
                     "multistart": settings.multistart, "max_nfev": settings.max_nfev,
                     "decimate": settings.decimate,
                     "joint_refinement": settings.joint_refinement},
        "params": params,
        "stages": [
            {"scenario": st.scenario, "tests": st.tests, "free": st.free, "cost": st.cost,
             "n_residuals": st.n_residuals, "start_costs": st.starts, "wall_s": st.wall_s,
             "correlation_matrix": st.correlation}
            for st in result.stages
        ],
        "preidentification": result.preid,
        "warnings": result.warnings,
        "wall_s": result.wall_s,
        "system": result.model.name,
        "vector": result.model.as_dict(result.params),
    }


def write_identify_outputs(result: IdentifyResult, out: Path, settings: IdentifySettings,
                           campaign: Campaign | None = None) -> None:
    """Everything ``mbst identify`` writes; with ``campaign`` also ``base_fit.json``, the
    cascade ``mbst discover --base-fit`` starts from instead of fitting it again."""
    write_json(out / "params.json", params_record(result, settings))
    if campaign is not None:
        write_json(out / "base_fit.json", fit_record(result, settings, campaign))
    result.correlation.to_csv(out / "correlation.csv", index=False, float_format="%.6g")
    result.identification_fit.to_csv(out / "identification_fit.csv", index=False,
                                     float_format="%.6g")
    figdir = out / "figures"
    figdir.mkdir(parents=True, exist_ok=True)
    controls = [result.prepared[t] for t in result.correlation["test"].unique()]
    shown = controls or [result.prepared[t] for t in result.identification_fit["test"].unique()]
    plots.time_histories(shown, {"base": result.twins}, figdir / "time_histories.png")
    plots.hysteresis_loops(list(result.prepared.values()), {"base": result.twins},
                           figdir / "hysteresis.png")
    plots.residuals(shown, {"base": result.twins}, figdir / "residuals.png")
    extra = family_report(result.model.name)(result, figdir)
    write_markdown(out / "identify.md", markdown_summary(result) + "".join(f"{x}\n" for x in extra))


def markdown_summary(result: IdentifyResult) -> str:
    lines = [f"# Identification of `{result.campaign}`", "",
             f"Cascade of {len(result.stages)} stages in {result.wall_s:.1f} s.", "",
             "| stage | tests | free parameters | cost |", "|---|---|---|---|"]
    for st in result.stages:
        lines.append(f"| {st.scenario} | {', '.join(st.tests)} | {len(st.free)} | {st.cost:.4g} |")
    lines += ["", "## Held-out control tests", ""]
    if len(result.correlation):
        lines += ["| test | channel | FIT % | NRMSE | r | R² | max abs error |",
                  "|---|---|---|---|---|---|---|"]
        for _, r in result.correlation.iterrows():
            lines.append(f"| {r.test} | {r.channel} | {r.fit_percent:.1f} | {r.nrmse:.4f} | "
                         f"{r.pearson_r:.4f} | {r.r2:.4f} | {r.max_abs_error:.4g} |")
    else:
        lines.append("No control test in this campaign.")
    lines += known_section(result)
    lines += ["", "## Warnings", ""]
    lines += [f"- {w}" for w in result.warnings] or ["- none"]
    return "\n".join(lines) + "\n"


def known_section(result: IdentifyResult) -> list[str]:
    """The stated known values against what the data say of them (priors and fixed values)."""
    if not result.known_checks:
        return []
    lines = ["", "## Known values against the data", "",
             "A prior `{value, sigma}` is fitted with its σ; a value held fixed is checked by "
             "a short refit of its stage with it freed beside the stage's parameters (the "
             "fit itself keeps the stated value). Beyond 3 σ the data contradict it: it is "
             "reported here, never changed silently.", "",
             "| parameter | stated | from the data | stage | distance | verdict |",
             "|---|---|---|---|---|---|"]
    for c in result.known_checks:
        stated = (f"{c.value:.4g} ± {c.sigma:.3g}" if c.sigma is not None
                  else f"{c.value:.4g} (fixed)")
        verdict = f"**{c.verdict}**" if c.contradicted else c.verdict
        lines.append(f"| {c.name} [{c.unit}] | {stated} | {c.fitted:.4g} ± {c.std_error:.3g} | "
                     f"{c.stage} | {abs(c.z):.1f} σ | {verdict} |")
    return lines


def run_identify(campaign: Campaign, out_dir: str | Path,
                 settings: IdentifySettings | None = None) -> IdentifyResult:
    """``mbst identify``: fit, correlate and write everything into ``out_dir`` atomically."""
    settings = settings or IdentifySettings()
    result = identify(campaign, settings)
    with atomic_output_dir(out_dir) as tmp:
        write_identify_outputs(result, tmp, settings, campaign)
    return result
