"""What ``mbst plan --resolve`` writes: the campaign with its next tests, the design, the page."""

from __future__ import annotations

import textwrap
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
import pandas as pd
import yaml

from mbst.identify.fitting import simulate_twin
from mbst.io.outputs import atomic_text, write_json, write_markdown
from mbst.plan.resolve.design import SAFETY, score
from mbst.plan.resolve.run import NEEDED_UP_TO, ResolveResult
from mbst.plan.resolve.signatures import reading_curves


def campaign_template(res: ResolveResult) -> dict:
    """The campaign's own ``campaign.yaml`` with the added tests after its own (no data yet).

    Its tests keep their order, so a bench run of the template (``mbst bench
    --tests-from``) with the campaign's seed repeats them and appends the new ones.
    """
    doc = yaml.safe_load((res.campaign.path / "campaign.yaml").read_text())
    doc["tests"] = list(doc.get("tests", []))
    for tid, c in res.added():
        entry = {"id": tid, "file": f"tests/{tid}.csv", "scenario": c.scenario,
                 "input": dict(c.input), "motor": c.motor, "role": "identification"}
        if c.input_noise_factor != 1.0:
            # the sensor the design assumed (the bench logs the test with it)
            entry["sensor_noise_rms"] = {res.input_channel: res.noise[res.input_channel]
                                         * c.input_noise_factor}
        doc["tests"].append(entry)
    doc["planned_by"] = "mbst plan --resolve"
    return doc


def _question_rows(res: ResolveResult) -> list[dict]:
    rows = []
    for q in res.questions:
        b = res.before.get(q.key, (0.0, 0.0))
        a = res.after.get(q.key, b)
        rows.append({"effect": q.effect, "component": q.component, "stage": q.stage,
                     "rival": q.rival_key, "question": q.label(),
                     "reason": q.reason, "size": q.headline,
                     "aic_drop_needed": res.margins.drop(q),
                     "share_before": b[0], "aic_delta_before": b[1],
                     "resolved_before": res.margins.clears(q, *b),
                     "share_after": a[0], "aic_delta_after": a[1],
                     "resolved_after": res.margins.clears(q, *a),
                     "test_time_needed_s": res.needed.get(q.key),
                     # a look-alike or a rival reading: the share of resamples (folds) in
                     # which the campaign already preferred the finding
                     "observed_share": q.observed_share,
                     "discovery_predicted_before": list(q.before) if q.before else None})
    return rows


def candidate_table(res: ResolveResult) -> pd.DataFrame:
    """Each candidate added alone to the campaign: its predicted (share, ΔAIC) per question."""
    ctx = res.context
    rows = []
    for c in res.candidates:
        qs = ctx.stage_questions(c.scenario)
        if not qs:
            continue
        logged = [ctx.blocks[i] for i in res.logged.get(c.scenario, [])]
        for q, (share, aic) in zip(qs, score(ctx, c.scenario, logged + [ctx.blocks[c.id]]),
                                   strict=True):
            rows.append({"candidate": c.id, "scenario": c.scenario, "duration_s": c.duration_s,
                         "input": yaml.safe_dump(c.input, default_flow_style=True).strip(),
                         "effect": q.effect, "component": q.component,
                         "rival": q.rival_key or "",
                         "predicted_share": share, "predicted_aic_delta": aic})
    return pd.DataFrame(rows)


def resolve_record(res: ResolveResult, discovery: str) -> dict:
    return {
        "format": "mbst-resolve/1",
        "campaign": res.campaign.name,
        "discovery": discovery,
        "margins": {"min_relative_gain": res.margins.min_gain, "safety_factor": SAFETY},
        "budget": {"test_time_s": res.budget_s, "campaign_test_time_s": res.campaign_time_s,
                   "added_test_time_s": sum(s.duration_s for s in res.steps)},
        "questions": _question_rows(res),
        "added_tests": [{"id": tid, "scenario": c.scenario, "input": c.input,
                         "sensor_change": c.sensor_change,
                         "duration_s": c.duration_s, "progress": s.progress}
                        for (tid, c), s in zip(res.added(), res.steps, strict=True)],
        "notes": list(res.notes),
        "wall_s": round(res.wall_s, 2),
    }


def _pair(r: dict) -> str:
    """A question's row label: the pair, a finding or its look-alike, or two readings."""
    if r["effect"] == "unexplained":
        return r["question"]
    return f"{r['effect']} in {r['component']}" + (
        f" or {r['rival'].replace(':', ' in ')}" if r["rival"] else "")


def _fmt_size(size: dict) -> str:
    return ", ".join(f"{k} {v:.4g}" for k, v in size.items())


def _questions_section(res: ResolveResult, questions: list[dict]) -> list[str]:
    """The page's title, what its questions mean, and their table before and after."""
    lines = [f"# Next tests for '{res.campaign.name}': what discovery could not decide", "",
             "A size question is one catalogue pair at one size: would discovery name it if "
             "the rig had it? Predicted share of its stage's cost and ΔAIC against "
             f"discovery's margins (share ≥ {100 * res.margins.min_gain:.0f} %, ΔAIC below "
             "the needed drop). A rival question (*A or B*) is a finding and a look-alike "
             "discovery did not rule out: the share and ΔAIC are what the look-alike's refit "
             "leaves of the finding's signal, and it is decided when the finding would win "
             "in 95 % of resamples (ΔAIC ≤ −10.8). A signature question is an unexplained "
             "finding's structure read two ways (two quantities it may follow, `signatures.py`): "
             "the share and ΔAIC are what the rival reading's refit leaves of the best "
             "reading's learned term, on that channel's cost. The design aims at "
             f"{SAFETY}× the margins. Method: `src/mbst/plan/resolve/design.py`.", "",
             "| pair | size | why asked | share before | ΔAIC before | share after | "
             "ΔAIC after | ΔAIC needed | decided after |", "|---|---|---|---|---|---|---|---|---|"]
    for r in questions:
        pair = _pair(r)
        lines.append(f"| {pair} | {_fmt_size(r['size'])} | "
                     f"{r['reason']} | {100 * r['share_before']:.1f} % | "
                     f"{r['aic_delta_before']:.1f} | {100 * r['share_after']:.1f} % | "
                     f"{r['aic_delta_after']:.1f} | −{r['aic_drop_needed']:.1f} | "
                     f"{'yes' if r['resolved_after'] else '**no**'} |")
    return lines


def _added_tests_section(rec: dict) -> list[str]:
    """The tests added: their test time against the campaign's, and their table."""
    b = rec["budget"]
    lines = ["", f"Tests added: {len(rec['added_tests'])}, {b['added_test_time_s']:.0f} s of "
             f"test time ({100 * b['added_test_time_s'] / max(b['campaign_test_time_s'], 1e-9):.0f}"
             f" % of the campaign's {b['campaign_test_time_s']:.0f} s; allowed "
             f"{b['test_time_s']:.0f} s). They stay on the campaign's cut-outs, sensors and "
             "amplitude and rate limits; the one sensor change offered is a finer angle encoder "
             "(`sensor_noise_rms` in the test's entry). `campaign.yaml` is the campaign with "
             "them appended.", "",
             "| test | cut-out | input | sensor change | duration |", "|---|---|---|---|---|"]
    for t in rec["added_tests"]:
        inp = yaml.safe_dump(t["input"], default_flow_style=True).strip()
        lines.append(f"| {t['id']} | {t['scenario']} | `{inp}` | {t['sensor_change'] or '—'} "
                     f"| {t['duration_s']:.1f} s |")
    return lines


def _undecided_section(questions: list[dict]) -> list[str]:
    """The questions the budget leaves open: the test time each would need, or why none."""
    undecided = [r for r in questions if not r["resolved_after"]]
    if not undecided:
        return []
    lines = ["", "Not decided within the budget (`candidates.csv`: what each candidate "
             "test alone would give):", ""]
    for r in undecided:
        t = r["test_time_needed_s"]
        lines.append(f"- {_pair(r)}: " + (
            f"decided after {t:.0f} s of added tests (the same greedy choice, "
            "past the budget)" if t is not None else
            f"not within {NEEDED_UP_TO:g}× the campaign's test time: " + (
                "the rival reading follows the structure in every candidate as well (the "
                "tests move the two quantities together), so a cut-out or an input this "
                "step does not offer would be needed" if r["effect"] == "unexplained" else
                "a refit of the stage's parameters takes over most of its signal in every "
                "candidate, so a cut-out, an input beyond the campaign's rate or "
                "amplitude, or a sensor this step does not offer would be needed — or the "
                "effect is below what this rig can show")))
    return lines


def resolve_page(res: ResolveResult, figures: list[str], failures: list[str]) -> str:
    """``resolve.md``: the questions, the tests added, what stays open, notes and figures."""
    rec = resolve_record(res, "")
    lines = _questions_section(res, rec["questions"])
    lines += _added_tests_section(rec)
    lines += _undecided_section(rec["questions"])
    for n in res.notes:
        lines += ["", f"Note: {n}"]
    if not res.questions:
        lines += ["", "Nothing open: discovery resolves every catalogue pair that acts in "
                  "these cut-outs at its realistic size, and no target was asked."]
    for f in figures:
        lines += ["", f"![{f}](figures/{f})"]
    for f in failures:
        lines += ["", f"**Failed:** {f}"]
    return "\n".join(lines) + "\n"


def _responses(res: ResolveResult, q, pt) -> tuple[tuple[str, str], dict]:
    """The two models' predicted responses of ``q`` on the predicted test ``pt``, per channel,
    and their names: (without, with) the effect, (rival, named), or for a signature question
    the rival reading's best fit to the best reading's learned term, and that term."""
    if q.signature is not None:
        term, fit = reading_curves(q, pt, res.context.p)
        r = q.signature
        return (f"{r.rival} (its best fit)", f"{r.group}: learned term"), \
            {r.channel: (fit, term)}
    y0, y1 = (simulate_twin(pt, p) for p in q.models(res.context.p, pt.model))
    names = ((f"{q.rival.effect} in {q.rival.component}", "named: " + q.spec.effect)
             if q.rival is not None else ("without", f"with {q.spec.effect}"))
    return names, {ch: (y0[ch], y1[ch]) for ch in pt.measured}


def question_figure(res: ResolveResult, path: Path) -> None:
    """Per question: the predicted response of its best added test without and with the
    effect, on the channel where they differ most, and their difference against the noise."""
    added = res.added()
    qs = [q for q in res.questions if any(c.scenario == q.stage for _, c in added)]
    fig, axes = plt.subplots(len(qs), 2, figsize=(11, 2.8 * len(qs)), squeeze=False)
    for ax, q in zip(axes, qs, strict=True):
        best = None
        for _, c in added:
            if c.scenario != q.stage:
                continue
            pt = res.predicted[c.id]
            names, curves = _responses(res, q, pt)
            for ch, (y0, y1) in curves.items():
                diff_rms = float(np.sqrt(np.mean((y1 - y0) ** 2)))
                snr = diff_rms / max(pt.noise.get(ch, 0.0), 1e-12)
                if best is None or snr > best[0]:
                    best = (snr, c, pt, ch, y0, y1, names)
        if best is not None:
            _draw_question(ax, q, *best)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _draw_question(ax, q, snr, c, pt, ch, y0, y1, names) -> None:
    ax[0].plot(pt.time_s, y0, lw=1, label=names[0])
    ax[0].plot(pt.time_s, y1, lw=1, ls="--", label=names[1])
    ax[0].set_title("\n".join([*textwrap.wrap(q.label(), 70), c.id]), fontsize=8)
    ax[0].set_ylabel(ch if q.signature is None else f"learned term in {ch}", fontsize=8)
    ax[0].legend(fontsize=7)
    sigma = pt.noise.get(ch, 0.0)
    ax[1].plot(pt.time_s, y1 - y0, lw=1, color="C3", label=f"{names[1]} − {names[0]}")
    ax[1].axhspan(-2 * sigma, 2 * sigma, color="0.85", label="±2σ sensor noise (filtered)")
    ax[1].set_title(f"difference, rms {snr:.1f}× the sensor noise", fontsize=9)
    ax[1].legend(fontsize=7)
    for a in ax:
        a.set_xlabel("time (s)", fontsize=8)
        a.tick_params(labelsize=7)


def write_resolve(out: Path, res: ResolveResult, discovery: str) -> None:
    """Everything into ``out`` (a fresh folder); a failing figure is reported, never fatal."""
    with atomic_text(out / "campaign.yaml") as fh:
        fh.write("# written by `mbst plan --resolve`: the campaign with the tests that decide\n"
                 "# what discovery left open appended (no data yet for those).\n")
        yaml.safe_dump(campaign_template(res), fh, sort_keys=False, default_flow_style=None,
                       width=100)
    with atomic_text(out / "candidates.csv", newline="") as fh:
        candidate_table(res).to_csv(fh, index=False, float_format="%.6g")
    figures, failures = [], []
    if res.steps:
        try:
            question_figure(res, out / "figures" / "predicted_responses.png")
            figures.append("predicted_responses.png")
        except Exception as exc:  # a figure never loses the design
            failures.append(f"figure predicted_responses.png: {type(exc).__name__}: {exc}")
    rec = resolve_record(res, discovery)
    rec["failures"] = failures
    write_json(out / "resolve.json", rec)
    write_markdown(out / "resolve.md", resolve_page(res, figures, failures))
