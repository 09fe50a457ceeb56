"""The simulation work of a fit, counted in integration steps, and its budget.

A fit's evaluation budget (``max_nfev``) bounds its evaluations, not its time: where a
family's step shrinks with the parameters (the EPS kernel's Stribeck limit: a rack dip of
static/Coulomb 4 at 0.05 mm/s needs 0.08 µs steps, 300× the base model's), one refit that
wanders there runs for hours (realistic rig 932: a round's cross-seeded Stribeck refits,
started from a fitted dip, were still running after 50 min). The
meter counts each simulation's steps (samples × sub-steps × rows: deterministic, unlike
seconds) and a fit stops at its best point once it has spent ``WORK_BUDGET_FACTOR`` ×
what its evaluation budget costs at the problem's base (for a candidate's refit: the
base model, the effect off). Discovery counts its rounds' fits at the base model's step, the
extension's cascade and the later rounds' fits included: once an effect far finer in
step than the base is in the model (realistic rig 2704's tyre Stribeck dip, 89 sub-steps
a sample against 4), the extension's cascade counted at its own start ran 24 min; at
the base's step, 15 min, with the same answer.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# A fit may spend this many times the work its evaluation budget costs at its base's
# step: a refit whose step stays within this factor of the base's never meets the bound
# (the rack Stribeck of realistic rig 932, at its true size, needs 4× the base's).
WORK_BUDGET_FACTOR = 8.0


class WorkSpent(Exception):
    """Raised inside an evaluation once the fit's work budget is spent."""


def simulation_steps(pt, ps: np.ndarray) -> float:
    """Integration steps of simulating the rows ``ps`` on one prepared test: samples ×
    the finest step any row needs (a batch runs at it) × rows; samples × rows where the
    family has no step rule."""
    ps = np.atleast_2d(ps)
    steps = pt.model.row_steps
    per_row = float(np.max(steps(pt, ps))) if steps is not None else 1.0
    return float(len(pt.time_s)) * per_row * len(ps)


@dataclass
class WorkMeter:
    """Steps spent by one fit run against its limit, and the best point it evaluated."""

    limit: float = float("inf")
    spent: float = 0.0
    best_u: np.ndarray | None = None
    best_cost: float = float("inf")
    best_r: np.ndarray | None = None

    def start(self, limit: float) -> None:
        self.limit, self.spent = limit, 0.0
        self.best_u, self.best_cost, self.best_r = None, float("inf"), None

    def charge(self, steps: float) -> None:
        """Count ``steps`` about to be simulated; raise once the budget is spent (never
        before a first point is evaluated: the fit always has an answer)."""
        if self.best_u is not None and self.spent + steps > self.limit:
            raise WorkSpent
        self.spent += steps

    def seen(self, u: np.ndarray, r: np.ndarray) -> None:
        cost = 0.5 * float(r @ r)
        if cost < self.best_cost:
            self.best_u, self.best_cost, self.best_r = np.array(u, float), cost, r
