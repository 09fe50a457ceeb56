"""Virtual test bench of the prismatic axis: EMPS-like campaigns with known truth.

The rig runs in closed loop on a bang-bang (trapezoidal-velocity) reference,
as in the EMPS identification run; the control test repeats the reference
with a square train of injected force pulses, as in its validation run.
The same compiled model that identification fits produces the data.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd

from mbst.io.campaign import TestSpec, write_campaign
from mbst.systems.prismatic import model as P
from mbst.systems.prismatic.channels import SYSTEM_NAME
from mbst.systems.prismatic.definition import PRISMATIC_MODEL

KNOWN = {"drive_gain_n_per_v": 35.15, "position_loop_gain_per_s": 160.18,
         "velocity_loop_gain_v_s_per_m": 243.45, "drive_command_limit_v": 10.0}
TRUE_BASE = {"carriage.mass_kg": 95.0, "ball_screw.viscous_ns_per_m": 200.0,
             "ball_screw.coulomb_n": 20.0, "drive.force_offset_n": -3.0}


def reference(duration_s: float, dt_s: float, stroke_m: float = 0.2,
              v_max_m_per_s: float = 0.12, a_max_m_per_s2: float = 1.5) -> np.ndarray:
    """Back-and-forth strokes with trapezoidal velocity and dwells at both ends."""
    t = np.arange(0.0, duration_s + 0.5 * dt_s, dt_s)
    t_acc = v_max_m_per_s / a_max_m_per_s2
    t_move = stroke_m / v_max_m_per_s + t_acc
    dwell = 0.3
    period = 2 * (t_move + dwell)

    def stroke(s):  # position along one move, s in [0, t_move]
        s = np.clip(s, 0.0, t_move)
        up = 0.5 * a_max_m_per_s2 * np.minimum(s, t_acc) ** 2
        cruise = v_max_m_per_s * np.clip(s - t_acc, 0.0, t_move - 2 * t_acc)
        tail = np.clip(s - (t_move - t_acc), 0.0, t_acc)
        down = v_max_m_per_s * tail - 0.5 * a_max_m_per_s2 * tail ** 2
        return up + cruise + down

    ph = np.mod(t, period)
    q = np.where(ph < t_move + dwell, stroke(ph), stroke_m - stroke(ph - t_move - dwell))
    return 0.01 + q


def _simulate(q_ref: np.ndarray, injected: np.ndarray, p: np.ndarray, dt_s: float
              ) -> tuple[np.ndarray, np.ndarray]:
    n = len(q_ref)
    raw = P.simulate_kernel(q_ref, np.zeros(n), injected, p[None], True, float(q_ref[0]), 0.0,
                            dt_s)[0]
    return raw[:, 0], raw[:, 1]


def run_prismatic_bench(out: str | Path, effects: dict[str, float] | None = None,
                        seed: int = 0, duration_s: float = 12.0, dt_s: float = 1e-3,
                        position_noise_m: float = 2e-7, force_noise_n: float = 0.5,
                        name: str = "bench-axis") -> Path:
    """Write ``out/campaign`` (identification run + pulse control) and ``out/truth.json``.

    ``effects`` sets catalogue parameters (e.g. ``{"ball_screw.asymmetric_friction.
    viscous_ratio": 1.45}``) on top of the base truth.
    """
    out = Path(out)
    p = PRISMATIC_MODEL.vector_from({**KNOWN, **TRUE_BASE, **(effects or {})})
    rng = np.random.default_rng(seed)
    q_ref = reference(duration_s, dt_s)
    n = len(q_ref)
    t = np.arange(n) * dt_s
    pulses = np.where(np.mod(t, 0.8) < 0.4, 0.0, 5.0 * KNOWN["drive_gain_n_per_v"])
    tests = []
    for test_id, inj, role in (("axis_identification", np.zeros(n), "identification"),
                               ("axis_pulses_ctrl", pulses, "control")):
        q, f = _simulate(q_ref, inj, p, dt_s)
        q = q + position_noise_m * rng.standard_normal(n)
        f = f + force_noise_n * rng.standard_normal(n)
        frame = pd.DataFrame({"time_s": t, "position_m": q, "motor_force_n": f,
                              "position_reference_m": q_ref, "injected_force_n": inj})
        spec = TestSpec(id=test_id, file=f"tests/{test_id}.csv", scenario="closed_loop",
                        input={"kind": "recorded"}, motor="drive", role=role)
        tests.append((spec, frame))
    camp = write_campaign(out / "campaign", name=name, system=SYSTEM_NAME, known=KNOWN,
                          tests=tests, overwrite=True)
    (out / "truth.json").write_text(json.dumps(
        {"system": SYSTEM_NAME, "seed": seed, "effects": effects or {},
         "params": PRISMATIC_MODEL.as_dict(p)}, indent=2))
    return camp
