"""``mbst plan --resolve``: read what discovery left open, design, predict, write."""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mbst.core.family import get_system
from mbst.core.model import ModelDefinition
from mbst.identify.fitting import PreparedTest, channel_scales, prepare_test
from mbst.identify.replicate import raw_noise
from mbst.io.campaign import Campaign, read_campaign
from mbst.plan.resolve.candidates import Candidate, candidate_tests, predicted_test
from mbst.plan.resolve.design import (
    Context,
    Margins,
    Step,
    calibrate_rivals,
    greedy,
    refit_rival,
    test_blocks,
    time_needed,
)
from mbst.plan.resolve.questions import Question, ResolveError, open_questions
from mbst.plan.resolve.signatures import signature_questions
from mbst.systems.eps.channels import SYSTEM_NAME

DISCOVERY_FORMAT = "mbst-discovery/2"
# beyond the budget, the design goes on up to this multiple of the campaign's test time to
# say how much test time an undecided question would need
NEEDED_UP_TO = 2.0


@dataclass
class ResolveResult:
    """The design: open questions, the tests added and the predictions before and after."""

    campaign: Campaign
    record: dict  # the discovery record read
    questions: list[Question]
    candidates: list[Candidate]
    steps: list[Step]
    before: dict[str, tuple[float, float]]
    margins: Margins
    budget_s: float
    campaign_time_s: float
    predicted: dict[str, PreparedTest] = field(repr=False, default_factory=dict)
    context: Context | None = field(repr=False, default=None)
    input_channel: str = ""
    noise: dict[str, float] = field(default_factory=dict)  # raw noise rms per channel
    logged: dict[str, list[str]] = field(default_factory=dict)  # stage -> the campaign's tests
    # per question: the test time after which it clears (None: not within NEEDED_UP_TO)
    needed: dict[str, float | None] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    wall_s: float = 0.0

    @property
    def after(self) -> dict[str, tuple[float, float]]:
        return self.steps[-1].scores if self.steps else dict(self.before)

    def added(self) -> list[tuple[str, Candidate]]:
        """(campaign test id, candidate) of every test added, in the order chosen."""
        by_id = {c.id: c for c in self.candidates}
        out, seen = [], {}
        for s in self.steps:
            seen[s.test] = seen.get(s.test, 0) + 1
            suffix = f"_r{seen[s.test]}" if seen[s.test] > 1 else ""
            out.append((f"resolve_{s.test}{suffix}", by_id[s.test]))
        return out

    def _needed_text(self, q: Question) -> str:
        if self.margins.clears(q, *self.after.get(q.key, (0.0, 0.0))):
            return ""
        t = self.needed.get(q.key)
        return (f" (would need {t:.0f} s of tests)" if t is not None else
                f" (not within {NEEDED_UP_TO:g}× the campaign's test time)")

    def summary(self) -> str:
        lines = [f"resolve '{self.campaign.name}' in {self.wall_s:.1f} s: "
                 f"{len(self.questions)} open question(s), {len(self.steps)} test(s) added "
                 f"({sum(s.duration_s for s in self.steps):.0f} s of "
                 f"{self.budget_s:.0f} s allowed; the campaign has {self.campaign_time_s:.0f} s)"]
        for q in self.questions:
            b, a = self.before.get(q.key, (0.0, 0.0)), self.after.get(q.key, (0.0, 0.0))
            lines.append(f"  {q.label():<60} share {100 * b[0]:5.1f} % -> {100 * a[0]:5.1f} %, "
                         f"ΔAIC {b[1]:8.1f} -> {a[1]:8.1f}: "
                         + ("resolved" if self.margins.clears(q, *a) else "NOT resolved")
                         + self._needed_text(q))
        for n in self.notes:
            lines.append(f"  note: {n}")
        for tid, c in self.added():
            change = f" with {c.sensor_change}" if c.sensor_change else ""
            lines.append(f"  + {tid}: {c.scenario}, {json.dumps(c.input)}{change} "
                         f"({c.duration_s:.0f} s)")
        return "\n".join(lines)


def read_discovery(path: str | Path) -> tuple[dict, Path]:
    """The discovery record (a ``discovery.json`` or the folder holding it)."""
    path = Path(path)
    if path.is_dir():
        path = path / "discovery.json"
    try:
        record = json.loads(path.read_text())
    except FileNotFoundError:
        raise ResolveError(f"{path}: no such file (run `mbst discover` first)") from None
    except json.JSONDecodeError as exc:
        raise ResolveError(f"{path}: not JSON ({exc})") from None
    if record.get("format") != DISCOVERY_FORMAT:
        raise ResolveError(f"{path}: format {record.get('format')!r}, expected {DISCOVERY_FORMAT}")
    if "stages" not in record or "vector" not in record:
        raise ResolveError(f"{path}: written by an older mbst without the stages the design "
                           "needs; run `mbst discover` again")
    return record, path


def _campaign(record: dict, path: Path, campaign_dir: str | Path | None) -> Campaign:
    where = Path(campaign_dir) if campaign_dir else Path(record["stages"]["campaign_path"])
    if not where.is_absolute() and campaign_dir is None and not where.exists():
        where = path.parent / where
    return read_campaign(where)


def _another_family(campaign: Campaign, record: dict, margins: Margins, t0: float
                    ) -> ResolveResult:
    """A campaign of a family the designer does not know: a note, no test designed."""
    # a workflow may list every family's campaigns: say so, do not stop the run
    note = (f"system '{campaign.system}': the test designer knows the {SYSTEM_NAME} "
            "rig's cut-outs, inputs and sensors only; no test designed")
    return ResolveResult(campaign, record, [], [], [], {}, margins, 0.0, 0.0,
                         notes=[note], wall_s=time.perf_counter() - t0)


def _readings(record: dict, campaign: Campaign, ids: list[PreparedTest], p: np.ndarray
              ) -> tuple[list[Question], list[str]]:
    """``signature_questions``, a failure there reported as a note."""
    try:
        readings, notes = signature_questions(record, campaign, ids, p)
    except Exception as exc:  # the catalogue's questions never hang on the readings'
        return [], [f"the unexplained finding's readings were not asked: "
                    f"{type(exc).__name__}: {exc}"]
    return readings, notes


def _logged_blocks(ctx: Context, model: ModelDefinition, ids: list[PreparedTest],
                   stages: set[str]) -> dict[str, list[str]]:
    """The campaign's own tests of each stage reduced into ``ctx.blocks``; their ids."""
    logged: dict[str, list[str]] = {}
    for stage in sorted(stages):
        for pt in model.stage_tests(stage, ids):
            dur = float(pt.time_s[-1] - pt.time_s[0])
            ctx.blocks[f"{stage}/{pt.id}"] = test_blocks(ctx, pt, stage, dur)
            logged.setdefault(stage, []).append(f"{stage}/{pt.id}")
    return logged


def _design(ctx: Context, logged: dict[str, list[str]], cands: list[Candidate],
            campaign_time: float, budget: float
            ) -> tuple[list[Step], dict[str, tuple[float, float]], dict[str, float | None]]:
    """The tests added within ``budget``, the scores before them, and per question the
    test time it needs."""
    # first how much test time each question needs; then the budget goes to the questions
    # it can decide (test time spent on one it cannot decide is wasted rig time)
    longer, _ = greedy(ctx, logged, [c.id for c in cands], NEEDED_UP_TO * campaign_time)
    needed = time_needed(ctx, longer)
    focus = {k for k, t in needed.items() if t is not None and t <= budget}
    steps, before = greedy(ctx, logged, [c.id for c in cands], budget, focus)
    return steps, before, needed


def resolve(discovery: str | Path, targets: list[str] | None = None,
            campaign_dir: str | Path | None = None, budget_share: float = 0.5, seed: int = 0,
            progress: bool = False) -> ResolveResult:
    """Design the tests that let discovery decide what it left open (module docs)."""
    t0 = time.perf_counter()
    record, path = read_discovery(discovery)
    campaign = _campaign(record, path, campaign_dir)
    model = campaign.model()
    acc = record["acceptance"]
    margins = Margins(acc["min_relative_gain"], acc["min_aic_drop"], len(model.catalogue))
    if campaign.system != SYSTEM_NAME:
        return _another_family(campaign, record, margins, t0)
    st = record["stages"]
    p = model.vector_from({k: v for k, v in record["vector"].items() if k in model.param_index})
    ids = [prepare_test(campaign, s, st["tau_s"]) for s in campaign.identification_tests()]
    questions, notes = open_questions(record, model, targets or [])
    readings, read_notes = _readings(record, campaign, ids, p)
    questions, notes = questions + readings, notes + read_notes
    ctx = Context(p, channel_scales(ids), st["stage_free"], st["compensating"], st["decimate"],
                  questions, margins)
    ctx.questions = questions = [q if q.rival is None else
                                 refit_rival(ctx, q, model.stage_tests(q.stage, ids))
                                 for q in questions]
    stages = {q.stage for q in questions}
    logged = _logged_blocks(ctx, model, ids, stages)
    cands = candidate_tests(ids, stages)
    channel = get_system(model.name).input_channel
    noise = raw_noise({pt.id: campaign.frame(pt.id) for pt in ids}, ids, channel)
    predicted = {}
    for i, c in enumerate(cands):
        if progress:
            print(f"  predicting {c.id} ({i + 1}/{len(cands)})", flush=True)
        pt = predicted_test(c, model, p, channel, noise, ids[0].dt_s, st["tau_s"],
                            np.random.default_rng([seed, 11, i]))
        predicted[c.id] = pt
        ctx.blocks[c.id] = test_blocks(ctx, pt, c.scenario, c.duration_s)
    calibrate_rivals(ctx, logged)
    campaign_time = sum(float(pt.time_s[-1] - pt.time_s[0]) for pt in ids)
    budget = budget_share * campaign_time
    steps, before, needed = _design(ctx, logged, cands, campaign_time, budget)
    return ResolveResult(campaign, record, questions, cands, steps, before, margins, budget,
                         campaign_time, predicted=predicted, context=ctx, input_channel=channel,
                         noise=noise, logged=logged, needed=needed, notes=notes,
                         wall_s=time.perf_counter() - t0)
