"""Physics + neural residual, open loop: the hybrid row of the EMPS benchmark.

The physics model (its open-loop parameters) is simulated from the measured
force; a latent neural ODE (``discovery.evidence.neural.NeuralResidual``,
torchdiffeq) learns the position that the simulation misses, driven by the
measured force and the simulation's own signals (velocity, friction, applied
force). It is trained on the identification runs only and then run open loop
over the whole test run from rest (z = 0), the physics beside it — the test
run is never read before the score.
"""

from __future__ import annotations

import numpy as np

from mbst.core.metrics import fit_percent
from mbst.discovery.data import TestResidual
from mbst.discovery.evidence.neural import NeuralResidual
from mbst.systems.prismatic import model as P

# features: the measured force (the open-loop input) and the simulation's own signals
SIGNALS = ("angle_rad", "omega_rad_per_s", *P.INTERNAL, "position_m")
SCENARIO = "open_loop"


def open_loop_residual(pt, p: np.ndarray) -> TestResidual:
    """A run replayed open loop from its measured force, paired with its measured position."""
    sim = P.simulate(pt, p, SCENARIO)[0]
    force = np.asarray(pt.raw["motor_force_n"], float)
    states = {k.split(".", 1)[1]: v for k, v in sim.items() if k.startswith("internal.")}
    states["position_m"] = sim["position_m"]
    return TestResidual(
        id=pt.id, scenario=SCENARIO, role=pt.spec.role, motor=pt.spec.motor, dt_s=pt.dt_s,
        time_s=pt.time_s, angle_rad=force, omega_rad_per_s=np.gradient(force, pt.dt_s),
        measured={"position_m": np.asarray(pt.raw["position_m"], float)},
        simulated={"position_m": sim["position_m"]}, states=states,
    )


def hybrid_record(idents: list, test, p_open_loop: np.ndarray, seed: int = 0) -> dict:
    """Open-loop FIT % of physics and of physics + neural residual on ``test``."""
    train = [open_loop_residual(pt, p_open_loop) for pt in idents]
    if any(t.role != "identification" for t in train):
        raise ValueError("the hybrid trains on identification runs only")
    net = NeuralResidual(seed=seed, signals=SIGNALS).fit(train)
    held = open_loop_residual(test, p_open_loop)
    y = held.measured["position_m"]
    return {
        "model": "physics (open-loop parameters) + latent neural ODE on the position "
                 "(torchdiffeq), trained on the identification runs only",
        "trained_on": net.trained_on,
        "open_loop_fit_percent_test": round(fit_percent(y, net.predict(held)["position_m"]), 6),
        "physics_open_loop_fit_percent_test": round(fit_percent(y, held.simulated["position_m"]),
                                                    6),
        "open_loop_fit_percent_identification": {
            t.id: round(fit_percent(t.measured["position_m"], net.predict(t)["position_m"]), 6)
            for t in train},
        "correction_gain": net.gains,
        "train_seconds": round(net.train_seconds, 1),
    }
