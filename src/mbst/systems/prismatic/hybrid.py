"""Physics + neural residual, open loop: the hybrid row of the EMPS benchmark.

The physics model (its open-loop parameters) is replayed from the measured
force; a learner handed over by discovery (a latent neural ODE, torchdiffeq)
learns the position the replay misses, driven by the measured force and the
replay's own signals (velocity, friction, applied force, position). It trains
on the identification runs only and then runs over the whole test run from
rest, the physics beside it: the test run is never read before the score.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from mbst.core.metrics import fit_percent
from mbst.systems.prismatic import model as P

SCENARIO = "open_loop"


def open_loop_run(pt, p: np.ndarray) -> dict:
    """A run replayed open loop from its measured force, beside its measured position."""
    sim = P.simulate(pt, p, SCENARIO)[0]
    states = {k.split(".", 1)[1]: v for k, v in sim.items() if k.startswith("internal.")}
    states["position_m"] = sim["position_m"]
    return {"id": pt.id, "role": pt.spec.role, "scenario": SCENARIO, "motor": pt.spec.motor,
            "time_s": pt.time_s, "input": np.asarray(pt.raw["motor_force_n"], float),
            "measured": {"position_m": np.asarray(pt.raw["position_m"], float)},
            "simulated": {"position_m": sim["position_m"]}, "states": states}


def hybrid_record(idents: list, test, p_open_loop: np.ndarray,
                  learner: Callable[[list[dict]], dict]) -> dict:
    """Open-loop FIT % of physics and of physics + learned residual on ``test``."""
    runs = [open_loop_run(pt, p_open_loop) for pt in [*idents, test]]
    out = learner(runs)
    if test.id in out["trained_on"]:
        raise ValueError("the hybrid's learner read the test run")
    fit = {r["id"]: round(fit_percent(r["measured"]["position_m"],
                                      out["predicted"][r["id"]]["position_m"]), 6) for r in runs}
    held = runs[-1]
    return {
        "model": "physics (open-loop parameters of the extended model) + latent neural ODE "
                 "on the position (torchdiffeq), trained on the identification runs only",
        "trained_on": out["trained_on"],
        "open_loop_fit_percent_test": fit[test.id],
        "physics_open_loop_fit_percent_test": round(
            fit_percent(held["measured"]["position_m"], held["simulated"]["position_m"]), 6),
        "open_loop_fit_percent_identification": {pt.id: fit[pt.id] for pt in idents},
        "correction_gain": out["gains"],
        "train_seconds": round(out["train_seconds"], 1),
    }
