"""Figures of a discovery run: what the base model gets wrong and what the extension fixes."""

from __future__ import annotations

import logging
import textwrap
from pathlib import Path

import numpy as np

from mbst.discovery.acceptance import FALSE_ALARM_RATE, pooled_rise
from mbst.discovery.rounds import equation_error, stickslip
from mbst.discovery.rounds.ripple import fast_part
from mbst.report import plots
from mbst.report.plots import MODEL_STYLE, SCALE, label_of, motion_reversals, plt

log = logging.getLogger(__name__)


def reversal_zoom(result, path: Path, half_window_s: float = 0.6) -> None:
    """Measured vs base vs extended around the reversal where the base model errs most."""
    controls = [result.base.prepared[t] for t in dict.fromkeys(result.comparison.test)]
    if not controls:
        controls = [result.base.prepared[r.id] for r in result.residual_tests[:2]]
    model = controls[0].model
    chans = [c for c in model.output_channels if any(c in pt.measured for pt in controls)][:2]
    fig, axes = plt.subplots(len(controls), len(chans), figsize=(5.2 * len(chans),
                             2.9 * len(controls)), squeeze=False)
    models = {m: tw for m, tw in result.twins.items() if m in ("base", "extended", "true")}
    for i, pt in enumerate(controls):
        base_tw = result.twins.get("base", {}).get(pt.id) or result.base.twins[pt.id]
        # the base model's error, each channel in units of its spread
        err = sum(np.abs(pt.measured[c] - base_tw[c]) / (np.std(pt.measured[c]) or 1.0)
                  for c in chans if c in pt.measured)
        revs = motion_reversals(pt.omega_rad_per_s)
        win = int(round(half_window_s / pt.dt_s))
        if len(revs):
            worst = max(revs, key=lambda r: err[r: r + win].max(initial=0.0))
        else:
            worst = int(np.argmax(err))
        lo, hi = max(worst - win, 0), min(worst + 2 * win, len(pt.time_s))
        sl = slice(lo, hi)
        for j, ch in enumerate(chans):
            ax = axes[i][j]
            if ch not in pt.measured:
                ax.set_axis_off()
                continue
            s = SCALE.get(ch, 1.0)
            ax.plot(pt.time_s[sl], s * pt.measured[ch][sl], color="black", lw=1.6,
                    label="measured")
            for name, tw in models.items():
                if pt.id in tw and ch in tw[pt.id]:
                    ax.plot(pt.time_s[sl], s * tw[pt.id][ch][sl], label=name,
                            **MODEL_STYLE.get(name, {}))
            # a solid, pale marker: the true model is drawn dotted grey
            ax.axvline(pt.time_s[worst], color="tab:blue", alpha=0.35, lw=0.8,
                       label="reversal")
            plots._style(ax, f"{pt.id}: reversal at {pt.time_s[worst]:.2f} s", label_of(ch))
    plots._finish(fig, axes, path)


def structure_bars(result, path: Path) -> None:
    """Share of the stage's residual cost each catalogue candidate removes, per round, with
    the realities outside the catalogue refitted as the winner's rivals (grey,
    ``discovery/rivals.py``): a torque zero that removes more than the winner is the reason
    for its low confidence, and belongs beside it."""
    rounds = [r for r in result.rounds if r["candidates"]]
    if not rounds:
        fig, ax = plt.subplots(figsize=(6, 2))
        ax.text(0.5, 0.5, "no candidate could be tested", ha="center", va="center")
        ax.set_axis_off()
        plots.save_figure(fig, path)
        return
    n = max(len(r["candidates"]) + len(r.get("rivals", [])) for r in rounds)
    fig, axes = plt.subplots(1, len(rounds), figsize=(6.5 * len(rounds), 0.28 * n + 1.6),
                             squeeze=False)
    for ax, r in zip(axes[0], rounds, strict=True):
        cands = sorted(r["candidates"] + [{**c, "rival": True} for c in r.get("rivals", [])],
                       key=lambda c: -c["relative_gain"])
        gains = [100 * max(c["relative_gain"], -5.0 / 100) for c in cands]
        colors = ["tab:green" if c["key"] == r["accepted"] else "tab:blue" for c in cands]
        y = np.arange(len(cands))[::-1]
        rival = np.array([bool(c.get("rival")) for c in cands])
        # ahead of the winner by share, but lost its held-out tests (``_cross_validated``)
        lost = {g["key"]: g for g in r.get("cross_validation_lost", [])}
        ax.barh(y[~rival], np.array(gains)[~rival], color=np.array(colors)[~rival])
        if rival.any():
            ax.barh(y[rival], np.array(gains)[rival], color="tab:gray",
                    label="rival outside the catalogue")
        # a refit that ended above the base cost is scored with the effect off (gain 0)
        # a rival of several channels has a long key: wrapped, not cut at the figure's edge
        ax.set_yticks(y, [textwrap.fill(f"{c['key']} ({c['stage']})"
                                        + (" — rival" if c.get("rival") else "")
                                        + (" — refit stuck, off" if c.get("fell_back") else "")
                                        + (_lost_label(lost[c["key"]])
                                           if c["key"] in lost and not c.get("rival") else ""),
                                        60, break_on_hyphens=False)
                          for c in cands], fontsize=7)
        method = r.get("method")
        margin = {"stick_slip": stickslip.MIN_GAIN,
                  "equation_error": equation_error.MIN_GAIN}.get(method, result_margin(result))
        ax.axvline(100 * margin, color="tab:red", ls="--", lw=1, label="acceptance margin")
        ax.set_xlabel({"stick_slip": "fast-envelope misfit removed in its stage [%]",
                       "equation_error": "inverse-model (equation-error) cost removed [%]"
                       }.get(method, "residual cost removed in its stage [%]")
                      + _screened_out_note(r) + _rivals_screened_note(r), fontsize=8)
        acc = r["accepted"] or "none"
        kind = {"stick_slip": " (stick-slip test)",
                "equation_error": " (equation-error test)"}.get(method, "")
        ax.set_title(f"round {r['round']}{kind}: accepted {acc}", fontsize=9)
        ax.grid(axis="x", alpha=0.3)
        ax.legend(fontsize=7, loc="lower right")
    fig.tight_layout()
    plots.save_figure(fig, path)


def _lost_label(lost: dict) -> str:
    """A structure bar's note for a candidate that lost its held-out tests."""
    label = f" — won {lost['wins']}/{lost['folds']} held-out tests"
    rise = pooled_rise(lost)
    return label if rise is None else f"{label}, all of them {rise:+.0f} % in cost"


def resolution_bars(result, path: Path) -> bool:
    """Predicted share of its stage's cost each pair would remove, realistic size and beyond."""
    res = sorted((r for r in result.resolution if r.size_at(1.0) is not None),
                 key=lambda r: r.size_at(1.0).share)
    if not res:
        return False
    fig, ax = plt.subplots(figsize=(11.0, 0.3 * len(res) + 1.8))
    y = np.arange(len(res))
    colors = ["tab:green" if r.resolved_at_realistic_size else
              "tab:orange" if r.resolved_from else "tab:gray" for r in res]
    ax.barh(y, [100 * r.size_at(1.0).share for r in res], color=colors)
    most = max(s.multiple for r in res for s in r.sizes)
    # sizes above the realistic one are tried only where it is not resolved
    beyond = [(k, r.sizes[-1]) for k, r in enumerate(res) if r.sizes[-1].multiple > 1.0]
    if beyond:
        ax.scatter([100 * s.share for _, s in beyond], [k for k, _ in beyond], marker="|",
                   s=120, color="black", zorder=3,
                   label=f"at the largest size tried ({most:g}× or the bound), where the "
                         "realistic size is not resolved")
    ax.set_yticks(y, [f"{r.key} ({r.stage}) — " + _side_label(r, False) + (
        "; the other way " + _side_label(r, True) if r.other_side else "") for r in res],
        fontsize=7)
    ax.axvline(100 * result_margin(result), color="tab:red", ls="--", lw=1,
               label=f"acceptance margin (and {aic_margin_text(result)})")
    ax.set_xlim(0, 100)
    ax.set_xlabel("predicted share of its stage's residual cost removed [%]", fontsize=8)
    ax.set_title("What these tests can resolve. Bar: at the realistic size; 'from k×': the "
                 "smallest size resolved\n(the detection limit; 'the other way': an effect "
                 "that acts either way from neutral, on the other side)\ngreen: resolved "
                 f"there · orange: only larger · gray: not up to {most:g}× or the bound",
                 fontsize=8)
    ax.grid(axis="x", alpha=0.3)
    # below the axes: inside, it covered the longest labels of the smallest bars
    ax.legend(fontsize=7, loc="upper right", bbox_to_anchor=(1.0, -0.07))
    fig.tight_layout(pad=1.5)
    plots.save_figure(fig, path, tight=True)  # a pair's limits both ways make long labels
    return True


def _side_label(r, other_side: bool) -> str:
    """One side's label: its limit, or why none is stated where the structure test's own
    refit contradicts the prediction (``resolution.RefitCheck``) or did not recover the
    effect added at the limit (``resolution.InjectionCheck``)."""
    c = r.refit
    if c is not None and c.contradicts and c.other_side == other_side:
        return (f"no limit stated (its refit removed {100 * c.refit_share:.0f} % where "
                f"{100 * c.predicted.share:.0f} % is predicted)")
    if c is not None and c.contradicts:
        return "no limit stated either"
    inj = r.injection
    if inj is not None and not inj.recovered:
        # the effect, added to the data, was not recovered (``rounds/limits.py``)
        return (f"no limit stated (added at {inj.multiple:g}×, its refit removed "
                f"{100 * inj.share:.0f} %)" if inj.other_side == other_side
                else "no limit stated either")
    if other_side:
        return _limit_label(r.other_side, r.other_side_resolved_from, False)
    return _limit_label(r.sizes, r.resolved_from)


def _limit_label(sizes: list, resolved_from: float | None, detail: bool = True) -> str:
    """'from k×' (the detection limit), or, with ``detail``, what the largest size tried
    predicts where none is resolved."""
    if resolved_from:
        return (f"from ≤ {resolved_from:g}×" if resolved_from == sizes[0].multiple
                else f"from {resolved_from:g}×")
    return (f"not resolved ({100 * sizes[-1].share:.0f} %, ΔAIC {sizes[-1].aic_delta:.0f}"
            f" at {sizes[-1].multiple:g}×)") if detail else "not resolved"


def result_margin(result) -> float:
    return float(result.settings.min_relative_gain)


def aic_margin_text(result) -> str:
    """The significance margin as the report states it: set by hand, or from the campaign."""
    if result.settings.min_aic_drop is not None:
        return f"ΔAIC ≤ −{result.settings.min_aic_drop:g}"
    drops = sorted({round(r.aic_drop_needed, 1) for r in result.resolution
                    if r.aic_drop_needed is not None}
                   | {round(r["aic_drop_needed"], 1) for r in result.rounds
                      if "aic_drop_needed" in r})
    span = (f"−{drops[0]:.1f}" if len(drops) == 1 else f"−{drops[0]:.1f} to −{drops[-1]:.1f}"
            ) if drops else "the chi-square quantile"
    return (f"ΔAIC ≤ {span}, the likelihood-ratio test at a {100 * FALSE_ALARM_RATE:g} % "
            "false-alarm rate over the catalogue")


def comparison_bars(result, path: Path) -> None:
    """Control FIT % per model family, per control test and channel."""
    df = result.comparison
    if df.empty:
        return
    models = list(dict.fromkeys(df.model))
    # dropna=False keeps a family with no FIT on some channel (a missing row once raised
    # KeyError) but also makes every test x channel pair: a test without a channel (no
    # tie-rod force where the tie rods are free) would stand as an empty slot
    wide = df.pivot_table(index=["test", "channel"], columns="model", values="fit_percent",
                          sort=False, dropna=False).dropna(how="all").reindex(columns=models)
    fig, ax = plt.subplots(figsize=(max(6, 1.3 * len(wide)), 4.2))
    x = np.arange(len(wide))
    w = 0.8 / len(models)
    lo = np.nanmin(np.clip(wide.to_numpy(float), 0, 100))
    ax.set_ylim(max(0.0, lo - 5), 100.5)
    for k, m in enumerate(models):
        vals = np.clip(wide[m].to_numpy(float), 0, 100)
        at = x + k * w - 0.4 + w / 2
        ax.bar(at, vals, w, label=m, color=MODEL_STYLE.get(m, {}).get("color"))
        for xi in at[np.isnan(vals)]:  # a family that could not simulate it ("What failed")
            ax.text(xi, max(0.0, lo - 5) + 0.5, "no FIT", rotation=90, fontsize=6,
                    ha="center", va="bottom", color=MODEL_STYLE.get(m, {}).get("color"))
    ax.set_xticks(x, [f"{t}\n{c}" for t, c in wide.index], fontsize=6)
    ax.set_ylabel("control FIT [%] (clipped to 0–100)", fontsize=8)
    ax.legend(fontsize=7, ncol=len(models), loc="upper center", bbox_to_anchor=(0.5, -0.22))
    ax.grid(axis="y", alpha=0.3)
    ax.set_title("held-out control tests: FIT % of each model family", fontsize=9)
    fig.tight_layout()
    plots.save_figure(fig, path)


def _stick_slip_verdict(result, rec: dict) -> str:
    """What the round named, with the parts its answer leaves open ("motor or rack"), or
    the winner a rival declined (a ripple locked to a rotating part shakes the stage as a
    stick-slip does: the envelope is high and yet nothing is named)."""
    declined = rec.get("rival_declined") or []
    if not rec["accepted"] and declined:
        return f"{declined[0]['key']} declined for {declined[0]['rival']}"
    if not rec["accepted"]:
        return "no finding"
    effect, component = rec["accepted"].split(":")
    f = next((f for f in result.findings if f.effect == effect
              and component in (f.component, *f.indistinguishable_from)), None)
    if f is None:
        return f"accepted {rec['accepted']}"
    parts = " or ".join([f.component, *f.indistinguishable_from])
    return f"named {effect} in {parts}, confidence {f.confidence:.2f}"


def stick_slip(result, path: Path) -> bool:
    """Fast part and its envelope on the test with the most stick-slip misfit.

    Drawn when the stick-slip test ran: measured vs base vs extended, high-passed
    (the sawtooth, whose phase no model can repeat) and as √power over the window
    (what the test compares). Returns whether a figure was written.
    """
    from mbst.identify.fitting import simulate_twin

    rec = next((r for r in result.rounds if r.get("method") == "stick_slip"), None)
    if rec is None or not rec.get("base_misfit"):
        return False
    stage = next((c["stage"] for c in rec["candidates"] if c["key"] == rec["accepted"]),
                 None) or max(rec["base_misfit"], key=rec["base_misfit"].get)
    ids = [result.base.prepared[r.id] for r in result.residual_tests]
    tests = result.base.model.stage_tests(stage, ids)
    if not tests:
        return False
    twins = {pt.id: {"base": simulate_twin(pt, result.base.params),
                     "extended": simulate_twin(pt, result.extended_params)} for pt in tests}
    pt = max(tests, key=lambda t: stickslip.envelope_misfit(t, twins[t.id]["base"]))
    ch = next(c for c in pt.model.output_channels if c in pt.measured)
    s = SCALE.get(ch, 1.0)
    hp = lambda y: stickslip.highpass(y, pt.dt_s)  # noqa: E731
    pn = pt.noise.get(ch, 0.0) ** 2 * stickslip.noise_hf_fraction(pt.dt_s, pt.tau_s)
    fig, axes = plt.subplots(2, 1, figsize=(10, 5.6), sharex=True)
    axes[0].plot(pt.time_s, s * hp(pt.measured[ch]), color="black", lw=1.0, label="measured")
    axes[1].plot(pt.time_s, s * np.sqrt(stickslip.hf_power(pt.measured[ch], pt.dt_s)),
                 color="black", lw=1.4, label="measured")
    for name in ("base", "extended"):
        y = twins[pt.id][name][ch]
        axes[0].plot(pt.time_s, s * hp(y), label=name, **MODEL_STYLE.get(name, {}))
        axes[1].plot(pt.time_s, s * np.sqrt(stickslip.hf_power(y, pt.dt_s) + pn),
                     label=f"{name} + sensor noise", **MODEL_STYLE.get(name, {}))
    # the twins are driven by the measured input: its sensor noise, through a stiff part
    # (the torsion bar of a blocked column), shows in their fast part and the measured
    # output's does not; the test's base misfit carries it alike for every candidate
    plots._style(axes[0], f"{pt.id}: {label_of(ch)} above {stickslip.HIGHPASS_HZ:g} Hz\n"
                 "(where a stick-slip sawtooth shows; its phase is not repeatable; the "
                 "twins carry the measured input's noise)", label_of(ch), "")
    verdict = _stick_slip_verdict(result, rec)
    plots._style(axes[1], f"envelope over {stickslip.WINDOW_S:g} s: what the stick-slip test "
                 f"compares ({stage}, {verdict})", f"rms {label_of(ch)}")
    for ax in axes:
        ax.legend(fontsize=7, loc="upper right")
    fig.tight_layout()
    plots.save_figure(fig, path)
    return True


def unexplained_signature(result, path: Path) -> bool:
    """The residual the catalogue leaves against what it correlates with, and the learned
    term, per structured channel (an ``unexplained`` finding). Returns whether drawn."""
    from mbst.discovery.rounds.unexplained import driving_input
    from mbst.discovery.signature import abscissa, learned_term

    found = [s for s in result.signatures if s.structured][:3]
    if not found:
        return False
    drive = driving_input(result.base.model)
    tests = result.extended_residuals
    places = result.places
    fig, axes = plt.subplots(len(found), 2, figsize=(11, 3.2 * len(found)), squeeze=False)
    for row, sig in zip(axes, found, strict=True):
        ch = sig.channel
        s = SCALE.get(ch, 1.0)
        logged = [t for t in tests if ch in t.measured]
        for t in logged:
            x, xlabel = abscissa(t, sig.best, places.get(t.id, 0.0), drive)
            lt = learned_term(t, sig, places.get(t.id, 0.0), drive)
            row[0].plot(x[::3], s * t.residual(ch)[::3], ".", ms=1.5, color="black", alpha=0.3)
            row[0].plot(x[::3], s * lt[::3], ".", ms=1.5, color="tab:orange", alpha=0.6)
        worst = max(logged, key=lambda t: float(np.std(t.residual(ch))))
        lt = learned_term(worst, sig, places.get(worst.id, 0.0), drive)
        row[1].plot(worst.time_s, s * worst.residual(ch), color="black", lw=0.8,
                    label="measured − extended")
        row[1].plot(worst.time_s, s * lt, color="tab:orange", lw=1.0, label="learned term")
        row[1].legend(fontsize=7, loc="upper right")
        plots._style(row[0], f"{sig.best.group}: {100 * sig.best.cv_share:.0f} % of the "
                     f"residual held out (chance {100 * sig.chance_share:.0f} %)",
                     f"residual {label_of(ch)}", xlabel)
        plots._style(row[1], f"{worst.id}: residual and the learned term", label_of(ch))
    fig.tight_layout()
    plots.save_figure(fig, path)
    return True


def outside_reality(result, path: Path) -> bool:
    """A reality outside the catalogue refitted as physics (a sensor's lag, a drift of the
    friction levels over the campaign: ``rounds/rival_findings.py``; a ripple:
    ``rounds/ripple.py``): what the base model leaves and what the model with it leaves
    (per test in the running order, or over one period of a ripple), and the worst test's
    residual over time. Returns whether drawn."""
    found = [f for f in result.findings if f.effect == "unexplained" and f.signature
             and f.signature.get("refitted") == "physics"][:2]
    if not found or not result.extended_residuals:
        return False
    with_it = {t.id: t for t in result.extended_residuals}
    fig, axes = plt.subplots(len(found), 2, figsize=(11, 3.4 * len(found)), squeeze=False)
    for row, f in zip(axes, found, strict=True):
        tests = [t for t in result.residual_tests if t.scenario == f.stage and t.id in with_it]
        ch = _lead_channel(f, tests, with_it)
        s = SCALE.get(ch, 1.0)
        what = _WHAT.get(f.signature["kind"], f.signature["kind"])
        if f.signature["kind"] == "periodic":
            _folded(row[0], f, ch, tests, with_it, s)
        else:
            _per_test(row[0], f, ch, tests, with_it, result.places, s)
        worst = max(tests, key=lambda t: float(np.std(t.residual(ch))))
        row[1].plot(worst.time_s, s * worst.residual(ch), color="black", lw=0.8,
                    label="measured − base")
        row[1].plot(worst.time_s, s * with_it[worst.id].residual(ch), color="tab:orange",
                    lw=0.8, label=f"measured − model with the {what}")
        row[1].legend(fontsize=7, loc="upper right")
        plots._style(row[1], f"{worst.id} ({f.stage})", label_of(ch))
    fig.tight_layout()
    plots.save_figure(fig, path)
    return True


_WHAT = {"lag": "lag", "drift": "drift", "periodic": "ripple"}


def _per_test(ax, f, ch: str, tests: list, with_it: dict, places: dict, s: float) -> None:
    """Per test in the running order: a drift as the friction level each test wants (the
    residual along the direction of motion), a lag as what is left at all."""
    drift = f.signature["kind"] == "drift"
    level = (lambda t: float(np.mean(t.residual(ch) * np.sign(t.omega_rad_per_s)))) \
        if drift else (lambda t: float(np.sqrt(np.mean(t.residual(ch) ** 2))))
    x = [places.get(t.id, 0.0) for t in tests]
    ax.plot(x, [s * level(t) for t in tests], "o-", color="black", label="base model")
    ax.plot(x, [s * level(with_it[t.id]) for t in tests], "o-", color="tab:orange",
            label=f"with the {_WHAT.get(f.signature['kind'])}")
    ax.axhline(0.0, color="grey", lw=0.5)
    ax.set_xticks(x, [t.id for t in tests], rotation=15, fontsize=7)
    ax.legend(fontsize=7)
    what = "mean residual × sign(rate)" if drift else "residual rms"
    plots._style(ax, textwrap.fill(f.signature["reading"], 70), f"{what} {label_of(ch)}",
                 "its tests, in the running order")


def _folded(ax, f, ch: str, tests: list, with_it: dict, s: float, bins: int = 36) -> None:
    """A ripple: the fast residual (above the drive's band) averaged over one period of
    its order of the part's angle, base vs with the ripple."""
    q, order = f.signature["quantity"], f.signature["periods_per_rev"]
    centres = (np.arange(bins) + 0.5) * 360.0 / bins
    for label, pick, color in (("base model", lambda t: t, "black"),
                               ("with the ripple", lambda t: with_it[t.id], "tab:orange")):
        phase, fast = [], []
        for t in tests:
            if ch in t.measured and q in t.states:
                phase.append(np.mod(order * t.states[q], 2 * np.pi))
                fast.append(fast_part(pick(t)).residual(ch))
        if not phase:
            continue
        k = np.minimum((np.concatenate(phase) / (2 * np.pi) * bins).astype(int), bins - 1)
        n = np.bincount(k, minlength=bins)
        mean = np.bincount(k, weights=np.concatenate(fast), minlength=bins) / np.maximum(n, 1)
        ax.plot(centres, s * mean, "o-", ms=3, color=color, label=label)
    ax.axhline(0.0, color="grey", lw=0.5)
    ax.legend(fontsize=7)
    plots._style(ax, textwrap.fill(f.signature["reading"], 70),
                 f"fast residual, mean per bin {label_of(ch)}",
                 f"{order:.0f}·{q} mod 360 [°]")


def _lead_channel(f, tests: list, with_it: dict) -> str:
    """The channel the reality acts on: the lagging sensor's, else the one whose residual
    it shrinks the most."""
    if f.signature["kind"] == "lag":
        return f.signature["quantity"]

    def shrink(ch: str) -> float:
        before = sum(float(np.sum(t.residual(ch) ** 2)) for t in tests if ch in t.measured)
        after = sum(float(np.sum(with_it[t.id].residual(ch) ** 2)) for t in tests
                    if ch in t.measured)
        return before / after if after > 0 else 0.0
    return max(dict.fromkeys(ch for t in tests for ch in t.measured), key=shrink)


def write_all(result, figdir: Path, failures: list[str] | None = None) -> None:
    """Every discovery figure, each on its own: one that fails is listed in ``failures``."""
    prepared = result.base.prepared
    controls = [prepared[t] for t in dict.fromkeys(result.comparison.test)]
    models = {m: tw for m, tw in result.twins.items()}
    shown = controls or [prepared[r.id] for r in result.residual_tests]
    physics = {m: models[m] for m in ("base", "extended") if m in models}
    drawers = {
        "reversal_zoom": lambda p: reversal_zoom(result, p),
        "structure_test": lambda p: structure_bars(result, p),
        "resolution": lambda p: resolution_bars(result, p),
        "stick_slip": lambda p: stick_slip(result, p),
        "unexplained": lambda p: unexplained_signature(result, p),
        "outside_reality": lambda p: outside_reality(result, p),
        "comparison": lambda p: comparison_bars(result, p),
        "time_histories": lambda p: plots.time_histories(shown, models, p),
        "hysteresis": lambda p: plots.hysteresis_loops(shown, physics, p),
        "residuals": lambda p: plots.residuals(shown, physics, p),
    }
    if result.neural_model is not None:
        drawers["neural_learned"] = lambda p: _neural_learned(result, p)
    for name, draw in drawers.items():
        try:
            draw(figdir / f"{name}.png")
        except Exception as exc:  # a figure is a view of the answer, never the answer
            log.warning("figure %s.png failed: %s: %s", name, type(exc).__name__, exc,
                        exc_info=exc)
            plt.close("all")
            if failures is not None:
                failures.append(f"figure {name}.png: {type(exc).__name__}: {exc}")


def _neural_learned(result, path: Path) -> None:
    from mbst.discovery.evidence.neural import plot_learned

    plot_learned(result.neural_model, result.residual_tests, path)


def _screened_out_note(rnd: dict) -> str:
    """A second axis line for the candidates the round's screen spared a refit."""
    screen = rnd.get("shortlist_screen")
    if not screen:
        return ""
    refitted = {c["key"] for c in rnd["candidates"]}
    spared = [k for k in screen["predicted_gain"] if k not in refitted]
    return (f"\n{len(spared)} more not refitted: the screen predicted each below "
            f"{100 * screen['needed']:.0f} % (discovery.md)" if spared else "")


def _rivals_screened_note(rnd: dict) -> str:
    """A further axis line for the rivals outside the catalogue that one step put under
    half the winner's share (``rivals.SCREEN_SHARE``): not drawn, as not refitted."""
    spared = rnd.get("rivals_screened", [])
    said = ", ".join(f"{g['key'].split(':')[0]} {100 * g['predicted_gain']:.1f} %"
                     for g in spared)
    return (f"\nrivals not refitted, one step under half the winner's share: {said}"
            if spared else "")
