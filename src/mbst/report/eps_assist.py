"""Report of the power assist (seed 001 Fig. 12–16, Table 2): curves, damping, bounds."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from mbst.systems.eps import assist as eps_assist

# torque span of the inset that shows the curve's foot
FOOT_NM = 0.6


def _binned(t: np.ndarray, a: np.ndarray, bins: int = 40, span: float | None = None
            ) -> tuple[np.ndarray, np.ndarray]:
    """Median assist per torque bin: the raw points of a test are thousands and noisy."""
    if span is not None:
        keep = np.abs(t) <= span
        t, a = t[keep], a[keep]
        if not len(t):
            return np.array([]), np.array([])
    edges = np.linspace(np.min(t), np.max(t), bins + 1)
    k = np.clip(np.digitize(t, edges) - 1, 0, bins - 1)
    tc, ac = [], []
    for i in range(bins):
        sel = k == i
        if sel.sum() >= 5:
            tc.append(np.median(t[sel]))
            ac.append(np.median(a[sel]))
    return np.array(tc), np.array(ac)


def measured_points(result: Any, span: float | None = None
                    ) -> dict[str, tuple[np.ndarray, np.ndarray, str]]:
    """Per assist mode, measured (torsion-bar torque, assist torque) of the slow powered tests.

    Binned medians; ``span`` keeps only |T| ≤ span (the curve's foot, where c1 shows).
    """
    from mbst.systems.eps.model import assist_points

    model, p = result.model, result.params
    idx = model.param_index
    prepared = list(result.prepared.values())
    passive = [pt for pt in prepared if pt.spec.motor != "assist"
               and pt.spec.role == "identification"]
    out: dict[str, list] = {}
    for on in prepared:
        if on.spec.motor != "assist" or not eps_assist.quasi_static(on) \
                or "steering_torque_nm" not in on.measured:
            continue
        offs = [pt for pt in passive if pt.scenario == on.scenario
                and eps_assist.quasi_static(pt) and "steering_torque_nm" in pt.measured]
        off = min(offs, key=lambda pt: np.max(np.abs(pt.omega_rad_per_s))) if offs else None
        got = assist_points(on, off, p, p[idx["offset.steering_torque_nm"]],
                            p[idx["offset.motor_current_a"]])
        if got is None:
            continue
        t, a = _binned(got[0], got[1], span=span)
        out.setdefault(on.spec.assist_mode or "default", []).append((t, a, f"{on.id}: {got[2]}"))
    return {m: (np.concatenate([x[0] for x in v]), np.concatenate([x[1] for x in v]),
                "; ".join(x[2] for x in v)) for m, v in out.items()}


def _family(model: Any, p: np.ndarray) -> str:
    """The identified characteristic's form: ``"hps"`` or ``"eps"``."""
    return "hps" if p[model.param_index["assist.family"]] == 1.0 else "eps"


def _std_errors(result: Any) -> dict[str, float]:
    """Standard error per parameter: the held pre-identified ones, then each stage's."""
    std = dict(result.preid.get("held", {}))
    for st in result.stages:
        std.update(st.std_error)
    return std


def _plot_characteristic(result: Any, curves: dict[str, dict[str, float]], family: str,
                         out: Path) -> None:
    """``assist_characteristic.png``: measured and identified curve per mode, foot inset."""
    import matplotlib.pyplot as plt

    from mbst.report.plots import save_figure

    points = measured_points(result)
    fig, ax = plt.subplots(figsize=(6.4, 4.4))
    for k, (mode, c) in enumerate(curves.items()):
        color = f"C{k}"
        # each curve over the torque its own tests reached (robustly: off − on has outliers)
        t_max = float(np.percentile(np.abs(points[mode][0]), 95)) if mode in points else 2.0
        grid = np.linspace(-t_max, t_max, 400)
        if mode in points:
            t, a, src = points[mode]
            ax.plot(t, a, "o", ms=3, color=color, alpha=0.6,
                    label=f"{mode}: measured ({'current' if 'current' in src else 'off − on'})")
        ax.plot(grid, eps_assist.characteristic(grid, c, family), color=color, lw=1.6,
                label=f"{mode}: identified " + ", ".join(f"{q}={v:.3g}" for q, v in c.items()))
    ax.set_xlabel("torsion-bar torque T [N·m]", fontsize=8)
    ax.set_ylabel("assist torque A(T), column side [N·m]", fontsize=8)
    ax.set_title(f"Power-assist characteristic per mode ({family.upper()} form)", fontsize=9)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="upper left")
    # the curve's foot, where its slope at zero torque (c1) is read
    foot = measured_points(result, span=FOOT_NM)
    if foot:
        _plot_foot_inset(ax, foot, curves, family)
    fig.tight_layout()
    save_figure(fig, out / "assist_characteristic.png")


def _plot_foot_inset(ax: Any, foot: dict[str, tuple[np.ndarray, np.ndarray, str]],
                     curves: dict[str, dict[str, float]], family: str) -> None:
    """Inset of the curves' foot, |T| ≤ ``FOOT_NM``, with the measured points there."""
    ins = ax.inset_axes([0.62, 0.08, 0.35, 0.35])
    grid = np.linspace(-FOOT_NM, FOOT_NM, 200)
    for k, (mode, c) in enumerate(curves.items()):
        if mode in foot:
            ins.plot(foot[mode][0], foot[mode][1], "o", ms=2, color=f"C{k}", alpha=0.6)
        ins.plot(grid, eps_assist.characteristic(grid, c, family), color=f"C{k}", lw=1.2)
    ins.set_title(f"|T| ≤ {FOOT_NM:g} N·m", fontsize=7)
    ins.tick_params(labelsize=6)
    ins.grid(alpha=0.3)


def _plot_damping(damp: dict[float, float], std: dict[str, float], out: Path) -> None:
    """``active_damping.png``: identified active damping per vehicle speed, ± std error."""
    import matplotlib.pyplot as plt

    from mbst.report.plots import save_figure

    fig, ax = plt.subplots(figsize=(5.2, 3.6))
    v = np.array(list(damp))
    c = np.array(list(damp.values()))
    e = np.array([std.get(eps_assist.speed_param(s), np.nan) or np.nan for s in damp])
    ax.errorbar(v, c, yerr=np.where(np.isfinite(e), e, 0.0), fmt="o-", capsize=4,
                color="tab:blue", label="identified ± std error")
    ax.set_xlabel("vehicle speed [km/h]", fontsize=8)
    ax.set_ylabel("active damping c_ad [N·m·s/rad]", fontsize=8)
    ax.set_title("Active damping vs vehicle speed", fontsize=9)
    ax.set_ylim(bottom=0)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    save_figure(fig, out / "active_damping.png")


def _curve_table(curves: dict[str, dict[str, float]], family: str,
                 std: dict[str, float]) -> list[str]:
    """The section's head and its table of curve coefficients per mode, ± std error."""
    lines = ["", "## Power assist (seed 001 Table 1–2)", "",
             f"Characteristic family: {family.upper()}.", "",
             "| mode | " + " | ".join(eps_assist.curve_names(family)) + " |",
             "|---|" + "---|" * len(eps_assist.curve_names(family))]
    for mode, cv in curves.items():
        names = [eps_assist.mode_param(mode, q) if mode != "default" else f"assist.{q}"
                 for q in cv]
        cells = [f"{cv[q]:.4g} ± {std.get(n, float('nan')):.2g}" for q, n in zip(cv, names)]
        lines.append(f"| {mode} | " + " | ".join(cells) + " |")
    return lines


def _boost_curve_note(measured: dict[str, Any] | None) -> list[str]:
    """Where the curves came from the motor current: how, and what was fitted beside."""
    if not measured:
        return []
    beside = measured["fitted_beside"]
    return ["", f"Curves of {', '.join(measured['points'])} and the active damping per "
            "speed from the motor current against "
            f"the torque sensor ({measured['method']}, {sum(measured['points'].values())} "
            f"points of {', '.join(measured['tests'])}), held by the cascade; fitted "
            "beside them: " + ", ".join(f"`{n}` {v:.4g}" for n, v in beside.items()) + "."]


def _damping_table(damp: dict[float, float], std: dict[str, float]) -> list[str]:
    """Table of the active damping per vehicle speed, ± std error (none without one)."""
    if not damp:
        return []
    lines = ["", "| vehicle speed [km/h] | active damping [N·m·s/rad] |", "|---|---|"]
    for s, val in damp.items():
        lines.append(f"| {s:g} | {val:.4g} ± {std.get(eps_assist.speed_param(s), float('nan')):.2g} |")
    return lines


def _total_friction_nm(model: Any, p: np.ndarray) -> float:
    """Identified friction at the column, C_o + F_o·r + F_m·N, in N·m."""
    g = lambda n: p[model.param_index[n]]  # noqa: E731
    return g("steering_column.coulomb_nm") + g("rack.coulomb_n") * g("pinion_radius_m") + \
        g("motor.coulomb_nm") * g("worm_gear_ratio")


def _friction_bounds_table(bounds: dict[str, dict[str, float | None]], model: Any,
                           p: np.ndarray) -> list[str]:
    """Engine-off/on loop half-widths per cut-out beside the identified friction."""
    if not bounds:
        return []
    total = _total_friction_nm(model, p)
    lines = ["", "Friction bounds from the half-width AB of the angle–torque loop "
             "(seed 001 Fig. 11): the engine-off width bounds the whole friction from "
             "above, the engine-on width (the assist works against the friction below "
             "the pinion) from below.", "",
             "| cut-out | engine off AB [N·m] | engine on AB [N·m] | identified C_o + F_o·r + F_m·N [N·m] |",
             "|---|---|---|---|"]
    for scen, b in bounds.items():
        off = b.get("half_width_off_nm")
        on = b.get("half_width_on_nm")
        fmt = lambda x: "–" if x is None else f"{x:.3f}"  # noqa: E731
        lines.append(f"| {scen} | {fmt(off)} | {fmt(on)} | {total:.3f} |")
    return lines


def write(result: Any, out: Path) -> list[str]:
    """Figures ``assist_characteristic.png`` and ``active_damping.png``; markdown lines."""
    model, p = result.model, result.params
    if not any(pt.spec.motor == "assist" for pt in result.prepared.values()):
        return []
    family = _family(model, p)
    curves = eps_assist.curves(model, p)
    std = _std_errors(result)
    _plot_characteristic(result, curves, family, out)
    damp = eps_assist.dampings(model, p)
    if damp:
        _plot_damping(damp, std, out)
    bounds = result.preid.get("assist_friction_bounds", {})
    return (_curve_table(curves, family, std) + _boost_curve_note(result.preid.get("boost_curve"))
            + _damping_table(damp, std) + _friction_bounds_table(bounds, model, p))
