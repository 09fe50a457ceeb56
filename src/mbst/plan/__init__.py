"""Simulation for testing (seed 000): plan a campaign before it is run.

The planner uses the one EPS model to decide which cut-outs to test, which
inputs to apply and which sensors to install so that every unknown parameter
can be identified at the lowest cost.

Modules, one idea each:

- ``config``: the planning config (``PLAN.yaml``) and its validation;
- ``sensors``: the candidate sensors, derived from the simulator's outputs;
- ``inputs``: candidate excitation profiles (sines, sweep, ramp, impact);
- ``sensitivity``: batched simulations over the parameter sweep, sensitivities
  and their Gram matrices;
- ``information``: Fisher information of a chosen set (conditioning,
  correlations, predicted standard errors);
- ``selection``: greedy selection per unit cost, pruning, control tests, the
  naive campaign of equal cost;
- ``effects``: which sensors and inputs separate catalogue effects that look
  alike;
- ``proof``: planned vs naive campaign on the virtual bench;
- ``figures`` and ``report``: what ``mbst plan`` writes.
"""

from mbst.plan.config import PlanConfig, PlanError, load_plan

__all__ = ["PlanConfig", "PlanError", "load_plan"]
