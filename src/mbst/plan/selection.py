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
    search = _Search.start(cfg, sens, rate_factor)
    steps = [search.step("start: " + ", ".join(
        s for s, m in zip(sens.sensors, search.mandatory, strict=True) if m))]
    notes: list[str] = []
    while search.rel.max() > search.target:
        moves = search.moves()
        if not moves.kinds:
            break
        dcost = np.array(moves.dcost)
        feasible = search.cost + dcost <= cfg.budget + 1e-9
        if not feasible.any():
            notes.append(f"budget {cfg.budget:g} reached at cost {search.cost:g}")
            break
        rel_all = relative_std(np.stack(moves.info),
                               None if search.q is None else np.stack(moves.error))
        gain = _objective(search.rel, search.target) - _objective(rel_all, search.target)
        score = np.where(feasible, gain / np.maximum(dcost, 1e-6), -np.inf)
        best = int(np.argmax(score))
        if not gain[best] > 1e-9:
            notes.append("no affordable test or sensor adds information on the parameters "
                         "still above the target")
            break
        steps.append(search.step(search.apply(*moves.kinds[best])))
    chosen, counts = search.chosen, search.counts
    if search.rel.max() <= search.target:
        chosen, counts = _prune(cfg, sens, chosen, counts, search.mandatory, rate_factor,
                                steps, search.prior)
    sensors = [s for s, on in zip(sens.sensors, chosen, strict=True) if on]
    tests = {c: int(v) for c, v in enumerate(counts) if v}
    return Plan(sensors, tests), steps, notes


@dataclass
class _Moves:
    """Every move the greedy step weighs: (kind, cell, sensor) with the information after
    it, its added cost and the input error after it."""

    kinds: list[tuple] = field(default_factory=list)
    info: list[np.ndarray] = field(default_factory=list)
    dcost: list[float] = field(default_factory=list)
    error: list = field(default_factory=list)

    def add(self, kind: tuple, info: np.ndarray, dcost: float, error) -> None:
        self.kinds.append(kind)
        self.info.append(info)
        self.dcost.append(dcost)
        self.error.append(error)


@dataclass
class _Search:
    """The greedy selection's problem (the grid's information at the campaign rate) and
    where it stands (sensors chosen, tests counted, their information)."""

    cfg: PlanConfig
    sens: Sensitivity
    rate_factor: float
    gram: np.ndarray  # (K, C, S, P, P)
    colsum: np.ndarray  # (K, C, S, P)
    nsamp: np.ndarray  # (C, S) samples each test logs per sensor
    fitted: np.ndarray  # (S,) sensors mbst identify fits
    logged: np.ndarray  # (C, S)
    mandatory: np.ndarray
    s_cost: np.ndarray
    prior: np.ndarray
    chosen: np.ndarray
    counts: np.ndarray
    a: np.ndarray  # (K, S, P, P) information of the tests chosen
    b: np.ndarray
    n: np.ndarray
    info: np.ndarray | None = None
    rel: np.ndarray | None = None
    q: np.ndarray | None = None
    cost: float = 0.0

    @property
    def target(self) -> float:
        return self.cfg.target_relative_std

    @classmethod
    def start(cls, cfg: PlanConfig, sens: Sensitivity, rate_factor: float) -> _Search:
        mandatory = np.array([cfg.sensor(s).mandatory for s in sens.sensors])
        logged = logged_mask(sens)  # (C, S)
        gram = sens.gram * rate_factor
        colsum = sens.colsum * rate_factor
        search = cls(
            cfg, sens, rate_factor, gram=gram, colsum=colsum,
            nsamp=sens.n_samples[:, None] * logged * rate_factor,
            # mbst identify fits the campaign-format channels only: a plan that paid for
            # another sensor would count information no identification uses (still ranked)
            fitted=np.array([SENSORS[s].campaign_channel for s in sens.sensors]),
            logged=logged, mandatory=mandatory,
            s_cost=np.array([cfg.sensor(s).cost for s in sens.sensors]),
            prior=prior_information(cfg), chosen=mandatory.copy(),
            counts=np.zeros(len(sens.cells), int), a=np.zeros_like(gram[:, 0]),
            b=np.zeros_like(colsum[:, 0]), n=np.zeros(len(sens.sensors)))
        search.evaluate()
        return search

    def cost_of(self, ch: np.ndarray, cnt: np.ndarray) -> float:
        tests = {c: int(v) for c, v in enumerate(cnt) if v}
        return plan_cost(self.cfg, self.sens,
                         [s for s, on in zip(self.sens.sensors, ch, strict=True) if on],
                         tests)["identification"]

    def per_test_error(self, ch: np.ndarray) -> np.ndarray | None:
        q = input_error_per_test(self.sens, ch)
        return None if q is None else self.rate_factor**2 * q  # (K, C, P, P)

    @staticmethod
    def total_error(q: np.ndarray | None, cnt: np.ndarray) -> np.ndarray | None:
        return None if q is None else np.einsum("c,kcpq->kpq", cnt.astype(float), q)

    def evaluate(self) -> None:
        eff = offset_eliminated(self.a, self.b, self.n) * self.chosen[:, None, None]
        self.info = eff.sum(axis=-3)  # sum over sensors (..., S, P, P) → (..., P, P)
        self.q = self.per_test_error(self.chosen)
        self.rel = relative_std(self.info, self.total_error(self.q, self.counts))
        self.cost = self.cost_of(self.chosen, self.counts)

    def step(self, label: str) -> Step:
        return Step(label, self.cost, float(np.mean(bits_gained(self.info, self.prior))),
                    float(self.rel.max()), int((self.rel.max(axis=0) <= self.target).sum()))

    def moves(self) -> _Moves:
        """Add a test, a sensor with a test, or a sensor to the tests chosen."""
        sens, chosen, counts = self.sens, self.chosen, self.counts
        cc, ss = len(sens.cells), len(sens.sensors)
        # per-sensor information after adding each candidate test: (C, K, S, P, P)
        a_new = self.a[None] + np.transpose(self.gram, (1, 0, 2, 3, 4))
        b_new = self.b[None] + np.transpose(self.colsum, (1, 0, 2, 3))
        n_new = self.n[None] + self.nsamp
        eff_new = offset_eliminated(a_new, b_new, n_new[:, None, :])
        eff_cur = offset_eliminated(self.a, self.b, self.n)
        out = _Moves()
        b_cur = self.total_error(self.q, counts)
        new_sensors = np.flatnonzero(~chosen & self.fitted)
        q_with = {s: self.per_test_error(chosen | (np.arange(ss) == s)) for s in new_sensors}
        per_scen = {sc.id: self.cfg.max_tests_per_scenario for sc in self.cfg.scenarios}
        for c in range(cc):
            sid = sens.cells[c].scenario_id
            # a repeat is a candidate too: a fresh draw of the angle noise averages the
            # input error that one test cannot (information and that error both add up)
            if sum(counts[k] for k in range(cc)
                   if sens.cells[k].scenario_id == sid) >= per_scen[sid]:
                continue
            cnt = counts.copy()
            cnt[c] += 1
            base_cost = self.cost_of(chosen, cnt)
            f_t = (eff_new[c] * chosen[None, :, None, None]).sum(axis=-3)
            out.add(("test", c, None), f_t, base_cost - self.cost,
                    None if self.q is None else b_cur + self.q[:, c])
            for s in new_sensors:
                if self.logged[c, s]:
                    out.add(("pair", c, s), f_t + eff_new[c][:, s],
                            base_cost + self.s_cost[s] - self.cost,
                            self.total_error(q_with[s], cnt))
        for s in new_sensors:
            out.add(("sensor", None, s), self.info + eff_cur[:, s], self.s_cost[s],
                    self.total_error(q_with[s], counts))
        return out

    def apply(self, kind: str, c: int | None, s: int | None) -> str:
        """Take a move; returns its label."""
        label = []
        if s is not None:
            self.chosen[s] = True
            label.append(f"+sensor {self.sens.sensors[s]}")
        if c is not None:
            self.counts[c] += 1
            self.a, self.b = self.a + self.gram[:, c], self.b + self.colsum[:, c]
            self.n = self.n + self.nsamp[c]
            label.append(f"+test {self.sens.cells[c].label}")
        self.evaluate()
        return " ".join(label)


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
