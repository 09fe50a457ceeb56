"""Signature questions: which quantity does an unexplained finding's structure follow?

Discovery's unexplained round ranks the generic library's groups by the share
of a channel's residual each predicts on held-out tests
(``discovery/signature.py``). Where another group comes within the margin of
the best (``min_share``, the share a catalogue effect must remove), the
campaign has not said which quantity the structure follows: a ripple in the
motor's angle or a law in the rack's position, a channel's lag or a level that
grows with the rate, a drift over the campaign or a law the running order
mimics. Each such pair is a question for the design, scored like a rival
catalogue pair (``design.py``): the best reading's learned term is the signal,
and what the rival reading's refit cannot take over of it (its features, the
channel's scale and the stage's parameters, jointly over the tests) is the
separation.

How far apart the campaign already has them comes from its own held-out
folds: per test left out, the squared error of each reading fitted on the
others; the mean difference over its spread (a paired z) is read as the share
of resamples the best reading would win, the bootstrap share a rival catalogue
pair carries (``design.calibrate_rivals``). A pair the campaign already
separates (that share ≥ 95 %) is no question.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.stats import norm

from mbst.core.family import get_system
from mbst.discovery.acceptance import SEPARATED_SHARE
from mbst.discovery.data import TestResidual, residual_data
from mbst.discovery.signature import SAMPLES_PER_TEST, feature_groups
from mbst.identify.fitting import FitProblem, PreparedTest
from mbst.io.campaign import Campaign, places_step, running_order_places
from mbst.plan.resolve.questions import Question

# rival readings asked per channel (the ranking's next best within the margin)
MAX_RIVALS = 2


@dataclass
class Reading:
    """One channel's structure read two ways, fitted on the campaign's own tests."""

    channel: str
    group: str  # the finding's reading (the best held-out group)
    harmonic: int  # its order where periodic (else 0)
    rival: str  # a group the campaign ranked within the margin of it
    rival_harmonic: int
    coefficients: np.ndarray  # the best reading's term, raw units (least squares)
    gain: float  # the held-out gain the finding applies its learned term at
    scenarios: tuple[str, ...]  # the cut-outs of the tests logging the channel (drift blocks)
    input_name: str
    places: dict[str, float]  # each campaign test's place in the running order (−½…½)
    next_place: float  # a test added after the campaign
    observed_z: float  # the campaign's own paired separation (module doc)
    shares: tuple[float, float] = (0.0, 0.0)  # held-out shares (reading, rival)
    rival_width: int = 0  # the rival reading's features (zeros where a test lacks them)
    _cache: dict = field(default_factory=dict, repr=False)

    def key(self, stage: str) -> str:
        return f"unexplained:{self.channel}:{self.group}|{self.rival}@{stage}"

    def label(self) -> str:
        return f"structure in {self.channel}: {_named(self.group, self.harmonic)} or " \
               f"{_named(self.rival, self.rival_harmonic)}"

    def place(self, test_id: str) -> float:
        return self.places.get(test_id, self.next_place)

    def term(self, t: TestResidual) -> np.ndarray:
        """The best reading's learned term on ``t`` (centred, at the finding's gain)."""
        x = _group(t, self, self.group, self.harmonic)
        return np.zeros(len(t.time_s)) if x is None else self.gain * (x @ self.coefficients)

    def rival_columns(self, t: TestResidual) -> np.ndarray:
        """What the rival reading's refit may use on ``t``: its features and the channel's
        scale against its twin (calibration both readings share), centred."""
        x = _group(t, self, self.rival, self.rival_harmonic)
        twin = _centre(t.simulated[self.channel])[:, None]
        return np.hstack([np.zeros((len(twin), self.rival_width)) if x is None else x, twin])


def _named(group: str, harmonic: int) -> str:
    return f"{group} (order {harmonic})" if group.startswith("periodic:") else group


def _centre(x: np.ndarray) -> np.ndarray:
    return x - x.mean(axis=0)


def _group(t: TestResidual, r: Reading, group: str, harmonic: int) -> np.ndarray | None:
    """A group's features on ``t`` (centred per test, as the library fits them)."""
    key = (t.id, len(t.time_s))
    if key not in r._cache:
        r._cache.clear()  # one test at a time: the periodic group holds every order
        r._cache[key] = feature_groups(t, r.channel, r.place(t.id), r.input_name, r.scenarios)
    x = _pick(r._cache[key], group, harmonic)
    return None if x is None else _centre(x)


def _pick(groups: dict, group: str, harmonic: int) -> np.ndarray | None:
    """A group's features from ``feature_groups``'s output (a periodic one at its order)."""
    x = groups.get(group)
    if isinstance(x, dict):
        x = x.get(harmonic)
    return None if x is None else np.asarray(x, float)


def _lstsq(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    sd = x.std(axis=0)
    sd[sd == 0] = 1.0
    return np.linalg.lstsq(x / sd, y, rcond=None)[0] / sd


def _fold_sse(xs: list[np.ndarray], ys: list[np.ndarray]) -> np.ndarray:
    """Squared error on each test of a reading fitted on the others."""
    out = np.zeros(len(ys))
    for k in range(len(ys)):
        rest = [i for i in range(len(ys)) if i != k]
        c = _lstsq(np.vstack([xs[i] for i in rest]), np.concatenate([ys[i] for i in rest]))
        out[k] = float(np.sum((ys[k] - xs[k] @ c) ** 2))
    return out


@dataclass
class _ChannelData:
    """One channel's residual and features over the campaign's tests that log it."""

    channel: str
    tests: list[TestResidual]
    ys: list[np.ndarray]
    twins: list[np.ndarray]
    groups: list[dict]

    def design(self, group: str, harmonic: int) -> list[np.ndarray] | None:
        """Per test, the group's features and the channel's twin; a test the group does not
        reach (an angle that sweeps too little there) has zero features, as in the
        library. None where no test has the group."""
        found = [_pick(g, group, harmonic) for g in self.groups]
        width = next((x.shape[1] for x in found if x is not None), None)
        if width is None:
            return None
        return [np.hstack([np.zeros((len(tw), width)) if x is None else _centre(x),
                           tw[:, None]]) for x, tw in zip(found, self.twins, strict=True)]

    def reached(self, group: str, harmonic: int) -> list[str]:
        """The cut-outs on whose tests the group has features (its angle sweeps enough)."""
        return list(dict.fromkeys(t.scenario for t, g in zip(self.tests, self.groups,
                                                              strict=True)
                                  if _pick(g, group, harmonic) is not None))

    def best_harmonic(self, group: str) -> int:
        """A periodic group's order by in-sample fit, as the library picks it (else 0)."""
        orders = sorted({n for g in self.groups if isinstance(g.get(group), dict)
                         for n in g[group]})
        if not orders:
            return 0
        y = np.concatenate(self.ys)
        best, at = -math.inf, 0
        for n in orders:
            xs = self.design(group, n)
            if xs is None:
                continue
            x = np.vstack(xs)
            fit = float(np.sum((x @ _lstsq(x, y)) ** 2))
            if fit > best:
                best, at = fit, n
        return at


def _channel_data(tests: list[TestResidual], channel: str, places: dict[str, float],
                  input_name: str) -> _ChannelData:
    logged = [t for t in tests if channel in t.measured]
    scenarios = tuple(dict.fromkeys(t.scenario for t in logged))
    ys, twins, groups = [], [], []
    for t in logged:
        step = max(1, len(t.time_s) // SAMPLES_PER_TEST)
        ys.append(_centre(t.residual(channel))[::step])
        twins.append(_centre(t.simulated[channel])[::step])
        g = feature_groups(t, channel, places.get(t.id, 0.0), input_name, scenarios)
        groups.append({k: ({n: x[::step] for n, x in v.items()} if isinstance(v, dict)
                           else v[::step]) for k, v in g.items()})
    return _ChannelData(channel, logged, ys, twins, groups)


def _paired_z(a: np.ndarray, b: np.ndarray) -> float:
    """How far the held-out errors of reading ``a`` sit below ``b``'s: mean over spread."""
    d = b - a
    if len(d) < 2:
        return 0.0
    sd = float(np.std(d, ddof=1))
    return float(np.mean(d) / (sd / math.sqrt(len(d)))) if sd > 0 else (
        math.inf if np.mean(d) > 0 else 0.0)


def _readings(data: _ChannelData, rec: dict, base: dict) -> list[Reading]:
    best = rec.get("best") or {}
    group, share = best.get("group"), float(best.get("share_of_residual") or 0.0)
    margin = float(rec.get("min_share") or 0.0)
    if not group or len(data.ys) < 2:
        return []
    harmonic = int(best.get("periods_per_rev") or 0) or data.best_harmonic(group)
    own = data.design(group, harmonic)
    if own is None:
        return []
    y = np.concatenate(data.ys)
    coef = _lstsq(np.vstack(own), y)[:-1]  # the channel's scale is not the reading's term
    sse = _fold_sse(own, data.ys)
    out = []
    for r in (rec.get("ranking") or [])[1:]:
        if len(out) == MAX_RIVALS or float(r["share_of_residual"]) < share - margin:
            break
        n = data.best_harmonic(r["group"])
        theirs = data.design(r["group"], n)
        if theirs is None:
            continue
        z = _paired_z(sse, _fold_sse(theirs, data.ys))
        out.append(Reading(data.channel, group, harmonic, r["group"], n, coef,
                           float(rec.get("learned_gain") or 1.0), **base, observed_z=z,
                           shares=(share, float(r["share_of_residual"])),
                           rival_width=theirs[0].shape[1] - 1))
    return out


def signature_questions(record: dict, campaign: Campaign, ids: list[PreparedTest],
                        p: np.ndarray) -> tuple[list[Question], list[str]]:
    """The open readings of every unexplained finding, one question per rival reading and
    cut-out; and notes on the findings whose reading the campaign already decides."""
    found = [f for f in record.get("findings", []) if f.get("effect") == "unexplained"
             and (f.get("signature") or {}).get("channels")]
    if not found:
        return [], []
    model = ids[0].model
    input_name = get_system(model.name).input_channel
    order = [s.id for s in campaign.tests]
    places = running_order_places(order)  # as discovery places them
    tests = [residual_data(pt, p) for pt in ids]
    questions, notes = [], []
    for f in found:
        for rec in f["signature"]["channels"]:
            if not rec.get("structured"):
                continue
            data = _channel_data(tests, rec["channel"], places, input_name)
            base = {"scenarios": tuple(dict.fromkeys(t.scenario for t in data.tests)),
                    "input_name": input_name, "places": places,
                    "next_place": 0.5 + places_step(order)}
            readings = _readings(data, rec, base)
            open_ = [r for r in readings if norm.cdf(r.observed_z) < SEPARATED_SHARE]
            if not open_:
                notes.append(f"the structure left in {rec['channel']} follows "
                             f"{(rec.get('best') or {}).get('group')}: no other reading within "
                             "the margin that these tests do not already rule out")
            for r in open_:
                for stage in data.reached(r.group, r.harmonic):
                    questions.append(Question(
                        None, stage, {}, "an unexplained finding's reading not decided",
                        {"share": r.shares[0], "rival's share": r.shares[1]},
                        observed_share=float(norm.cdf(r.observed_z)), signature=r))
    return questions, notes


def signature_rows(q: Question, prob: FitProblem, pt: PreparedTest, t: TestResidual
                   ) -> tuple[np.ndarray, np.ndarray]:
    """The question's signal on test ``pt`` and the rival reading's columns, in the stage's
    residual layout (channels stacked, decimated, weighted as the fit weighs them)."""
    r = q.signature
    ch = r.channel
    if ch not in pt.measured:  # zero rows, as many columns as on a test that logs it
        rows = len(prob._res_of_twin(pt, pt.measured))
        return np.zeros(rows), np.zeros((rows, r.rival_width + 1))

    def rows_of(x: np.ndarray) -> np.ndarray:
        return prob._res_of_twin(pt, {**pt.measured, ch: pt.measured[ch] + x})

    cols = r.rival_columns(t)
    return rows_of(r.term(t)), np.column_stack([rows_of(c) for c in cols.T])


def reading_curves(q: Question, pt: PreparedTest, p: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray]:
    """The best reading's term on a predicted test and the rival reading's best fit to it
    on that test alone (channel units): what the figure draws."""
    t = residual_data(pt, p)
    term = q.signature.term(t)
    cols = q.signature.rival_columns(t)
    return term, cols @ _lstsq(cols, term)
