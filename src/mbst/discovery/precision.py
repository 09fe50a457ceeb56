"""How precisely the tests measure a named effect's size.

A finding's size is read from the extended model. The fit of its stage there gives each
free parameter a standard error (identification's sandwich, ``fitting.precision_at``: the
residual's own memory widens it). It counts the noise, not the model's own error (stated
values a bit off, a sensor lag), which moves a size further: it says when a size is *not*
measured, never that one is exact.

Where the noise alone leaves a strength parameter's standard error above
``NOT_MEASURED_SHARE`` of its distance from neutral, its 2σ interval reaches the effect
switched off: the effect cleared the margins, but these tests do not pin its size. Most
often it trades off with another parameter of the stage (realistic rig 2518: a rack
position-dependent friction centred beyond the 4.6 mm the rack travelled was named at
amplitude 3.28, the rig's 0.46; amplitude and place correlated 0.998, the amplitude's
standard error 2.75).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np

from mbst.core.model import EffectSpec, ModelDefinition
from mbst.discovery.rounds.catalogue import stage_scorer
from mbst.discovery.state import DiscoveryState, Finding
from mbst.identify.fitting import FitResult, precision_at

log = logging.getLogger(__name__)

# a strength whose standard error exceeds this share of its distance from neutral has a
# 2σ interval that reaches the effect switched off
NOT_MEASURED_SHARE = 0.5
# a parameter this correlated with the size is named as what it trades off with
TRADE_OFF_CORRELATION = 0.95


@dataclass
class SizePrecision:
    """The standard errors of one effect's headline parameters, and which strengths these
    tests do not measure, each with the stage parameter it trades off with (or ``None``)."""

    std_error: dict[str, float]
    not_measured: dict[str, tuple[str, float] | None]


def effect_precision(fit: FitResult, free: list[str], spec: EffectSpec,
                     values: dict[str, float], model: ModelDefinition) -> SizePrecision:
    """``spec``'s headline parameters (``values``: headline → fitted value) judged from the
    stage fit's standard errors and correlations (``free``: its parameter order)."""
    std: dict[str, float] = {}
    not_measured: dict[str, tuple[str, float] | None] = {}
    corr = np.asarray(fit.correlation, float)
    for h, v in values.items():
        n = spec.headline[h]
        se = fit.std_error.get(n)
        if se is None or not math.isfinite(se):
            continue
        std[h] = float(se)
        if n not in model.size_parameters(spec):
            continue  # a place or a shape: its error is stated, not judged
        # a strength that grows as its parameter falls (a Dahl stiffness) is 1/value
        dist = abs(v) if n in spec.inverse_size else abs(v - model.spec(n).default)
        if dist > 0 and se > NOT_MEASURED_SHARE * dist:
            not_measured[h] = _partner(corr, free, n)
    return SizePrecision(std, not_measured)


def _partner(corr: np.ndarray, free: list[str], name: str) -> tuple[str, float] | None:
    """The stage parameter most correlated with ``name``, where it reaches
    ``TRADE_OFF_CORRELATION``."""
    j = free.index(name)
    row = np.abs(np.nan_to_num(corr[j]))
    row[j] = 0.0
    k = int(np.argmax(row))
    if row[k] >= TRADE_OFF_CORRELATION:
        return free[k], float(corr[j, k])
    return None


def state_size_precision(findings: list[Finding], state: DiscoveryState) -> None:
    """Each named catalogue effect sized in the extended model gets its precision
    (``Finding.size_std_error``, ``size_not_measured``); a stage whose Jacobian fails
    costs those findings their precision only."""
    model = state.model
    by_stage: dict[str, list[tuple[Finding, EffectSpec, dict[str, float]]]] = {}
    for f in findings:
        spec = model.effects.get(f"{f.effect}:{f.component}")
        if spec is None or spec.key not in state.accepted:
            continue
        # a size restated as its body's (``lumped.py``) is not the fitted parameter
        values = {h: v for h, v in f.parameters.items() if h in spec.headline and math.isclose(
            v, float(state.p[model.param_index[spec.headline[h]]]), rel_tol=1e-9)}
        if values:
            by_stage.setdefault(f.stage, []).append((f, spec, values))
    for stage, items in by_stage.items():
        try:
            fit, free = _stage_fit(state, stage)
        except Exception as exc:  # a precision is a report's aid; it never sinks a name
            log.warning("size precision of the %s stage failed: %s", stage, exc)
            state.failures.append(f"size precision ({stage}): {type(exc).__name__}: {exc}")
            continue
        for f, spec, values in items:
            if any(spec.headline[h] not in free for h in values):
                continue
            _state(f, effect_precision(fit, free, spec, values, model))


def _stage_fit(state: DiscoveryState, stage: str) -> tuple[FitResult, list[str]]:
    """The stage's free parameters' precision at the extended model (its scorer as the
    rounds build it: the same free set, weights and bounds), and their order."""
    scorer = stage_scorer(state, stage)
    free = list(scorer.stage_free)
    return precision_at(scorer.problem(free, state.p), state.p), free


def _state(f: Finding, precision: SizePrecision) -> None:
    f.size_std_error = precision.std_error
    f.size_not_measured = list(precision.not_measured)
    for h, partner in precision.not_measured.items():
        v, se = f.parameters[h], precision.std_error[h]
        with_ = "" if partner is None else (
            f"; these tests fix it only together with {partner[0]} (correlation "
            f"{partner[1]:.3f})")
        f.evidence += (f"; SIZE NOT MEASURED: {h} {v:.3g} has a standard error of "
                       f"{se:.3g} from the noise alone, so its 2σ interval reaches the "
                       f"effect switched off{with_}: these tests show the effect, not its "
                       "size")
