"""What ``mbst discover`` writes: ``discovery.json`` and the tables, figures and page beside it."""

from __future__ import annotations

import json
import logging
import math
from pathlib import Path

import numpy as np
import pandas as pd

from mbst.core.filtering import FAST_HZ
from mbst.core.model import ModelDefinition
from mbst.discovery.acceptance import FALSE_ALARM_RATE
from mbst.discovery.pipeline import (
    FORMAT,
    DiscoverSettings,
    DiscoveryResult,
    controls_below_base,
    discover,
)
from mbst.discovery.residuals import dominant_regions
from mbst.discovery.rivals import label
from mbst.discovery.rounds.resolution import Resolution
from mbst.discovery.rounds.stickslip import HELD_OUT_FAMILIES, MIN_BASE_MISFIT
from mbst.discovery.rounds.unexplained import signature_record
from mbst.discovery.signature import ChannelSignature
from mbst.io.campaign import Campaign
from mbst.io.outputs import atomic_output_dir, write_json, write_markdown
from mbst.report import discovery_figures as figures
from mbst.report.bounds import bound_lines, parameters_on_bounds

log = logging.getLogger(__name__)


# --------------------------------------------------------------------------------------
# outputs
# --------------------------------------------------------------------------------------
def _control_fit(df: pd.DataFrame, model: str) -> dict:
    out: dict[str, dict[str, float]] = {}
    for r in df[df.model == model].itertuples():
        out.setdefault(r.test, {})[r.channel] = round(float(r.fit_percent), 3)
    return out


def _model_params(p: np.ndarray, effects: list[str], model: ModelDefinition
                  ) -> dict[str, float]:
    active = {n for k in effects for n in model.effects[k].free}
    return {s.name: float(p[i]) for i, s in enumerate(model.param_specs)
            if s.kind in ("base", "offset", "known") or s.name in active}


def _bound_rows(result: DiscoveryResult) -> list[dict]:
    stage_free = (getattr(result, "stages", None) or {}).get("stage_free", {})
    if not stage_free:
        return []
    free = [n for names in stage_free.values() for n in names]
    return parameters_on_bounds(result.base.model, free, result.base.params,
                                result.extended_params,
                                (getattr(result.base, "preid", None) or {}).get("upper"))


def _bound_section(result: DiscoveryResult) -> list[str]:
    rows = _bound_rows(result)
    return bound_lines(rows, not np.array_equal(result.extended_params, result.base.params)) \
        if rows else []


def discovery_record(result: DiscoveryResult) -> dict:
    """``discovery.json`` in the format of campaign-format.md."""
    # an ``unexplained`` finding adds no catalogue parameter to the extended model
    keys = [k for f in result.findings
            if (k := f"{f.effect}:{f.component}") in result.base.model.effects]
    return {
        "format": FORMAT,
        "campaign": result.campaign,
        "base": {"params": _model_params(result.base.params, [], result.base.model),
                 "control_fit_percent": _control_fit(result.comparison, "base")},
        "findings": [f.record() for f in result.findings],
        "extended": {"params": _model_params(result.extended_params, keys, result.base.model),
                     "control_fit_percent": _control_fit(result.comparison, "extended")},
        "gain": result.gain,
        "acceptance": {"min_relative_gain": result.settings.min_relative_gain,
                       # None: from the campaign (each round's ``aic_drop_needed``)
                       "min_aic_drop": result.settings.min_aic_drop,
                       "false_alarm_rate": FALSE_ALARM_RATE,
                       "max_effects": result.settings.max_effects},
        "rounds": result.rounds,
        "residual_regions": dominant_regions(result.locations, 0.0)[:8],
        "sparse_regression": result.sparse,
        "neural_residual": result.neural,
        "comparison_mean_fit_percent": {
            m: round(float(v), 3)
            for m, v in result.comparison.groupby("model", sort=False)["fit_percent"].mean().items()
        },
        "resolution": [r.record() for r in result.resolution],
        "parameters_on_bounds": _bound_rows(result),
        # what `mbst plan --resolve` designs the next tests with
        "stages": result.stages,
        # what the extended model's residual correlates with, channel by channel
        "unexplained": [signature_record(s) for s in result.signatures],
        "failures": list(result.failures),
        "timings_s": {k: round(v, 2) for k, v in result.timings.items()},
        "wall_s": round(result.wall_s, 2),
        "system": result.base.model.name,
        "vector": result.base.model.as_dict(result.extended_params),
    }


def write_discover_outputs(result: DiscoveryResult, out: Path) -> None:
    """The answer first; then every table, figure and the page, each on its own.

    A failure in one of them is logged, listed under "What failed" in
    ``discovery.md`` and in ``discovery.json`` — it never loses the answer.
    """
    failures = result.failures
    write_json(out / "discovery.json", discovery_record(result))
    if result.benchmark is not None:
        _guarded("benchmark.json", lambda: write_json(out / "benchmark.json", result.benchmark),
                 failures)
    _guarded("comparison.csv", lambda: result.comparison.to_csv(
        out / "comparison.csv", index=False, float_format="%.4f"), failures,
        out / "comparison.csv")
    _guarded("structure_test.csv", lambda: _structure_table(result).to_csv(
        out / "structure_test.csv", index=False, float_format="%.6g"), failures)
    _guarded("residual_locations.csv", lambda: pd.DataFrame(result.locations).to_csv(
        out / "residual_locations.csv", index=False, float_format="%.4f"), failures)
    _guarded("resolution.csv", lambda: resolution_table(result.resolution).to_csv(
        out / "resolution.csv", index=False, float_format="%.6g"), failures,
        out / "resolution.csv")
    figdir = out / "figures"
    figdir.mkdir(parents=True, exist_ok=True)
    figures.write_all(result, figdir, failures)
    try:
        page = markdown_summary(result)
    except Exception as exc:  # the page is a view of the answer: fall back to a plain one
        _record_failure("discovery.md", exc, failures)
        page = fallback_summary(result)
    write_markdown(out / "discovery.md", page)
    if failures:  # the answer again, now with what failed beside it
        write_json(out / "discovery.json", discovery_record(result))


def _structure_table(result: DiscoveryResult) -> pd.DataFrame:
    rows = [{"round": r["round"], **{k: v for k, v in c.items() if k != "headline"},
             "headline": json.dumps(c["headline"])} for r in result.rounds
            for c in r["candidates"]]
    return pd.DataFrame(rows)


def _record_failure(what: str, exc: BaseException, failures: list[str]) -> None:
    msg = f"{what}: {type(exc).__name__}: {exc}"
    log.warning("could not write %s", msg, exc_info=exc)
    failures.append(msg)


def _guarded(what: str, write, failures: list[str], required: Path | None = None) -> None:
    """Run one writer; on failure record it (and leave a stub where the workflow needs a file)."""
    try:
        write()
    except Exception as exc:  # one table or figure must never lose the answer
        _record_failure(what, exc, failures)
        if required is not None:
            required.write_text(f"# not written: {type(exc).__name__}: {exc}\n")


def fallback_summary(result: DiscoveryResult) -> str:
    """The findings and what failed, when the full page cannot be drawn up."""
    lines = [f"# Discovery on `{result.campaign}`", ""]
    lines += [f"- **{f.effect} / {_where(f)}** ({f.confidence:.2f}): {f.evidence}"
              for f in result.findings] or ["No finding."]
    return "\n".join(lines + failure_lines(result.failures)) + "\n"


def _size_text(f, headline: str, value: float) -> str:
    """One parameter of a finding, with its standard error where these tests do not
    measure it (``discovery/precision.py``)."""
    if headline not in f.size_not_measured:
        return f"{headline} = {value:.4g}"
    return f"{headline} = {value:.4g} (± {f.size_std_error[headline]:.2g}: not measured)"


def _where(f) -> str:
    """A finding's component, with the parts of its body it could sit in as well."""
    return " or ".join([f.component, *f.indistinguishable_from]) or "–"


def failure_lines(failures: list[str]) -> list[str]:
    if not failures:
        return []
    return ["", "## What failed", "",
            "The answer above stands; these rounds, evidence or report parts could not be made "
            "(details in the log):", ""] + [f"- {f}" for f in failures]


def markdown_summary(result: DiscoveryResult) -> str:
    lines = [f"# Discovery on `{result.campaign}`", "",
             f"{len(result.rounds)} round(s) of the structure test in {result.wall_s:.0f} s.", ""]
    if result.findings:
        lines += ["| # | effect | component | parameters | confidence |", "|---|---|---|---|---|"]
        for i, f in enumerate(result.findings, 1):
            pars = ", ".join(_size_text(f, k, v) for k, v in f.parameters.items())
            if f.effect == "unexplained" and f.signature:
                # a refitted reality says its size; a signature, what it follows
                pars = (f.signature["reading"] if f.signature.get("refitted") == "physics"
                        else f"{f.signature['kind']} in {f.signature['quantity']}")
            alt = "".join(f" (or {label(a['effect'], a['component'])}?)"
                          for a in f.alternatives)
            lines.append(f"| {i} | {f.effect}{alt} | {_where(f)} | {pars} | "
                         f"{f.confidence:.2f} |")
        lines += [""] + [f"- **{f.effect} / {_where(f)}**: {f.evidence}"
                         for f in result.findings]
        lines += controls_below_base_lines(result)
    elif any(f.startswith("structure round") for f in result.failures):
        lines.append("No finding: a structure round failed before it could name anything "
                     "(\"What failed\", below), so this is not a statement that the base "
                     "model is at the noise floor.")
    elif any(r.get("rival_declined") for r in result.rounds):
        lines.append("No finding: no catalogue effect is named. What a stage's winner "
                     "took was matched as well by a reality outside the catalogue (a sensor, "
                     "a drift or the stated values: below), so the base model is not at the "
                     "noise floor there.")
    else:
        lines.append("No finding: the base model explains the identification tests down to "
                     "the noise floor of the catalogue" + (
                         " (of what these tests can resolve: see below)."
                         if result.resolution else "."))
    for r in result.rounds:
        for gone in r.get("rival_declined", []):  # a winner a reality outside the catalogue matched
            lines += ["", f"Round {r['round']}, not named: {gone['reason']}."]
        if r.get("kind") == "backward":
            lines += ["", f"{r['reason'][0].upper()}{r['reason'][1:]}."]
        elif r.get("reason"):
            lines += ["", f"Round {r['round']} stopped: {r['reason']}."]
    lines += screened_out_lines(result.rounds)
    lines += untested_lines(result.rounds)
    lines += _bound_section(result)
    lines += signature_lines(result)
    if result.resolution:
        lines += resolution_lines(result)
    lines += control_lines(result.comparison)
    lines += stick_slip_held_out_lines(result.gain.get("stick_slip_envelope_held_out", {}))
    if result.benchmark and "published" in result.benchmark:
        lines += benchmark_table(result.benchmark)
    elif result.benchmark and "tests" in result.benchmark:
        lines += windowed_benchmark_lines(result.benchmark)
    lines += failure_lines(result.failures)
    return "\n".join(lines) + "\n"


def controls_below_base_lines(result: DiscoveryResult) -> list[str]:
    """The warning an engineer needs where the extension does worse than the base on the
    held-out controls: the names were fitted on the identification tests and do not carry
    over (a realistic rig with a 20 mN·m motor cogging, outside the catalogue: rack power
    law and Stribeck named at 0.28 and 0.02, control FIT 95.6 → 91.8 %). Said only: the
    controls never choose a finding or its confidence."""
    below = controls_below_base(result.findings, result.comparison)
    if below is None:
        return []
    stick_slip = any(f.aic_delta is None for f in result.findings
                     if f.effect == "stribeck_friction")
    return ["", f"**Held out, the extension does worse:** on the control tests the extended "
                f"model's mean FIT is {below[1]:.1f} % against the base model's {below[0]:.1f} "
                "%. The named effects were fitted on the identification tests and do not "
                "carry over to these: read the names with care. The misfit may lie outside "
                "the catalogue (what the catalogue leaves, below), or these tests may not pin "
                "the sizes" + (" (a stick-slip's FIT can fall where its model is right: its "
                               "own measure is under the control table)" if stick_slip else "")
                + "."]


def control_lines(comparison: pd.DataFrame) -> list[str]:
    """The control FIT table, one row per test and channel the comparison has: a dash
    where a family has no FIT, a channel no family has one for (constant in its test)
    listed under it instead of a row of blanks, the means the summary prints beneath."""
    lines = ["", "## Control tests (held out): FIT %", ""]
    if comparison.empty:
        return lines + ["No control test: nothing held out to measure the gain on."]
    # the rows the comparison has, in its order (a pivot's product of tests and channels
    # would add channels a test does not log)
    rows = pd.MultiIndex.from_tuples(list(dict.fromkeys(zip(comparison.test,
                                                            comparison.channel))))
    wide = comparison.set_index(["test", "channel", "model"])["fit_percent"] \
        .unstack("model").reindex(rows)
    models = list(dict.fromkeys(comparison.model))
    scored = wide[models].notna().any(axis=1)
    lines += ["| test | channel | " + " | ".join(models) + " |",
              "|---|---|" + "---|" * len(models)]
    for (t, ch), row in wide[scored].iterrows():
        lines.append(f"| {t} | {ch} | " + " | ".join(
            f"{row[m]:.1f}" if np.isfinite(row[m]) else "–" for m in models) + " |")
    means = wide[scored][models].mean()
    lines += ["", "Mean over the rows above: " + ", ".join(
        f"{m} {means[m]:.1f} %" for m in models if np.isfinite(means[m])) + "."]
    blank = [f"{t} {ch}" for t, ch in wide.index[~scored.to_numpy()]]
    if blank:
        lines.append(f"No FIT in any family (a channel constant in its test has none, nor "
                     f"a twin that could not be simulated): {', '.join(blank)}.")
    return lines


def stick_slip_held_out_lines(envelopes: dict[str, dict]) -> list[str]:
    """A stick-slip finding's gain on the controls in its own measure (the fast envelope),
    beside the FIT that cannot show it."""
    lines = []
    for stage, row in envelopes.items():
        values = ", ".join(f"{m} {row[m]:.1f}" for m in HELD_OUT_FAMILIES if m in row)
        if not values:
            continue
        worse = ("; the extension leaves more of it than the base: the Stribeck size fitted "
                 "on the identification tests does not carry over to these"
                 if row.get("extended", -math.inf) > row.get("base", math.inf) else "")
        lines += ["", f"A stick-slip's break-aways hang on the noise, so the FIT above can "
                      f"fall where its model is right. Its own measure on the held-out "
                      f"{stage} tests ({', '.join(row['tests'])}), the misfit of the fast "
                      f"(> {FAST_HZ:g} Hz) envelope in noise-power units (clean campaigns "
                      f"< {MIN_BASE_MISFIT:g}): {values}{worse}."]
    return lines


def signature_lines(result: DiscoveryResult) -> list[str]:
    """What the extended model leaves, per channel: at the noise floor, or what it follows."""
    if not result.signatures:
        return []
    lines = ["", "## What the catalogue leaves (unexplained round)", "",
             "Each channel's residual after the extension, set against a generic library "
             "(lags, ripples periodic in an angle, polynomials of the model's signals, drift "
             "over the campaign): the share it predicts on held-out identification tests, "
             "against the best of 19 phase-randomised copies of the residual (chance). "
             "The channel's scale against its twin is taken out first and shown apart: a "
             "known ratio or a sensor gain a little off is calibration, not an effect.", "",
             "| channel | scale error | residual rms | noise floor | best signature | "
             "held-out share | chance | verdict |", "|---|---|---|---|---|---|---|---|"]
    for sig in result.signatures:
        best = sig.best
        what = "—" if best is None else best.group + "".join(
            f", {k} = {v:.4g}" for k, v in best.quantities().items())
        level = sig.residual_rms / sig.noise_rms if sig.noise_rms > 0 else float("inf")
        lines.append(f"| {sig.channel} | {100 * sig.gain_error:+.2f} % | {sig.residual_rms:.4g} | {sig.noise_rms:.4g} | {what} "
                     f"| {100 * (best.cv_share if best else 0):.1f} % | "
                     f"{100 * sig.chance_share:.1f} % | {_verdict(sig, level)} |")
    return lines


def _verdict(sig: ChannelSignature, level: float) -> str:
    """A channel's verdict: structure left, a small structure below the margin, or none;
    with why a periodic reading was dropped, if one was (``ChannelSignature.not_a_ripple``)."""
    aside = f"; {sig.not_a_ripple}" if sig.not_a_ripple else ""
    if sig.structured:
        return "**structure left** (see figures/unexplained.png)" + aside
    if 0 < sig.above_chance < sig.min_share and sig.explained_rms > sig.noise_rms:
        return (f"a small structure, {100 * sig.above_chance:.1f} % above chance: below the "
                f"{100 * sig.min_share:.0f} % an effect must explain to be named" + aside)
    return f"nothing this library predicts (residual {level:.1f}× the noise floor)" + aside


def resolution_table(resolution: list[Resolution]) -> pd.DataFrame:
    """One row per (pair, size) of the predicted scores (``resolution.csv``)."""
    columns = ["effect", "component", "stage", "side", "multiple_of_realistic_size",
               "predicted_relative_gain", "predicted_aic_delta", "resolved",
               "detection_limit_multiple", "refit_relative_gain", "injected_relative_gain",
               "injected_recovered"]
    if not resolution:
        return pd.DataFrame(columns=columns)
    # side: "realistic" for the realistic size's side of neutral, "other" for the other
    # side of an effect that acts either way (a power-law exponent above 1), "refit" the
    # prediction at the size the structure test's refit reached (``RefitCheck``),
    # "injected" the prediction at the size the limit check added to the data (``limits.py``)
    return pd.DataFrame([
        {"effect": r.effect, "component": r.component, "stage": r.stage, "side": side,
         "multiple_of_realistic_size": s.multiple,
         **{f"size.{k}": v for k, v in s.values.items()},
         "predicted_relative_gain": s.share, "predicted_aic_delta": s.aic_delta,
         "resolved": limit is not None and s.multiple >= limit,
         "detection_limit_multiple": limit,
         "refit_relative_gain": r.refit.refit_share if side == "refit" else None,
         "injected_relative_gain": r.injection.share if side == "injected" else None,
         "injected_recovered": r.injection.recovered if side == "injected" else None}
        for r in resolution
        for side, sizes, limit in (("realistic", r.sizes, r.resolved_from),
                                   ("other", r.other_side, r.other_side_resolved_from),
                                   ("refit", [r.refit.predicted] if r.refit else [], None),
                                   ("injected", _injected_size(r), None))
        for s in sizes])


def _injected_size(r: Resolution) -> list:
    """The prediction at the size the limit check added (none where it did not run)."""
    inj = r.injection
    if inj is None:
        return []
    sizes = r.other_side if inj.other_side else r.sizes
    return [s for s in sizes if s.multiple == inj.multiple][:1]


def resolution_lines(result: DiscoveryResult) -> list[str]:
    """The report's section: which pairs these tests can show, and from which size."""
    st = result.settings
    lines = ["", "## What these tests can resolve", "",
             "Predicted share of its stage's residual cost each catalogue pair would remove if "
             "the rig had it at its realistic size (the twin with the effect minus the twin "
             "without, less what the stage's parameters absorb, against the model the "
             "structure rounds searched last; `resolution.csv`), and the "
             "smallest size tried (0.1× to 4× the realistic size) that clears the margins — "
             f"the detection limit of these tests ({100 * st.min_relative_gain:.0f} % and "
             f"{figures.aic_margin_text(result)}). An estimate: a pair marked *not resolved* can "
             "be in the rig without any finding here; longer or other tests would be needed "
             "(figure: `figures/resolution.png`): `mbst plan --resolve` on this folder "
             "designs them (docs/loop.md).",
             "", "| effect | component | stage | share at realistic size | ΔAIC | "
             "detection limit (smallest size resolved) |", "|---|---|---|---|---|---|"]
    # the blind spots first, then the pairs that need the largest size
    model = result.base.model
    for r in sorted(result.resolution, key=lambda r: (r.stage is not None,
                                                      r.resolved_from is not None,
                                                      -(r.resolved_from or 0), r.key)):
        if r.stage is None:
            where = " or ".join(model.component_scenarios.get(r.component, ())) or "–"
            lines.append(f"| {r.effect} | {r.component} | – | – | – | **not tested**: no "
                         f"identification test where it acts ({where}) |")
            continue
        one = r.size_at(1.0)
        if one is None:  # the simulator could not run the realistic size
            continue
        where = limit_text(r, False)
        if r.other_side:
            where += "; the other way: " + limit_text(r, True)
        lines.append(f"| {r.effect} | {r.component} | {r.stage} | {100 * one.share:.1f} % | "
                     f"{one.aic_delta:.0f} | {where} |")
    return lines + _floor_caveat(result.resolution)


def _floor_caveat(resolution: list[Resolution]) -> list[str]:
    """How far each stage's fit is from its noise floor, and what that does to the limits."""
    over = {r.stage: r.stage_over_floor for r in resolution
            if r.stage is not None and r.stage_over_floor is not None}
    if not over:
        return []
    return ["", "The prediction takes the rest of the model as right. Each stage's fit "
            "leaves " + ", ".join(f"{v:.1f}× ({st})" for st, v in sorted(over.items()))
            + " the cost its noise floor would leave. The floor counts each sensor's fast "
            "noise; noise that wanders over tens of milliseconds counts in the fit's cost "
            "and not in the floor (a clean realistic bench rig: 22× and 33× with AR(1) "
            "noise, 1.6× and 3.0× with the same noise white). A ratio well above 1 with "
            "white noise means the model misses more than any one pair (sensor lags, known "
            "values off, an effect the catalogue lacks). Either way a refit can take more "
            "of an effect than the linearised prediction, and the limits above can be "
            "optimistic: on that rig a rack load-dependent friction "
            "predicted to remove 7.3 % of its stage at the realistic size removed 2.0 % "
            "when added to the data and refitted, and 12.7 % at twice that size where 53 % "
            "was predicted."]


def limit_text(r: Resolution, other_side: bool) -> str:
    """The detection limit of one side of neutral, in the effect's own unit."""
    sizes = r.other_side if other_side else r.sizes
    limit = r.detection_limit(other_side)
    c = r.refit
    if c is not None and c.contradicts and c.other_side == other_side:
        when = "" if c.round is None else f" in round {c.round} (the later rounds' screen " \
            "spared it)"
        now = "" if c.carried is None else f"; {100 * c.carried[0]:.1f} % of what is left now"
        return (f"**no limit stated**: the structure test's refit{when} reached "
                f"{size_text(c.predicted, r.size_parameters)} and removed "
                f"{100 * c.refit_share:.1f} % of its stage (ΔAIC {c.refit_aic_delta:.0f}{now}), "
                "where "
                f"this prediction says {100 * c.predicted.share:.1f} % at that size: these "
                "tests' output error does not reach the effect as predicted, so they do not "
                "rule it out at any size")
    if c is not None and c.contradicts:
        return ("**no limit stated** either: the refit on the other side contradicts the "
                "prediction both limits come from")
    inj = r.injection
    if inj is not None and not inj.recovered:
        return _not_recovered_text(r, inj, other_side)
    # an effect that grows as its parameter falls (a presliding's stiffness, an exponent
    # below 1) is stated the other way round: rig 2512's motor presliding read "at or
    # below stiffness = 20" where sizes of 20 and less (stiffer is weaker) were resolved
    falls = _grows_as_it_falls(sizes, r.size_parameters)
    if limit is None:
        return (f"**not resolved** {'down' if falls else 'up'} to "
                + size_text(sizes[-1], r.size_parameters))
    # resolved already at the weakest size tried: the limit lies beyond it
    if limit is sizes[0]:
        bound = f"at or {'above' if falls else 'below'} {size_text(limit, r.size_parameters)}"
    else:
        bound = f"from {size_text(limit, r.size_parameters)}" + (" down" if falls else "")
    weaker = "weaker than" if falls else "below"
    checked = "" if inj is None or inj.other_side != other_side else (
        f" (checked: added at {_injected_text(r, inj)} to these data, the structure test's "
        f"refit removed {100 * inj.share:.1f} % of its stage, ΔAIC {inj.aic_delta:.0f})")
    if r.injection_skipped and (c is None or c.other_side == other_side):
        checked = (" (not checked: its refit did not clear the margins either, and the "
                   "injection checks went to pairs whose refit found less)")
    return f"{bound}, " + (
        f"{weaker} the realistic size" if limit.multiple < 1 else
        "the realistic size" if limit.multiple == 1 else
        f"{limit.multiple:g}× the realistic size") + checked


def _not_recovered_text(r: Resolution, inj, other_side: bool) -> str:
    """A limit withheld because the effect, added to the data, was not recovered."""
    if inj.other_side != other_side:
        return ("**no limit stated** either: the limit on the other side, added to these "
                "data, was not recovered, and both come from one prediction")
    limit = ", ".join(f"{k} = {v:.3g}" for k, v in inj.limit_values.items()
                      if k in r.size_parameters)
    predicted = f"predicted from {limit}, " if limit else ""
    ended = ", ".join(f"{k} = {v:.3g}" for k, v in inj.refit_values.items()
                      if k in r.size_parameters)
    return (f"**no limit stated**: {predicted}but the effect at {_injected_text(r, inj)}, "
            f"added to these data, was refitted by the structure test to {ended} and removed "
            f"{100 * inj.share:.1f} % of its stage (ΔAIC {inj.aic_delta:.0f}): these tests "
            "would not have named it, so they do not rule it out")


def _injected_text(r: Resolution, inj) -> str:
    """The size a limit check added: its values, and the realistic size said as such."""
    size = ", ".join(f"{k} = {v:.3g}" for k, v in inj.values.items() if k in r.size_parameters)
    return f"the realistic size ({size})" if inj.multiple == 1.0 else size


def _grows_as_it_falls(sizes: list, size_parameters: list[str]) -> bool:
    """Whether the sizes tried, weakest first, set the effect's parameter lower as they
    grow stronger. Read from the sizes, not ``EffectSpec.inverse_size``: a power law's
    exponent below 1 falls too, and the record carries no model."""
    names = [k for k in sizes[0].values if k in size_parameters] if sizes else []
    return bool(names) and sizes[-1].values[names[0]] < sizes[0].values[names[0]]


def size_text(size, size_parameters: list[str]) -> str:
    """A size in the effect's own unit: ``width_rad = 0.00524 (0.30°)``."""
    parts = []
    for k, v in size.values.items():
        if k in size_parameters:
            deg = f" ({np.degrees(v):.2f}°)" if k.endswith("_rad") else ""
            parts.append(f"{k} = {v:.3g}{deg}")
    return ", ".join(parts)


def benchmark_table(bench: dict) -> list[str]:
    """The family's published figures of merit next to ours (benchmark.json)."""
    base = bench.get("base", {})
    authors = bench.get("authors_parameters_here", {})
    lines = ["", f"## Published benchmark measures on `{bench.get('test')}`", "",
             "| measure | published | source | authors' parameters, our code | base | extended |",
             "|---|---|---|---|---|---|"]
    for key, pub in bench["published"].items():
        ext = bench.get(key)
        b = base.get(key)
        a = authors.get(key)
        fmt = lambda v: "–" if v is None else f"{v:.4g}"
        lines.append(f"| {key} | {pub['value']:.4g} | {pub['model']} | {fmt(a)} | {fmt(b)} | "
                     f"{fmt(ext)} |")
    lines += ["", "Errors in %, lower is better; FIT in %, higher is better. Definitions in "
              "`benchmark.json`."]
    key = "open_loop_fit_percent_test"
    if f"{key}_output_error_parameters" in bench:
        fmt = lambda v: "–" if v is None else f"{v:.4g}"
        lines += ["", f"Open-loop FIT: base and extended parameters refitted by open-loop "
                  "simulation error on the identification run (`open_loop_parameters`); with "
                  "the cascade's output-error parameters it is "
                  f"{fmt(base.get(f'{key}_output_error_parameters'))} (base) and "
                  f"{fmt(bench[f'{key}_output_error_parameters'])} (extended)."]
    lines += _hybrid_lines(bench.get("hybrid"))
    return lines


def windowed_benchmark_lines(bench: dict) -> list[str]:
    """Per control test, our models beside the published one over its scoring window
    (the friction damper's ``benchmark.json``: ``tests`` → ``window``)."""
    rows = {tid: r for tid, r in bench["tests"].items() if "window" in r}
    if not rows:
        return []
    names = [n for n in bench.get("mean_window_fit_percent", {}) if n != "base"] + ["base"]
    published = next(iter(rows.values())).get("published_model", "published")
    lines = ["", f"## Control tests beside the published model ({published}), its windows",
             "", "FIT % / RMSE N / NRMSE of the raw force over the samples the makers scored.",
             "", "| test | samples | " + " | ".join(names) + " |",
             "|---|---|" + "---|" * len(names)]
    for tid, r in rows.items():
        a, b = r["window_samples"]
        cells = [f"{r['window'][n]['fit_percent']:.1f} / {r['window'][n]['rmse_n']:.0f} / "
                 f"{r['window'][n]['nrmse']:.3f}" for n in names]
        lines.append(f"| {tid} | {a}–{b} | " + " | ".join(cells) + " |")
    means = bench.get("mean_window_fit_percent", {})
    lines += ["", "Mean FIT: " + ", ".join(f"{n} {means[n]:.1f} %" for n in names if n in means)
              + "."]
    hybrid = bench.get("hybrid")
    if hybrid and "error" in hybrid:
        lines += ["", f"Physics + neural residual: not computed ({hybrid['error']})."]
    elif hybrid:
        lines += ["", f"Physics + neural residual: {hybrid['model']} "
                  f"({len(hybrid['trained_on'])} tests, {hybrid['train_seconds']:.0f} s; "
                  f"correction gain {', '.join(f'{g:.2f}' for g in hybrid['correction_gain'].values())})."]
    return lines + _error_place_lines(rows)


def _error_place_lines(rows: dict) -> list[str]:
    """Where the squared force error lies, by the band's state in the physics replay."""
    shares = {tid: r["error_by_band_state"] for tid, r in rows.items() if "error_by_band_state" in r}
    if not shares:
        return []
    states = list(next(iter(shares.values()))["samples"])
    models = [m for m in next(iter(shares.values())) if m != "samples"]
    lines = ["", "Where the error is left (share of the squared force error, by the band's "
             "state in the extended model's replay; first column: share of samples):", "",
             "| test | model | " + " | ".join(s.replace("_", " ") for s in states) + " |",
             "|---|---|" + "---|" * len(states)]
    for tid, sh in shares.items():
        lines.append(f"| {tid} | samples | " + " | ".join(
            f"{100 * sh['samples'][s]:.0f} %" for s in states) + " |")
        lines += [f"| | {m} | " + " | ".join(f"{100 * sh[m][s]:.0f} %" for s in states) + " |"
                  for m in models]
    return lines


def _hybrid_lines(hybrid: dict | None) -> list[str]:
    """The physics + neural residual row of the benchmark, or why it is missing."""
    if not hybrid:
        return []
    if "error" in hybrid:
        return ["", f"Physics + neural residual (open loop): not computed ({hybrid['error']})."]
    ident = ", ".join(f"{v:.4g} %" for v in hybrid["open_loop_fit_percent_identification"].values())
    return ["", f"Physics + neural residual, open loop on the test run: FIT "
            f"**{hybrid['open_loop_fit_percent_test']:.4g} %** against "
            f"{hybrid['physics_open_loop_fit_percent_test']:.4g} % for the physics alone "
            f"(trained on {', '.join(hybrid['trained_on'])} only, where it reaches {ident}; "
            f"correction gain {', '.join(f'{g:.2f}' for g in hybrid['correction_gain'].values())})."]


def run_discover(campaign: Campaign, out_dir: str | Path,
                 settings: DiscoverSettings | None = None, base_fit: dict | None = None
                 ) -> DiscoveryResult:
    """``mbst discover``: everything into ``out_dir``, atomically (``base_fit``: the
    record ``mbst identify`` wrote, see ``discover``)."""
    result = discover(campaign, settings, base_fit)
    with atomic_output_dir(out_dir) as tmp:
        write_discover_outputs(result, tmp)
    return result


def screened_out_lines(rounds: list[dict]) -> list[str]:
    """Which candidates the first round did not refit: the screen's prediction for them."""
    first = next((r for r in rounds if r.get("shortlist_screen")), None)
    if first is None:
        return []
    screen = first["shortlist_screen"]
    refitted = {c["key"] for c in first.get("candidates", [])}
    out = sorted(((g, k) for k, g in screen["predicted_gain"].items() if k not in refitted),
                 reverse=True)
    if not out:
        return []
    g, k = out[0]
    return ["", f"Round {first['round']} refitted {len(screen['predicted_gain']) - len(out)} "
                f"of {len(screen['predicted_gain'])} candidates: the linearised screen "
                f"(`rounds/screen.py`) predicted that each of the other {len(out)} would "
                f"remove less than {100 * screen['needed']:.0f} % of its stage (the most: "
                f"{k}, {100 * g:.2f} %)."]


def untested_lines(rounds: list[dict]) -> list[str]:
    """How many structure-test candidates were not fully tested, and which."""
    cands = [c for r in rounds for c in r.get("candidates", []) if "fell_back" in c]
    if not cands:
        return []
    stuck = [f"{c['key']} (round {r['round']})" for r in rounds
             for c in r.get("candidates", []) if c.get("fell_back")]
    short = [f"{c['key']} (round {r['round']})" for r in rounds
             for c in r.get("candidates", []) if c.get("work_spent")]
    if short:  # their refits needed steps far finer than the base model's (work.py)
        short_line = (f" {len(short)} stopped at their work budget, their step far finer "
                      "than the base model's (scored at their best point): "
                      + ", ".join(short) + ".")
    else:
        short_line = ""
    if not stuck:
        return ["", f"Every candidate refit ended at or below the base it nests "
                    f"({len(cands)} refits).{short_line}"]
    return ["", f"**Not fully tested:** {len(stuck)} of {len(cands)} candidate refits ended "
                f"above the base model they nest (scored as the base, gain 0): "
                + ", ".join(stuck) + "." + short_line]

