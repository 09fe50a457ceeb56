"""Candidate next tests, and how each would look when logged on this rig.

The candidates stay on the cut-outs the campaign already has set up and
inside the rig's limits the campaign itself shows: per cut-out, no larger
angle amplitude and no faster angle rate than its identification tests drove.
Per cut-out: slow to fast sines at full stroke (rate-limited) and small-stroke
sines (many reversals: backlash, presliding, a Stribeck rise). Every one starts
and ends with a cosine taper. Triangles were candidates until their start from
rest at full speed proved to be where twin and rig differ most: on the bench
the true model fitted a 2-s triangle worse than the base model did (column
Stribeck, seed 1: cost 1.74e-5 against 1.17e-5) and three of them took a
predicted 18.7 % share of the stage down to 8.9 %.

A candidate is *predicted*, not run: the model as discovery left it is
simulated on the input, white noise at the level the preprocessing measured
on the campaign's own channels is added, and the result goes through the very
preprocessing a logged test gets (``prepare_frame``). Its cost is its
duration: the loop's budget is test time.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from mbst.core.model import ModelDefinition
from mbst.identify.fitting import PreparedTest
from mbst.identify.replicate import logged_like
from mbst.io.campaign import TestSpec
from mbst.systems.eps.bench import input_profile

SINE_HZ = (0.1, 0.25, 0.5, 1.0, 2.0)
SMALL_STROKE = 0.25  # small-stroke sines: this share of the cut-out's amplitude...
SMALL_STROKE_HZ = (0.25, 0.5, 1.0)  # ...at these frequencies
TEST_SECONDS = 6.0  # each sine runs about this long (at least two cycles)
# The one sensor change offered: the driving angle logged by an encoder this many times
# finer than the campaign's angle sensor (a 16-bit absolute encoder resolves 0.0055°, rms
# 0.0016°, against a potentiometer's 0.05°). On a blocked column the angle noise through
# the torsion bar is the floor that hides a column Stribeck rise or asymmetry.
FINE_INPUT_FACTOR = 0.1


@dataclass(frozen=True)
class Candidate:
    """One possible next test: its campaign entry and the template test it copies."""

    id: str
    scenario: str
    motor: str
    input: dict
    duration_s: float
    channels: tuple[str, ...]
    # the driving input's sensor noise against the campaign's (FINE_INPUT_FACTOR: encoder)
    input_noise_factor: float = 1.0

    @property
    def sensor_change(self) -> str:
        return "" if self.input_noise_factor == 1.0 else \
            f"angle encoder, noise {self.input_noise_factor:g}× the campaign's angle sensor"


def _peak_rate_deg_s(inp: dict) -> float:
    a = float(inp.get("amplitude_deg", 0.0))
    if inp.get("kind") == "sine":
        return 2 * math.pi * float(inp["frequency_hz"]) * a
    if inp.get("kind") == "sweep":
        return 2 * math.pi * float(inp.get("f1_hz", 2.0)) * a
    if inp.get("kind") in ("ramp", "triangle"):
        return float(inp.get("rate_deg_per_s", 20.0))
    return 0.0


def _name(x: float) -> str:
    return f"{x:g}".replace(".", "p")


def _inputs(amplitude_deg: float, rate_deg_s: float) -> list[tuple[str, dict]]:
    """The candidate inputs of one cut-out, inside its amplitude and rate."""
    out = []
    for f in SINE_HZ:
        a = min(amplitude_deg, rate_deg_s / (2 * math.pi * f))
        out.append((f"sine_{_name(f)}hz", {"kind": "sine", "amplitude_deg": round(a, 3),
                                           "frequency_hz": f,
                                           "cycles": max(2, math.ceil(TEST_SECONDS * f))}))
    for f in SMALL_STROKE_HZ:
        a = min(SMALL_STROKE * amplitude_deg, rate_deg_s / (2 * math.pi * f))
        out.append((f"small_sine_{_name(f)}hz",
                    {"kind": "sine", "amplitude_deg": round(a, 3), "frequency_hz": f,
                     "cycles": max(2, math.ceil(TEST_SECONDS * f))}))
    return out


def candidate_tests(tests: list[PreparedTest], scenarios: set[str]) -> list[Candidate]:
    """Every candidate input on every cut-out in ``scenarios`` that the campaign tested."""
    out = []
    for sc in sorted(scenarios):
        mine = [pt for pt in tests if pt.scenario == sc]
        if not mine:
            continue
        amp = max(float(pt.spec.input.get("amplitude_deg", 0.0)) for pt in mine)
        rate = max(_peak_rate_deg_s(pt.spec.input) for pt in mine)
        if amp <= 0 or rate <= 0:
            continue
        rate_hz = 1.0 / mine[0].dt_s
        for label, inp in _inputs(amp, rate):
            t, _ = input_profile(inp, rate_hz)
            for factor in (1.0, FINE_INPUT_FACTOR):
                suffix = "" if factor == 1.0 else "_fine_angle"
                out.append(Candidate(f"{sc}_{label}{suffix}", sc, mine[0].spec.motor, inp,
                                     float(t[-1] - t[0]), tuple(mine[0].measured), factor))
    return out


def predicted_test(cand: Candidate, model: ModelDefinition, p: np.ndarray, input_channel: str,
                   noise: dict[str, float], dt_s: float, tau_s: float,
                   rng: np.random.Generator) -> PreparedTest:
    """The candidate as it would be logged (``identify.replicate.logged_like``).

    The model sees the angle only through its sensor: on a blocked column the angle
    noise through the torsion bar is a floor several times the torque sensor's own, and
    a prediction that drove rig and model alike with one signal would not see it.
    """
    t, ang = input_profile(cand.input, 1.0 / dt_s)
    spec = TestSpec(id=cand.id, file=f"tests/{cand.id}.csv", scenario=cand.scenario,
                    input=dict(cand.input), motor=cand.motor, role="identification")
    noise = {**noise, input_channel: noise.get(input_channel, 0.0) * cand.input_noise_factor}
    return logged_like(model, spec, t, ang, p, cand.channels, input_channel, noise, tau_s, rng)
