"""Speed of the fixed-step EPS simulator, and its agreement with scipy's LSODA.

Run from the repository root::

    python benchmarks/simulate.py

Times ``eps.simulate`` on a 20 s test sampled at 1 kHz (the bench's demo rig,
worm-gear backlash off, a 0.8 Hz 30° sine in ``free_tie_rods``) as the median
of repeated runs after a warm-up call, so numba compilation is excluded; times
``solve_ivp(method="LSODA")`` on the same right-hand side; checks that both
agree (FIT ≥ 99 % on steering torque and rack position). Prints a per-scenario
table and, as its last line, ``simulate: <ms> ms per run, <ratio>x solve_ivp``.
Exits with status 1 if the two solvers disagree.
"""

from __future__ import annotations

import os
import statistics
import sys
import time

import numpy as np
from scipy.integrate import solve_ivp

from mbst.systems.eps import simulate as eps
from mbst.systems.eps.bench import BenchRecipe, input_profile

SAMPLE_RATE_HZ = 1000.0
FREQUENCY_HZ = 0.8
DURATION_S = 20.0
LEAD_S = 0.5  # input_profile rests this long at each end
N_RUNS = 25
N_IVP_RUNS = 2
FIT_MIN = 99.0
# per-scenario amplitude (deg) of the seed-000 plan: the blocked column only twists the
# torsion bar, the tires only slide beyond ~90°; the headline case is free_tie_rods at 30°
AMPLITUDE_DEG = {
    "blocked_column": 5.0,
    "free_tie_rods": 30.0,
    "blocked_rack": 30.0,
    "suspended": 60.0,
    "tires_on_ground": 100.0,
}
HEADLINE = "free_tie_rods"
CHECKED = ("steering_torque_nm", "rack_position_m")


def fit_percent(y: np.ndarray, y_hat: np.ndarray) -> float:
    """FIT % = 100·(1 − ‖y − ŷ‖ / ‖y − mean y‖)."""
    return 100.0 * (1.0 - np.linalg.norm(y - y_hat) / np.linalg.norm(y - np.mean(y)))


def test_input(amplitude_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """A tapered sine whose whole test (rest, motion, rest) lasts DURATION_S."""
    cycles = FREQUENCY_HZ * (DURATION_S - 2 * LEAD_S)
    spec = {"kind": "sine", "amplitude_deg": amplitude_deg, "frequency_hz": FREQUENCY_HZ,
            "cycles": cycles}
    return input_profile(spec, SAMPLE_RATE_HZ)


def time_simulate(scenario: str, t: np.ndarray, angle: np.ndarray, p: np.ndarray) -> float:
    """Median wall time (s) of ``eps.simulate`` over N_RUNS, after one warm-up call."""
    eps.simulate(scenario, "passive", t, angle, p)  # compiles (or loads the numba cache)
    times = []
    for _ in range(N_RUNS):
        t0 = time.perf_counter()
        eps.simulate(scenario, "passive", t, angle, p)
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def main() -> int:
    p = BenchRecipe(effects=[]).true_params()  # the demo rig, no hidden effect
    dt = 1.0 / SAMPLE_RATE_HZ

    print(f"eps.simulate: {DURATION_S:.0f} s test at {SAMPLE_RATE_HZ:.0f} Hz, "
          f"{FREQUENCY_HZ} Hz sine, median of {N_RUNS} runs, {os.cpu_count()} CPUs")
    print(f"{'scenario':<18}{'amplitude':>10}{'ms/run':>10}{'sub-steps/sample':>18}")
    ms = {}
    for scenario, amp in AMPLITUDE_DEG.items():
        t, angle = test_input(amp)
        ms[scenario] = 1e3 * time_simulate(scenario, t, angle, p)
        print(f"{scenario:<18}{amp:>9.0f}°{ms[scenario]:>10.1f}"
              f"{eps.substeps(p, scenario, dt):>18d}")

    # reference: LSODA on the same equations, a Python callback per evaluation
    t, angle = test_input(AMPLITUDE_DEG[HEADLINE])
    fast = eps.simulate(HEADLINE, "passive", t, angle, p)
    f, x0 = eps.rhs_for(HEADLINE, "passive", t, angle, p)
    ivp_times = []
    for _ in range(N_IVP_RUNS):
        t0 = time.perf_counter()
        sol = solve_ivp(f, (t[0], t[-1]), x0, method="LSODA", t_eval=t,
                        rtol=1e-6, atol=1e-9, max_step=1e-3)
        ivp_times.append(time.perf_counter() - t0)
    ivp_ms = 1e3 * min(ivp_times)
    ok = bool(sol.success)
    fits = {}
    if ok:
        ref = eps.outputs_along(HEADLINE, "passive", t, angle, sol.y.T, p)
        fits = {ch: fit_percent(ref[ch], fast[ch]) for ch in CHECKED}
        ok = all(v >= FIT_MIN for v in fits.values())
    fit_text = ", ".join(f"{ch} {v:.3f} %" for ch, v in fits.items()) or sol.message
    print(f"solve_ivp LSODA ({HEADLINE}, rtol 1e-6, atol 1e-9, max_step 1e-3): "
          f"{ivp_ms:.0f} ms (best of {N_IVP_RUNS}), {sol.nfev} evaluations")
    print(f"agreement (FIT vs LSODA, need >= {FIT_MIN:.0f} %): {fit_text}")
    if not ok:
        print("FAIL: eps.simulate and solve_ivp disagree", file=sys.stderr)
    ratio = ivp_ms / ms[HEADLINE]
    print(f"simulate: {ms[HEADLINE]:.1f} ms per run, {round(ratio):d}x solve_ivp")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
