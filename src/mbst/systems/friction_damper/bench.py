"""Virtual test bench of the friction damper: campaigns with a known truth.

Sine characterization tests (frequencies × amplitudes, as the published data
set) identify; a multi-sine "earthquake" with strokes of several sizes is the
held-out control. The band is simulated on a displacement four times finer than
the campaign's and read at the sample instants, and the measured displacement
carries its own noise, so the model that identification fits is not handed
the bench's exact input. (Averaging the fine force over each sample instead
would smear the band's transitions, 0.6 mm of stroke per sample at 2 Hz and
256 Hz against a 2 mm elastic range, into kilonewtons of difference: a filter
no load cell has.)
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd

from mbst.io.campaign import TestSpec, write_campaign
from mbst.systems.friction_damper import model as M
from mbst.systems.friction_damper.channels import SYSTEM_NAME
from mbst.systems.friction_damper.definition import FRICTION_DAMPER_MODEL

# a band brake of the published data set's size (about 15 kN slip level)
TRUE_BASE = {"band.stiffness_n_per_m": 8e6, "band.coulomb_n": 15000.0,
             "band.viscous_ns_per_m": 2000.0}
SINES = ((0.5, 0.0127), (0.5, 0.0254), (1.0, 0.0127), (2.0, 0.0127))
OVERSAMPLE = 4


def _sine(f_hz: float, amp_m: float, rate_hz: float, cycles: float = 3.0) -> np.ndarray:
    t = np.arange(0.0, cycles / f_hz, 1.0 / rate_hz)
    ramp = np.clip(t * f_hz, 0.0, 1.0)  # one cycle of amplitude ramp, as a rig starts
    return amp_m * ramp * np.sin(2 * np.pi * f_hz * t)


def _earthquake(rate_hz: float, rng: np.random.Generator, duration_s: float = 8.0
                ) -> np.ndarray:
    t = np.arange(0.0, duration_s, 1.0 / rate_hz)
    x = np.zeros_like(t)
    for f in (0.3, 0.7, 1.3, 2.1, 3.4):
        x += rng.uniform(0.002, 0.006) * np.sin(2 * np.pi * f * t + rng.uniform(0, 2 * np.pi))
    return x * np.sin(np.pi * t / duration_s) ** 2  # a record's build-up and decay


def _force(x: np.ndarray, p: np.ndarray, rate_hz: float) -> np.ndarray:
    """The band's force on a displacement refined ``OVERSAMPLE`` times (the rig moves
    between samples: a reversal need not fall on one), read at the sample instants."""
    n = len(x)
    fine = np.interp(np.arange((n - 1) * OVERSAMPLE + 1) / OVERSAMPLE, np.arange(n), x)
    dt = 1.0 / (rate_hz * OVERSAMPLE)
    f = M.simulate_kernel(fine, np.gradient(fine, dt), p[None], 0.0, dt)[0][:, 0]
    return f[::OVERSAMPLE]


def run_friction_damper_bench(out: str | Path, effects: dict[str, float] | None = None,
                              seed: int = 0, rate_hz: float = 256.0,
                              force_noise_n: float = 150.0,
                              displacement_noise_m: float = 5e-6,
                              name: str = "bench-damper") -> Path:
    """Write ``out/campaign`` and ``out/truth.json``.

    ``effects`` sets catalogue parameters (e.g. ``{"band.backlash.width_m": 2e-3}``)
    on top of the base truth.
    """
    out = Path(out)
    p = FRICTION_DAMPER_MODEL.vector_from({**TRUE_BASE, **(effects or {})})
    rng = np.random.default_rng(seed)
    runs = [(f"sine_{f:g}hz_{a * 1e3:g}mm".replace(".", "p"), _sine(f, a, rate_hz),
             {"kind": "sine", "frequency_hz": f, "amplitude_m": a}, "identification")
            for f, a in SINES]
    runs.append(("earthquake_ctrl", _earthquake(rate_hz, rng), {"kind": "recorded"},
                 "control"))
    tests = []
    for test_id, x, profile, role in runs:
        force = _force(x, p, rate_hz) + force_noise_n * rng.standard_normal(len(x))
        frame = pd.DataFrame({
            "time_s": np.arange(len(x)) / rate_hz,
            "displacement_m": x + displacement_noise_m * rng.standard_normal(len(x)),
            "friction_force_n": force})
        spec = TestSpec(id=test_id, file="", scenario="imposed_displacement", input=profile,
                        motor="actuator", role=role)
        tests.append((spec, frame))
    camp = write_campaign(out / "campaign", name=name, system=SYSTEM_NAME, known={},
                          tests=tests, overwrite=True)
    (out / "truth.json").write_text(json.dumps(
        {"system": SYSTEM_NAME, "seed": seed, "effects": effects or {},
         "params": FRICTION_DAMPER_MODEL.as_dict(p)}, indent=2))
    return camp
