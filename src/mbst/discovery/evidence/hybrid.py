"""Physics + neural residual for a family's benchmark: the learner discovery hands over.

A family's benchmark (``ModelDefinition.benchmark``) lives below discovery and
cannot import the neural residual; discovery passes it ``neural_correction``.
A run is a plain dict — ``id``, ``role``, ``time_s``, ``input`` (the signal that
drives the physics), ``measured`` and ``simulated`` (channel → array, the physics
replayed as the benchmark scores it) and ``states`` (the simulation's own
signals). The learner trains on the runs with role ``identification`` only and
predicts every run from rest.
"""

from __future__ import annotations

import numpy as np

from mbst.discovery.data import TestResidual
from mbst.discovery.evidence.neural import NeuralResidual


def _residual(run: dict) -> TestResidual:
    u = np.asarray(run["input"], float)
    t = np.asarray(run["time_s"], float)
    return TestResidual(
        id=run["id"], scenario=run.get("scenario", "replay"), role=run["role"],
        motor=run.get("motor", ""), dt_s=float(np.median(np.diff(t))), time_s=t,
        angle_rad=u, omega_rad_per_s=np.gradient(u, t),
        measured=dict(run["measured"]), simulated=dict(run["simulated"]),
        states=dict(run.get("states", {})))


def neural_correction(runs: list[dict], seed: int = 0) -> dict:
    """Train on the identification runs; ``predicted[id][channel]`` = physics + correction."""
    tests = [_residual(r) for r in runs]
    signals = ("angle_rad", "omega_rad_per_s",
               *sorted({k for r in runs for k in r.get("states", {})}))
    net = NeuralResidual(seed=seed, signals=signals).fit(tests)
    return {"predicted": {t.id: net.predict(t) for t in tests}, "gains": dict(net.gains),
            "trained_on": list(net.trained_on), "train_seconds": float(net.train_seconds)}
