"""Figures of ``mbst plan``: sensitivity heat map, information vs cost, seed 000 Fig. 6."""

from __future__ import annotations

import math
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from mbst.plan.config import PlanConfig
from mbst.plan.inputs import profile, test_input
from mbst.plan.selection import Step
from mbst.plan.sensitivity import Sensitivity
from mbst.systems.eps import simulate as eps
from mbst.systems.eps.params import PARAM_SPECS


def _short(name: str) -> str:
    parts = name.split(".")
    return f"{parts[0]}.{parts[1].split('_')[0]}" if len(parts) > 1 else name


def _save(fig, path: Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def sensitivity_heatmap(sens: Sensitivity, cfg: PlanConfig, path: Path) -> None:
    """Sensors × parameters per scenario: response change over the range, in noise σ.

    Seed 000's question — does the sensor capture a response change when the
    parameter sweeps its range? — as log₁₀ of the rms change per sample over
    the noise rms, the largest over the scenario's inputs.
    """
    sids = [s.id for s in cfg.scenarios]
    ncol = min(3, len(sids))
    nrow = math.ceil(len(sids) / ncol)
    fig, axes = plt.subplots(nrow, ncol, figsize=(5.2 * ncol, 0.42 * len(sens.sensors) * nrow
                                                  + 2.2 * nrow), squeeze=False,
                             layout="constrained")
    vmax = max(1.0, float(np.log10(max(sens.swing.max(), 1e-12))))
    im = None
    for k, sid in enumerate(sids):
        ax = axes[k // ncol][k % ncol]
        cells = [c for c, cell in enumerate(sens.cells) if cell.scenario_id == sid]
        val = np.log10(np.maximum(sens.swing[cells].max(axis=0), 1e-3))  # (S, P)
        im = ax.imshow(val, aspect="auto", cmap="viridis", vmin=-1.0, vmax=vmax)
        ax.set_title(sid, fontsize=9)
        ax.set_xticks(range(len(sens.unknowns)))
        ax.set_xticklabels([_short(u) for u in sens.unknowns], rotation=90, fontsize=6)
        ax.set_yticks(range(len(sens.sensors)))
        ax.set_yticklabels(sens.sensors if k % ncol == 0 else [], fontsize=7)
        for s in range(val.shape[0]):
            for p in range(val.shape[1]):
                if val[s, p] < 0.0:  # below the noise: the sensor cannot see it
                    ax.text(p, s, "·", ha="center", va="center", color="w", fontsize=7)
    for k in range(len(sids), nrow * ncol):
        axes[k // ncol][k % ncol].axis("off")
    fig.suptitle("response change over each parameter's range (log10 rms / noise rms, best "
                 "input); '·' = below the noise", fontsize=10)
    fig.colorbar(im, ax=axes.ravel().tolist(), shrink=0.8, label="log10(Δy rms / σ)")
    _save(fig, path)


def information_vs_cost(steps: list[Step], naive: tuple[float, float, float] | None,
                        target: float, path: Path) -> None:
    """Bits gained and worst relative std as the greedy adds sensors and tests."""
    cost = [s.cost for s in steps]
    bits = [s.bits for s in steps]
    worst = [min(s.worst_relative_std, 1e3) for s in steps]
    fig, ax = plt.subplots(figsize=(8.5, 4.8))
    ax.step(cost, bits, where="post", color="tab:blue", marker="o", ms=4)
    ax.set_xlabel("campaign cost (identification part)")
    ax.set_ylabel("information gained over the ranges [bits]", color="tab:blue")
    for i, s in enumerate(steps):
        ax.annotate(str(i), (s.cost, s.bits), textcoords="offset points", xytext=(3, 3),
                    fontsize=7, color="tab:blue")
    ax2 = ax.twinx()
    ax2.step(cost, worst, where="post", color="tab:red", marker="s", ms=3)
    ax2.axhline(target, color="tab:red", ls=":", lw=1)
    ax2.set_yscale("log")
    ax2.set_ylabel("worst predicted relative std (over the sweep)", color="tab:red")
    if naive is not None:
        ax.plot([naive[0]], [naive[1]], marker="*", ms=12, color="k", ls="none",
                label=f"naive campaign (worst σ {naive[2]:.2g})")
        ax.legend(loc="lower right", fontsize=8)
    ax.set_title("greedy selection: information per unit cost (numbers: steps in "
                 "selection_path.csv)", fontsize=9)
    fig.tight_layout()
    _save(fig, path)


def frequency_comparison(cfg: PlanConfig, path: Path) -> dict[str, float]:
    """Seed 000 Fig. 6: angle–torque loops of one cut-out at two input frequencies.

    Both sines have the scenario's reference amplitude. Dashed: every unknown
    viscous/damping parameter at the top of its range — the gap between the
    lines is what each frequency tells about them. Returns that gap per
    frequency (rms torque change / torque noise).
    """
    sc = cfg.scenario(cfg.fig_scenario)
    p0 = cfg.nominal_vector()
    p1 = p0.copy()
    damp = [u for u in cfg.unknowns if "viscous" in u.name or "damping" in u.name]
    for u in damp:
        p1[[s.name for s in PARAM_SPECS].index(u.name)] = u.high
    noise = next((s.noise for s in cfg.sensors if s.name == "steering_torque_nm"), 0.02)
    fig, axes = plt.subplots(1, 2, figsize=(10, 4.4), sharey=True)
    gaps = {}
    for ax, iid in zip(axes, cfg.fig_inputs, strict=True):
        inp = cfg.input(iid)
        spec = test_input(inp.kind, sc.amplitude_deg, inp.options)
        t, ang = profile(spec, cfg.sample_rate_hz)
        tq = [eps.simulate(sc.scenario, sc.motor, t, ang, p)["steering_torque_nm"]
              for p in (p0, p1)]
        ax.plot(np.degrees(ang), tq[0], lw=1.0, label="centre of the ranges")
        ax.plot(np.degrees(ang), tq[1], lw=1.0, ls="--", label="damping at the top of range")
        gap = float(np.sqrt(np.mean((tq[1] - tq[0]) ** 2)) / noise)
        gaps[iid] = gap
        freq = spec.get("frequency_hz", spec.get("f1_hz", float("nan")))
        ax.set_title(f"{sc.id}, {iid} ({freq} Hz, {sc.amplitude_deg:g}°): "
                     f"gap {gap:.0f} σ", fontsize=9)
        ax.set_xlabel("steering-wheel angle [deg]")
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("steering torque [N·m]")
    axes[0].legend(fontsize=8)
    fig.suptitle("seed 000 Fig. 6: the faster input must overcome more inertia and viscous "
                 "torque — its loop opens and separates the damping parameters", fontsize=9)
    fig.tight_layout()
    _save(fig, path)
    return gaps
