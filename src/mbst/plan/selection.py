"""Greedy choice of sensors, cut-outs and inputs per unit cost.

A plan is a set of installed sensors plus identification tests (cells,
with a count). Its cost is the sensors' cost, each used scenario's set-up
cost once, and each test's input cost.

Greedy step: among every feasible move (add a test, add a sensor, or add a
sensor together with a test — a sensor without a test and a test without a
sensor are worth nothing alone), take the one with the largest information
gain per unit cost. The gain is the drop of Σ_p log max(σ_p, target),
averaged over the sweep points: the D-optimal log-determinant restricted to
the parameters that are not yet at their target, so the budget goes where
identifiability is still missing. It stops when every unknown reaches the
target at every sweep point (or nothing affordable helps), then prunes:
each test and sensor, most expensive first, is dropped if the target still
holds without it. The result is minimal in the sense that no single
element can be removed.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from mbst.core.family import get_system
from mbst.plan.config import PlanConfig
from mbst.plan.information import (
    RIDGE,
    bits_gained,
    fisher,
    input_error_per_test,
    input_error_term,
    logged_mask,
    offset_eliminated,
    prior_information,
    relative_std,
)
from mbst.plan.sensitivity import Sensitivity
from mbst.plan.sensors import SENSORS
from mbst.systems.eps.channels import SYSTEM_NAME


@dataclass
class Plan:
    """A campaign plan: installed sensors, identification tests and controls."""

    sensors: list[str]
    tests: dict[int, int]  # cell index → repetitions
    controls: list[int] = field(default_factory=list)
    required: list[str] = field(default_factory=list)  # added for the campaign format
    added_for_cascade: list[str] = field(default_factory=list)  # slow loops for the cascade

    @property
    def logged(self) -> list[str]:
        return list(dict.fromkeys(self.sensors + self.required))

    def counts(self, n_cells: int) -> np.ndarray:
        c = np.zeros(n_cells)
        for k, v in self.tests.items():
            c[k] = v
        return c


@dataclass
class Step:
    """One greedy move, for the information-vs-cost figure and table."""

    move: str
    cost: float
    bits: float
    worst_relative_std: float
    n_identifiable: int


def scenario_ids(sens: Sensitivity, cells: list[int] | dict[int, int]) -> list[str]:
    out = []
    for c in cells:
        sid = sens.cells[c].scenario_id
        if sid not in out:
            out.append(sid)
    return out


def plan_cost(cfg: PlanConfig, sens: Sensitivity, sensors: list[str],
              tests: dict[int, int], controls: list[int] = ()) -> dict[str, float]:
    """Cost breakdown: sensors, scenario set-ups, identification and control tests."""
    sc = sum(cfg.sensor(s).cost for s in dict.fromkeys(sensors))
    used = scenario_ids(sens, list(tests) + list(controls))
    setup = sum(cfg.scenario(s).cost for s in used)
    tcost = sum(n * cfg.input(sens.cells[c].input_id).cost for c, n in tests.items())
    ccost = sum(cfg.input(sens.cells[c].input_id).cost for c in controls)
    return {"sensors": sc, "scenarios": setup, "tests": tcost, "controls": ccost,
            "identification": sc + setup + tcost, "total": sc + setup + tcost + ccost}


def required_channels(sens: Sensitivity, cells) -> list[str]:
    """Channels campaign-format.md requires in the scenarios of ``cells``."""
    fam = get_system(SYSTEM_NAME)
    out: list[str] = []
    for c in cells:
        for ch in fam.required_channels(sens.cells[c].scenario):
            if ch != fam.time_channel and ch not in out:
                out.append(ch)
    return out


def _objective(rel: np.ndarray, target: float) -> np.ndarray:
    """Σ_p log max(σ_p, target), mean over sweep points; rel is (..., K, P)."""
    return np.log(np.maximum(rel, target)).sum(axis=-1).mean(axis=-1)


def greedy(cfg: PlanConfig, sens: Sensitivity, rate_factor: float
           ) -> tuple[Plan, list[Step], list[str]]:
    """Greedy forward selection then pruning; returns the plan, the path and notes."""
    cc, ss = len(sens.cells), len(sens.sensors)
    target = cfg.target_relative_std
    prior = prior_information(cfg)
    mandatory = np.array([cfg.sensor(s).mandatory for s in sens.sensors])
    s_cost = np.array([cfg.sensor(s).cost for s in sens.sensors])
    # mbst identify fits the campaign-format channels only: a plan that paid for another
    # sensor would count information no identification uses (they are still ranked)
    fitted = np.array([SENSORS[s].campaign_channel for s in sens.sensors])
    logged = logged_mask(sens)  # (C, S)
    gram = sens.gram * rate_factor
    colsum = sens.colsum * rate_factor
    nsamp = sens.n_samples[:, None] * logged * rate_factor  # (C, S)

    chosen = mandatory.copy()
    counts = np.zeros(cc, int)
    a = np.zeros_like(gram[:, 0])  # (K, S, P, P)
    b = np.zeros_like(colsum[:, 0])
    n = np.zeros(ss)
    steps: list[Step] = []
    notes: list[str] = []

    def cost_of(ch: np.ndarray, cnt: np.ndarray) -> float:
        tests = {c: int(v) for c, v in enumerate(cnt) if v}
        return plan_cost(cfg, sens, [s for s, on in zip(sens.sensors, ch, strict=True) if on],
                         tests)["identification"]

    def info(eff_sel: np.ndarray) -> np.ndarray:
        return eff_sel.sum(axis=-3)  # sum over sensors (..., S, P, P) → (..., P, P)

    def per_test_error(ch: np.ndarray):
        q = input_error_per_test(sens, ch)
        return None if q is None else rate_factor**2 * q  # (K, C, P, P)

    def total_error(q, cnt: np.ndarray):
        return None if q is None else np.einsum("c,kcpq->kpq", cnt.astype(float), q)

    def state_eval(ch, aa, bb, nn, cnt):
        eff = offset_eliminated(aa, bb, nn) * ch[:, None, None]
        f = info(eff)
        q = per_test_error(ch)
        return f, relative_std(f, total_error(q, cnt)), q

    f_cur, rel_cur, q_cur = state_eval(chosen, a, b, n, counts)
    cost_cur = cost_of(chosen, counts)
    steps.append(Step("start: " + ", ".join(s for s, m in zip(sens.sensors, mandatory,
                                                                strict=True) if m),
                      cost_cur, float(np.mean(bits_gained(f_cur, prior))),
                      float(rel_cur.max()), int((rel_cur.max(axis=0) <= target).sum())))
    per_scen = {sc.id: cfg.max_tests_per_scenario for sc in cfg.scenarios}
    while rel_cur.max() > target:
        j_cur = _objective(rel_cur, target)
        # per-sensor information after adding each candidate test: (C, K, S, P, P)
        a_new = a[None] + np.transpose(gram, (1, 0, 2, 3, 4))
        b_new = b[None] + np.transpose(colsum, (1, 0, 2, 3))
        n_new = n[None] + nsamp
        eff_new = offset_eliminated(a_new, b_new, n_new[:, None, :])
        eff_cur = offset_eliminated(a, b, n)
        moves, fs, dcost, bs = [], [], [], []
        b_cur = total_error(q_cur, counts)
        q_with = {s: per_test_error(chosen | (np.arange(ss) == s))
                  for s in np.flatnonzero(~chosen & fitted)}
        for c in range(cc):
            sid = sens.cells[c].scenario_id
            # a repeat is a candidate too: a fresh draw of the angle noise averages the
            # input error that one test cannot (information and that error both add up)
            if sum(counts[k] for k in range(cc)
                   if sens.cells[k].scenario_id == sid) >= per_scen[sid]:
                continue
            cnt = counts.copy()
            cnt[c] += 1
            base_cost = cost_of(chosen, cnt)
            f_t = info(eff_new[c] * chosen[None, :, None, None])
            moves.append(("test", c, None))
            fs.append(f_t)
            dcost.append(base_cost - cost_cur)
            bs.append(None if q_cur is None else b_cur + q_cur[:, c])
            for s in np.flatnonzero(~chosen & fitted):
                if not logged[c, s]:
                    continue
                moves.append(("pair", c, s))
                fs.append(f_t + eff_new[c][:, s])
                dcost.append(base_cost + s_cost[s] - cost_cur)
                bs.append(total_error(q_with[s], cnt))
        for s in np.flatnonzero(~chosen & fitted):
            moves.append(("sensor", None, s))
            fs.append(f_cur + eff_cur[:, s])
            dcost.append(s_cost[s])
            bs.append(total_error(q_with[s], counts))
        if not moves:
            break
        dcost = np.array(dcost)
        feasible = cost_cur + dcost <= cfg.budget + 1e-9
        if not feasible.any():
            notes.append(f"budget {cfg.budget:g} reached at cost {cost_cur:g}")
            break
        rel_all = relative_std(np.stack(fs), None if q_cur is None else np.stack(bs))
        gain = j_cur - _objective(rel_all, target)
        score = np.where(feasible, gain / np.maximum(dcost, 1e-6), -np.inf)
        best = int(np.argmax(score))
        if not gain[best] > 1e-9:
            notes.append("no affordable test or sensor adds information on the parameters "
                         "still above the target")
            break
        kind, c, s = moves[best]
        label = []
        if s is not None:
            chosen[s] = True
            label.append(f"+sensor {sens.sensors[s]}")
        if c is not None:
            counts[c] += 1
            a, b, n = a + gram[:, c], b + colsum[:, c], n + nsamp[c]
            label.append(f"+test {sens.cells[c].label}")
        f_cur, rel_cur, q_cur = state_eval(chosen, a, b, n, counts)
        cost_cur = cost_of(chosen, counts)
        steps.append(Step(" ".join(label), cost_cur, float(np.mean(bits_gained(f_cur, prior))),
                          float(rel_cur.max()), int((rel_cur.max(axis=0) <= target).sum())))

    if rel_cur.max() <= target:
        chosen, counts = _prune(cfg, sens, chosen, counts, mandatory, rate_factor, steps, prior)
    sensors = [s for s, on in zip(sens.sensors, chosen, strict=True) if on]
    tests = {c: int(v) for c, v in enumerate(counts) if v}
    return Plan(sensors, tests), steps, notes


def _prune(cfg, sens, chosen, counts, mandatory, rate_factor, steps, prior):
    """Drop any test or sensor (most expensive first) whose removal keeps the target."""
    target = cfg.target_relative_std

    def ok(ch, cnt) -> bool:
        f = fisher(sens, ch, cnt, rate_factor)
        return bool(relative_std(f, input_error_term(sens, ch, cnt, rate_factor)).max()
                    <= target)

    items = [("test", c, cfg.input(sens.cells[c].input_id).cost) for c in np.flatnonzero(counts)]
    items += [("sensor", s, cfg.sensor(sens.sensors[s]).cost)
              for s in np.flatnonzero(chosen & ~mandatory)]
    for kind, i, _ in sorted(items, key=lambda it: (-it[2], it[0], it[1])):
        ch, cnt = chosen.copy(), counts.copy()
        if kind == "test":
            cnt[i] = 0
        else:
            ch[i] = False
        if ok(ch, cnt):
            chosen, counts = ch, cnt
            name = sens.cells[i].label if kind == "test" else sens.sensors[i]
            f = fisher(sens, chosen, counts, rate_factor)
            rel = relative_std(f, input_error_term(sens, chosen, counts, rate_factor))
            cost = plan_cost(cfg, sens, [s for s, on in zip(sens.sensors, chosen, strict=True)
                                         if on],
                             {c: int(v) for c, v in enumerate(counts) if v})["identification"]
            steps.append(Step(f"-{kind} {name} (pruned)", cost,
                              float(np.mean(bits_gained(f, prior))), float(rel.max()),
                              int((rel.max(axis=0) <= target).sum())))
    return chosen, counts


def complete_for_cascade(cfg: PlanConfig, sens: Sensitivity, plan: Plan) -> Plan:
    """Give every chosen scenario a slow loop (sine or ramp) if the greedy chose none.

    The identification cascade starts from signal processing on the slowest
    test of a scenario (friction from the angle–torque loop, rack/angle slope);
    an impact or a sweep gives it no loop and a wrong start and bounds. The
    slowest sine (else a ramp) is added, its cost counted.
    """
    loops = sorted((i for i in cfg.inputs if i.kind in ("sine", "ramp")),
                   key=lambda i: (i.kind != "sine", i.options.get("frequency_hz", 0.0),
                                  cfg.inputs.index(i)))
    if not loops:
        return plan
    for sid in scenario_ids(sens, plan.tests):
        kinds = {cfg.input(sens.cells[c].input_id).kind for c in plan.tests
                 if sens.cells[c].scenario_id == sid}
        if not kinds & {"sine", "ramp"}:
            plan.tests[sens.cell_index(sid, loops[0].id)] = 1
            plan.added_for_cascade.append(f"{sid}/{loops[0].id}")
    return plan


def add_controls(cfg: PlanConfig, sens: Sensitivity, plan: Plan) -> Plan:
    """One held-out control test per chosen scenario, with an input not fitted there.

    Preference: a sine the scenario was not identified with (seed 000 held out a
    sine), else any unused input, else a repeat of the first one.
    """
    if not cfg.controls:
        return plan
    controls = []
    for sid in scenario_ids(sens, plan.tests):
        used = {sens.cells[c].input_id for c in plan.tests if sens.cells[c].scenario_id == sid}
        order = sorted(cfg.inputs, key=lambda i: (i.kind != "sine", cfg.inputs.index(i)))
        pick = next((i for i in order if i.id not in used), order[0])
        controls.append(sens.cell_index(sid, pick.id))
    plan.controls = controls
    return plan


def complete_for_format(sens: Sensitivity, plan: Plan) -> Plan:
    """Add the channels the campaign format requires in the chosen scenarios."""
    req = required_channels(sens, list(plan.tests) + plan.controls)
    plan.required = [ch for ch in req if ch not in plan.sensors]
    return plan


def naive_plan(cfg: PlanConfig, sens: Sensitivity, total_cost: float) -> Plan:
    """One scenario, one slow input repeated, the cheapest sensors: equal total cost.

    The repetitions fill the budget the planned campaign spent (at least one).
    """
    mand = [s.name for s in cfg.sensors if s.mandatory]
    rest = sorted((s for s in cfg.sensors if not s.mandatory),
                  key=lambda s: (s.cost, cfg.sensors.index(s)))
    sensors = mand + [s.name for s in rest[: cfg.naive_sensors]]
    c = sens.cell_index(cfg.naive_scenario, cfg.naive_input)
    others = [i for i in cfg.inputs if i.id != cfg.naive_input]
    others.sort(key=lambda i: (i.kind != "sine", cfg.inputs.index(i)))
    controls = [sens.cell_index(cfg.naive_scenario, others[0].id)] if (
        cfg.controls and others) else []
    plan = complete_for_format(sens, Plan(sensors, {c: 1}, controls))
    reps = 1
    while plan_cost(cfg, sens, plan.logged, {c: reps + 1}, controls)["total"] <= total_cost + 1e-9:
        reps += 1
    plan.tests = {c: reps}
    return plan


def evaluate(cfg: PlanConfig, sens: Sensitivity, plan: Plan, rate_factor: float,
             logged: bool = True):
    """Identifiability of a plan (with the format-required channels when ``logged``)."""
    from mbst.plan.information import identifiability

    sensors = plan.logged if logged else plan.sensors
    counts = plan.counts(len(sens.cells))
    f = fisher(sens, sensors, counts, rate_factor)
    return f, identifiability(f, cfg.target_relative_std, prior_information(cfg),
                              input_error_term(sens, sensors, counts, rate_factor))


__all__ = ["Plan", "Step", "add_controls", "complete_for_format", "evaluate", "greedy",
           "naive_plan", "plan_cost", "complete_for_cascade", "required_channels", "RIDGE"]
