"""Figures for engineers: time histories, hysteresis loops, residuals."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from mbst.core.filtering import motion_reversals
from mbst.identify.fitting import PreparedTest

LABELS = {
    "steering_torque_nm": "steering torque [N·m]",
    "rack_position_m": "rack position [mm]",
    "tie_rod_force_left_n": "tie-rod force left [N]",
    "tie_rod_force_right_n": "tie-rod force right [N]",
    "motor_angle_rad": "motor angle [rad]",
    "motor_current_a": "motor current [A]",
    "position_m": "position [mm]",
    "motor_force_n": "motor force [N]",
    "steering_angle_rad": "steering angle [rad]",
    "position_reference_m": "position reference [mm]",
    "displacement_m": "displacement [mm]",
    "friction_force_n": "friction force [kN]",
}
SCALE = {"rack_position_m": 1e3, "position_m": 1e3, "position_reference_m": 1e3,
         "displacement_m": 1e3, "friction_force_n": 1e-3}


def label_of(channel: str) -> str:
    """The axis label of a channel (its name where the table has none)."""
    return LABELS.get(channel, channel)
MODEL_STYLE = {
    "base": dict(color="tab:red", lw=1.1, ls="--"),
    "extended": dict(color="tab:green", lw=1.1, ls="-"),
    "true": dict(color="tab:gray", lw=0.9, ls=":"),
    "sindy": dict(color="tab:purple", lw=0.9, ls="-."),
    "neural": dict(color="tab:orange", lw=0.9, ls="-."),
    "physics+learned": dict(color="tab:olive", lw=0.9, ls="-."),
}


def save_figure(fig, path: Path, tight: bool = False) -> None:
    """``tight``: the saved area fits what is drawn (long tick labels); it draws the
    figure twice, twice the time of a figure of long traces, so only where asked."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110, bbox_inches="tight" if tight else None)
    plt.close(fig)


def _style(ax, title: str, ylabel: str, xlabel: str = "time [s]") -> None:
    ax.set_title(title, fontsize=9)
    ax.set_ylabel(ylabel, fontsize=8)
    ax.set_xlabel(xlabel, fontsize=8)
    ax.grid(alpha=0.3)


def _finish(fig, axes, path: Path) -> None:
    """Legend in the first cell (the styles repeat in every cell), then save."""
    if axes[0][0].get_legend_handles_labels()[0]:  # an empty figure (no control test) has none
        axes[0][0].legend(fontsize=8)
    fig.tight_layout()
    save_figure(fig, path)


def _channel_grid(tests: list[PreparedTest], row_height: float):
    """A tests × channels grid; yields (test, channel, axes, unit scale) per filled cell.

    The right tie-rod channel only mirrors the left one and is not shown;
    cells of channels a test does not have are blanked.
    """
    chans = [c for c in LABELS if any(c in pt.measured for pt in tests)]
    chans += sorted({c for pt in tests for c in pt.measured} - set(chans))
    chans = [c for c in chans if c != "tie_rod_force_right_n"] or chans
    fig, axes = plt.subplots(len(tests), len(chans),
                             figsize=(4.2 * len(chans), row_height * len(tests)), squeeze=False)

    def cells():
        for i, pt in enumerate(tests):
            for j, ch in enumerate(chans):
                if ch in pt.measured:
                    yield pt, ch, axes[i][j], SCALE.get(ch, 1.0)
                else:
                    axes[i][j].set_axis_off()

    return fig, axes, cells()


def time_histories(tests: list[PreparedTest], models: dict[str, dict], path: Path) -> None:
    """Measured vs simulated (both filtered), one row per test, one column per channel."""
    fig, axes, cells = _channel_grid(tests, 2.6)
    for pt, ch, ax, s in cells:
        ax.plot(pt.time_s, s * pt.measured[ch], color="black", lw=1.4, label="measured")
        for name, twins in models.items():
            if pt.id in twins and ch in twins[pt.id]:
                ax.plot(pt.time_s, s * twins[pt.id][ch], label=name, **MODEL_STYLE.get(name, {}))
        _style(ax, f"{pt.id} ({pt.spec.role})", label_of(ch))
    _finish(fig, axes, path)


def _loop_x(pt: PreparedTest, key: str) -> np.ndarray:
    if key == "input":
        return pt.input_signal
    if key.startswith("rate:"):
        return np.gradient(pt.measured[key[5:]], pt.dt_s)
    return pt.measured[key]


def hysteresis_loops(tests: list[PreparedTest], models: dict[str, dict], path: Path) -> None:
    """The family's loop: steering angle vs torque for EPS (seed 000 Fig. 6/8, seed 001
    Fig. 11–16), velocity vs motor force (the friction characteristic) for an axis.
    """
    spec = tests[0].model.hysteresis if tests and tests[0].model else None
    if spec is None:
        return
    xkey, ych, xlabel, ylabel, xscale = spec
    need = xkey[5:] if xkey.startswith("rate:") else (None if xkey == "input" else xkey)
    tests = [pt for pt in tests if ych in pt.measured and (need is None or need in pt.measured)]
    n = max(len(tests), 1)
    cols = min(4, n)
    rows = int(np.ceil(n / cols))
    fig, axes = plt.subplots(rows, cols, figsize=(3.8 * cols, 3.3 * rows), squeeze=False)
    for k, pt in enumerate(tests):
        ax = axes[k // cols][k % cols]
        x = xscale * _loop_x(pt, xkey)
        ax.plot(x, pt.measured[ych], color="black", lw=1.2, label="measured")
        for name, twins in models.items():
            if pt.id in twins:
                ax.plot(x, twins[pt.id][ych], label=name, **MODEL_STYLE.get(name, {}))
        ax.set_title(f"{pt.id}\n{pt.scenario}, {pt.spec.role}{_assist_label(pt)}", fontsize=8)
        ax.set_xlabel(xlabel, fontsize=8)
        ax.set_ylabel(ylabel, fontsize=8)
        ax.grid(alpha=0.3)
    for k in range(len(tests), rows * cols):
        axes[k // cols][k % cols].set_axis_off()
    if tests:
        axes[0][0].legend(fontsize=7)
    fig.tight_layout()
    save_figure(fig, path)


def _assist_label(pt: PreparedTest) -> str:
    if pt.spec.motor != "assist":
        return ""
    speed = "" if pt.spec.vehicle_speed_kph is None else f" {pt.spec.vehicle_speed_kph:g} km/h"
    return f", assist {pt.spec.assist_mode or ''}{speed}"


def residuals(tests: list[PreparedTest], models: dict[str, dict], path: Path) -> None:
    """Measured minus simulated over time, with the motion reversals marked."""
    fig, axes, cells = _channel_grid(tests, 2.4)
    for pt, ch, ax, s in cells:
        for name, twins in models.items():
            if pt.id in twins and ch in twins[pt.id]:
                ax.plot(pt.time_s, s * (pt.measured[ch] - twins[pt.id][ch]), label=name,
                        **{**MODEL_STYLE.get(name, {}), "ls": "-"})
        for r in motion_reversals(pt.omega_rad_per_s):
            ax.axvline(pt.time_s[r], color="0.8", lw=0.6, zorder=0)
        _style(ax, f"{pt.id}: residual", label_of(ch), "time [s] (grey: motion reversals)")
    _finish(fig, axes, path)


def filter_effect(tests: list[PreparedTest], path: Path, zoom_s: float = 0.4,
                  measured_inputs: dict[str, tuple[str, np.ndarray]] | None = None) -> None:
    """Raw vs filtered measurement of one test: the whole test and a zoom on a reversal.

    The test is the identification test with the most channels (ties: the first);
    the zoom is centred on its first motion reversal, where friction and backlash
    act and where the filter's lag matters most. ``measured_inputs`` (test id ->
    channel name, raw samples) adds a first row: the measured input against the
    model input derived from it.
    """
    ident = [pt for pt in tests if pt.spec.role == "identification"] or tests
    if not ident:
        return
    pt = max(ident, key=lambda p: len(p.measured))
    rows = [(c, pt.raw[c], pt.measured[c], f"filtered (τ = {pt.tau_s * 1e3:g} ms)")
            for c in LABELS if c in pt.measured]
    if measured_inputs and pt.id in measured_inputs:
        name, raw = measured_inputs[pt.id]
        rows.insert(0, (name, raw, pt.input_signal, "model input"))
    rev = motion_reversals(pt.input_rate)
    centre = pt.time_s[rev[0]] if len(rev) else pt.time_s[len(pt.time_s) // 2]
    win = np.abs(pt.time_s - centre) <= zoom_s / 2
    fig, axes = plt.subplots(len(rows), 2, figsize=(11, 2.3 * len(rows)), squeeze=False,
                             gridspec_kw={"width_ratios": [2, 1]})
    for i, (ch, raw, used, label) in enumerate(rows):
        s = SCALE.get(ch, 1.0)
        for j, mask in enumerate((slice(None), win)):
            ax = axes[i][j]
            ax.plot(pt.time_s[mask], s * raw[mask], color="0.7", lw=0.6, label="raw")
            ax.plot(pt.time_s[mask], s * used[mask], color="tab:blue", lw=1.1, label=label)
            title = (f"{pt.id}: {ch}" if j == 0
                     else f"zoom: {zoom_s:g} s around the first reversal")
            _style(ax, title, LABELS.get(ch, ch))
        axes[i][0].axvspan(pt.time_s[win][0], pt.time_s[win][-1], color="tab:orange", alpha=0.15)
        axes[i][0].legend(fontsize=8, loc="upper right")
    fig.tight_layout()
    save_figure(fig, path)
