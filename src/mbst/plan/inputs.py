"""Candidate excitation inputs (seed 000: harmonic, sweep, ramp, impact).

An input candidate is scenario-independent in shape; its amplitude is a
fraction of the scenario's reference amplitude (a blocked column twists the
torsion bar a few degrees, the tires only slide beyond ~90°), so one input
list serves every cut-out. ``test_input`` turns a (scenario, input) pair into
the absolute ``input:`` entry of campaign.yaml, ``profile`` into samples.
"""

from __future__ import annotations

import math

import numpy as np

from mbst.systems.eps.bench import input_profile as bench_profile

# kinds the planner can generate, with their required keys (besides amplitude_scale, cost)
INPUT_KINDS: dict[str, tuple[str, ...]] = {
    "sine": ("frequency_hz",),
    "sweep": ("f0_hz", "f1_hz", "duration_s"),
    "ramp": ("ramp_time_s",),
    "impact": ("width_s",),
}
LEAD_S = 0.5  # at rest before and after the motion (the bench's convention)


def test_input(kind: str, amplitude_deg: float, options: dict) -> dict:
    """The absolute ``input:`` entry of a test (campaign.yaml and the bench).

    Parameters
    ----------
    kind
        One of ``INPUT_KINDS``.
    amplitude_deg
        Scenario reference amplitude × the input's ``amplitude_scale``.
    options
        The input candidate's shape keys (frequency, cycles, ramp time...).
    """
    a = round(float(amplitude_deg), 6)
    if kind == "sine":
        return {"kind": "sine", "amplitude_deg": a, "frequency_hz": float(options["frequency_hz"]),
                "cycles": int(options.get("cycles", 3))}
    if kind == "sweep":
        return {"kind": "sweep", "amplitude_deg": a, "f0_hz": float(options["f0_hz"]),
                "f1_hz": float(options["f1_hz"]), "duration_s": float(options["duration_s"])}
    if kind == "ramp":
        # the rate scales with the amplitude: every scenario ramps in the same time
        return {"kind": "ramp", "amplitude_deg": a,
                "rate_deg_per_s": round(a / float(options["ramp_time_s"]), 6),
                "hold_s": float(options.get("hold_s", 1.0))}
    if kind == "impact":
        return {"kind": "impact", "amplitude_deg": a, "width_s": float(options["width_s"]),
                "count": int(options.get("count", 4)),
                "spacing_s": float(options.get("spacing_s", 1.0))}
    raise ValueError(f"the planner cannot generate input kind '{kind}'")


def impact_profile(spec: dict, sample_rate_hz: float) -> tuple[np.ndarray, np.ndarray]:
    """Short raised-cosine angle pulses of alternating sign, at rest in between.

    A sharp impact excites the linear dynamics (seed 000); the pulse is smooth
    so its rate stays finite for the angle-driven model.
    """
    a = math.radians(float(spec.get("amplitude_deg", 10.0)))
    w = float(spec.get("width_s", 0.1))
    count = int(spec.get("count", 4))
    gap = float(spec.get("spacing_s", 1.0))
    dur = LEAD_S + count * (w + gap) + LEAD_S
    t = np.arange(0.0, dur, 1.0 / sample_rate_hz)
    ang = np.zeros_like(t)
    for k in range(count):
        t0 = LEAD_S + k * (w + gap)
        inside = (t >= t0) & (t <= t0 + w)
        sign = 1.0 if k % 2 == 0 else -1.0
        ang[inside] += sign * a * 0.5 * (1.0 - np.cos(2.0 * np.pi * (t[inside] - t0) / w))
    return t, ang


def profile(spec: dict, sample_rate_hz: float) -> tuple[np.ndarray, np.ndarray]:
    """Time and steering angle (rad) of an absolute input entry (see ``test_input``)."""
    if spec["kind"] == "impact":
        return impact_profile(spec, sample_rate_hz)
    return bench_profile(spec, sample_rate_hz)


def duration_s(spec: dict) -> float:
    """Length of a test in seconds (for reports)."""
    t, _ = profile(spec, 50.0)
    return float(t[-1])
