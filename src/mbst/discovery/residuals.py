"""Where in the state space the base model's error lives (issue #4, step 1).

For every identification test and output channel, the residual energy is
split over regions of the base model's own state: just after a motion
reversal, high column speed, large torsion-bar load, large torsion angle,
and each fifth of the rack travel. A region that holds much more of the
energy than of the time ("enrichment" > 1) is where the missing effect acts:
reversals for backlash, Dahl and Stribeck, load for load-dependent friction,
one rack position for a position-dependent one, large torsion angle for a
limit stop.
"""

from __future__ import annotations

import numpy as np

from mbst.core.filtering import motion_reversals
from mbst.discovery.data import TestResidual

REVERSAL_WINDOW_S = 0.2


def regions(t: TestResidual) -> dict[str, np.ndarray]:
    """Boolean masks of the state-space regions of one test."""
    n = len(t.time_s)
    after = np.zeros(n, bool)
    for r in motion_reversals(t.omega_rad_per_s):
        after[r: r + int(round(REVERSAL_WINDOW_S / t.dt_s))] = True
    speed = np.abs(t.omega_rad_per_s)
    out = {
        "after_reversal": after,
        "high_speed": speed > np.quantile(speed, 0.75),
    }
    load = t.states.get("torsion_bar_torque_nm")
    if load is not None and np.ptp(load) > 0:
        out["large_load"] = np.abs(load) > np.quantile(np.abs(load), 0.75)
    pin = t.states.get("pinion_angle_rad")
    if pin is not None:
        tors = np.abs(t.angle_rad - pin)
        if np.ptp(tors) > 0:
            out["large_torsion_angle"] = tors > np.quantile(tors, 0.9)
    rack = t.states.get("rack_position_m")
    if rack is not None and np.ptp(rack) > 1e-4:
        edges = np.linspace(rack.min(), rack.max(), 6)
        for k in range(5):
            m = (rack >= edges[k]) & (rack <= edges[k + 1])
            out[f"rack_travel_{k + 1}_of_5"] = m
    return out


def residual_locations(tests: list[TestResidual]) -> list[dict]:
    """Per test and channel: share of residual energy and of time in each region.

    Returns rows ``{test, channel, region, energy_share, time_share, enrichment}``.
    """
    rows = []
    for t in tests:
        masks = regions(t)
        for ch in t.channels:
            r = t.residual(ch)
            r = r - np.mean(r)  # a constant is an offset, not a location
            e = r * r
            total = float(e.sum())
            if total <= 0:
                continue
            for name, m in masks.items():
                ts = float(m.mean())
                es = float(e[m].sum() / total)
                rows.append({"test": t.id, "channel": ch, "region": name, "energy_share": es,
                             "time_share": ts, "enrichment": es / ts if ts > 0 else 0.0})
    return rows


def dominant_regions(rows: list[dict], min_enrichment: float = 1.5) -> list[tuple[str, float]]:
    """Regions ranked by energy-weighted enrichment over all tests and channels."""
    acc: dict[str, list[float]] = {}
    for r in rows:
        acc.setdefault(r["region"], []).append(r["enrichment"])
    ranked = sorted(((k, float(np.median(v))) for k, v in acc.items()), key=lambda x: -x[1])
    return [(k, v) for k, v in ranked if v >= min_enrichment]
