"""Observability of catalogue effects: which sensors separate look-alikes.

An effect's signature in a test is the change of every sensor signal when
the effect (at its catalogue size) is added to the model at the centre of
the ranges. Discovery refits the unknowns, so only the part of a signature
that the unknowns' sensitivities cannot mimic counts (projection, in noise
units, with a per-test sensor offset removed). Two effects look alike when
their projected signatures are parallel; effect e is *separated* from f when
the part of e that f cannot mimic either (at any size) carries

- evidence ≥ ``effects.min_evidence`` (its norm in noise σ summed over the
  test), and
- ≥ ``effects.min_unexplained`` of e's projected signature.

The nearest look-alike of e is the effect whose signature explains most of
e's in any one candidate test at the default sensors (all sensors if e shows
at none of them). For each effect
the search then tries every single test (scenario × input) with every
subset of the sensors and keeps the cheapest that separates e from it.
Only Gram matrices are needed (``Sensitivity.effect_gram``).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np

from mbst.plan.config import PlanConfig
from mbst.plan.information import logged_mask
from mbst.plan.selection import Plan
from mbst.plan.sensitivity import Sensitivity


def residual_gram(m: np.ndarray, p: int) -> np.ndarray:
    """Gram of effect signatures after projecting out the first ``p`` columns (batched)."""
    mjj = m[..., :p, :p]
    mjd = m[..., :p, p:]
    mdd = m[..., p:, p:]
    # pseudo-inverse: a parameter a test cannot see has an all-zero column
    scale = np.sqrt(np.maximum(np.diagonal(mjj, axis1=-2, axis2=-1), 1e-300))
    mn = mjj / (scale[..., :, None] * scale[..., None, :])
    inv = np.linalg.pinv(mn, rcond=1e-10, hermitian=True) / (scale[..., :, None] *
                                                               scale[..., None, :])
    return mdd - np.swapaxes(mjd, -1, -2) @ inv @ mjd


def separation(r: np.ndarray, e: int, f: int | None) -> tuple[np.ndarray, np.ndarray]:
    """Evidence (noise σ) and unexplained share of effect e not mimicked by f (batched)."""
    ree = r[..., e, e]
    if f is None:
        rest = ree
    else:
        rff = r[..., f, f]
        ref = r[..., e, f]
        rest = ree - np.where(rff > 1e-12, ref**2 / np.maximum(rff, 1e-300), 0.0)
    rest = np.maximum(rest, 0.0)
    share = np.sqrt(rest / np.maximum(ree, 1e-300))
    return np.sqrt(rest), np.where(ree > 0, share, 0.0)


def _look_alikes(rs: np.ndarray, min_evidence: float) -> list[tuple[int | None, float]]:
    """For each effect, the other effect that mimics it most in any one test.

    ``rs`` is (C, E, E): residual Grams per test. Similarity is cos² of the
    projected signatures, counted only in tests where both effects show
    (evidence ≥ ``min_evidence``); the look-alike maximises it over the tests.
    """
    ee = rs.shape[-1]
    d2 = np.maximum(np.diagonal(rs, axis1=-2, axis2=-1), 0.0)  # (C, E)
    shows = d2 >= min_evidence**2
    with np.errstate(invalid="ignore", divide="ignore"):
        cos2 = rs**2 / (d2[:, :, None] * d2[:, None, :])
    cos2 = np.where(shows[:, :, None] & shows[:, None, :], np.nan_to_num(cos2), -1.0)
    sim = cos2.max(axis=0)  # (E, E)
    out = []
    for e in range(ee):
        row = sim[e].copy()
        row[e] = -1.0
        f = int(np.argmax(row))
        out.append((f, float(row[f])) if row[f] >= 0 else (None, 0.0))
    return out


def effect_observability(cfg: PlanConfig, sens: Sensitivity, plan: Plan | None,
                         rate_factor: float) -> list[dict]:
    """Per catalogue effect: look-alike, whether the defaults and the plan separate it,
    and the cheapest sensor set + test that does.

    Returns
    -------
    list of dict
        One row per effect (for ``effects.csv``).
    """
    if not sens.effects:
        return []
    p = len(sens.unknowns)
    mg = sens.effect_gram * rate_factor  # (C, S, A, A)
    default = _default_sensor_mask(cfg, sens)
    r_def = residual_gram(np.einsum("s,csab->ab", default, mg), p)
    looks = _look_alikes(residual_gram(np.einsum("s,csab->cab", default, mg), p),
                         cfg.effects_min_evidence)
    looks_all = _look_alikes(residual_gram(mg.sum(axis=1), p), cfg.effects_min_evidence)
    r_plan = None if plan is None else _plan_residual_gram(sens, plan, mg, p)
    mand = [i for i, s in enumerate(sens.sensors) if cfg.sensor(s).mandatory]
    options = _test_options(cfg, sens, mg, mand)

    rows = []
    for e, key in enumerate(sens.effects):
        f, c2 = looks[e]
        if f is None:
            f, c2 = looks_all[e]
        ev_def, sh_def = separation(r_def, e, f)
        best = _cheapest_separation(cfg, options, e, f)
        row = {
            "effect": key,
            "look_alike": sens.effects[f] if f is not None else "",
            "similarity_at_defaults": round(c2, 4),
            "evidence_at_defaults": float(ev_def),
            "separated_at_defaults": _separated(cfg, ev_def, sh_def),
        }
        if r_plan is not None:
            ev_p, sh_p = separation(r_plan, e, f)
            row["evidence_in_plan"] = float(ev_p)
            row["separated_by_plan"] = _separated(cfg, ev_p, sh_p)
        row.update(_cheapest_columns(sens, mand, best))
        rows.append(row)
    return rows


def _default_sensor_mask(cfg: PlanConfig, sens: Sensitivity) -> np.ndarray:
    """(S,) 1 for the sensors ``effects.default_sensors`` names, else 0."""
    s_index = {s: i for i, s in enumerate(sens.sensors)}
    default = np.zeros(len(sens.sensors))
    for s in cfg.effects_default_sensors:
        default[s_index[s]] = 1.0
    return default


def _plan_residual_gram(sens: Sensitivity, plan: Plan, mg: np.ndarray, p: int) -> np.ndarray:
    """(E, E) residual Gram of the plan's tests on the sensors it logs."""
    smask = np.array([s in plan.logged for s in sens.sensors], float)
    counts = plan.counts(len(sens.cells))
    return residual_gram(np.einsum("c,s,csab->ab", counts, smask, mg), p)


def _separated(cfg: PlanConfig, evidence: np.ndarray, share: np.ndarray) -> bool:
    """Whether what a look-alike cannot mimic is both large and a large enough share."""
    return bool(evidence >= cfg.effects_min_evidence and share >= cfg.effects_min_unexplained)


@dataclass
class _TestOption:
    """One test (cell) with every sensor set the search tries on it."""

    cell: int
    subsets: list[tuple[int, ...]]  # optional sensors added to the mandatory ones
    costs: np.ndarray  # (B,) test plus sensors
    residual: np.ndarray  # (B, E, E) residual Gram of each sensor set


def _sensor_subsets(optional: list[int]) -> list[tuple[int, ...]]:
    """Every subset of ``optional``, the empty one first, then by size."""
    subsets = [()]
    for k in range(1, len(optional) + 1):
        subsets += list(itertools.combinations(optional, k))
    return subsets


def _test_options(cfg: PlanConfig, sens: Sensitivity, mg: np.ndarray, mand: list[int]
                  ) -> list[_TestOption]:
    """Per cell: every subset of the optional sensors that move in that scenario, with the
    mandatory sensors, priced and reduced to its residual Gram."""
    p = len(sens.unknowns)
    mand_cost = sum(cfg.sensor(sens.sensors[i]).cost for i in mand)
    logged = logged_mask(sens)
    options = []
    for c, cell in enumerate(sens.cells):
        opt = [i for i in range(len(sens.sensors)) if i not in mand and logged[c, i]]
        subsets = _sensor_subsets(opt)
        masks = np.zeros((len(subsets), len(sens.sensors)))
        costs = np.zeros(len(subsets))
        for b, sub in enumerate(subsets):
            masks[b, list(sub) + mand] = 1.0
            costs[b] = mand_cost + sum(cfg.sensor(sens.sensors[i]).cost for i in sub)
        costs += cfg.scenario(cell.scenario_id).cost + cfg.input(cell.input_id).cost
        r = residual_gram(np.einsum("bs,sxy->bxy", masks, mg[c]), p)
        options.append(_TestOption(c, subsets, costs, r))
    return options


@dataclass
class _Separation:
    """The cheapest test and sensor set found to separate an effect from its look-alike."""

    cost: float
    cell: int
    subset: tuple[int, ...]
    evidence: float
    share: float


def _cheapest_separation(cfg: PlanConfig, options: list[_TestOption], e: int, f: int | None
                         ) -> _Separation | None:
    """Over every test and sensor set: the cheapest that separates effect ``e`` from ``f``,
    then the one with the most evidence (None if none does)."""
    best = None
    for opt in options:
        ev, sh = separation(opt.residual, e, f)
        ok = (ev >= cfg.effects_min_evidence) & (sh >= cfg.effects_min_unexplained)
        if not ok.any():
            continue
        # cheapest, then the most evidence
        order = np.lexsort((-ev, opt.costs))
        b = int(next(i for i in order if ok[i]))
        cand = _Separation(float(opt.costs[b]), opt.cell, opt.subsets[b], float(ev[b]),
                           float(sh[b]))
        if best is None or (cand.cost, -cand.evidence) < (best.cost, -best.evidence):
            best = cand
    return best


def _cheapest_columns(sens: Sensitivity, mand: list[int], best: _Separation | None) -> dict:
    """The ``cheapest_*``, ``evidence`` and ``unexplained_share`` columns of an effect's row."""
    if best is None:
        return {"cheapest_scenario": "", "cheapest_input": "", "cheapest_sensors": "",
                "cheapest_cost": float("nan"), "evidence": float("nan"),
                "unexplained_share": float("nan")}
    names = [sens.sensors[i] for i in mand] + [sens.sensors[i] for i in best.subset]
    return {"cheapest_scenario": sens.cells[best.cell].scenario_id,
            "cheapest_input": sens.cells[best.cell].input_id,
            "cheapest_sensors": " ".join(names), "cheapest_cost": best.cost,
            "evidence": best.evidence, "unexplained_share": best.share}
