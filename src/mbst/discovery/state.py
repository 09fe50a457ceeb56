"""What discovery carries from round to round: settings, the model as it stands, records.

Every round (``discovery/rounds/``) takes a ``DiscoveryState`` and proposes findings
into it; the pipeline loops over the family's rounds and never reaches inside them.
"""

from __future__ import annotations

import copy
import logging
import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from mbst.core.family import get_system
from mbst.core.model import ModelDefinition
from mbst.discovery.data import TestResidual
from mbst.discovery.restarts import compensating_parameters
from mbst.discovery.structure import effective_samples
from mbst.identify.cascade import IdentifyResult, IdentifySettings
from mbst.identify.fitting import (
    PreparedTest,
    channel_scales,
    input_noise_floors,
    twins_of_tests,
)
from mbst.io.campaign import Campaign

log = logging.getLogger(__name__)

# what a round may change in the state: put back when it fails (``DiscoveryState.checkpoint``)
_ROUND_MUTABLE = ("residuals", "p", "cost", "accepted", "extra_free", "rounds", "proposals",
                  "findings", "resolution", "signatures", "extended_residuals",
                  "rival_physics", "p_searched")

if TYPE_CHECKING:
    from mbst.discovery.structure import CandidateScore


@dataclass
class DiscoverSettings:
    """Settings of discovery (config: ``discover.*``).

    ``min_relative_gain`` is the smallest share of its stage's residual cost an
    effect must remove to be named: on clean campaigns, the EPS bench's and the
    realistic bench's, the best candidate removes at most ~5 % (``benchmarks/``
    prints it). ``min_aic_drop`` ``None``: the significance margin comes from the
    campaign (``acceptance.aic_drop_needed``); a number replaces it.
    ``sparse``, ``neural``, ``stick_slip``, ``equation_error`` and ``resolution``
    switch off a round or an evidence method the family has; they never switch on
    one it does not declare (``ModelDefinition.discovery_rounds``/``evidence_methods``).
    """

    identify: IdentifySettings = field(default_factory=IdentifySettings)
    max_effects: int = 4
    min_relative_gain: float = 0.10
    min_aic_drop: float | None = None
    refine: int = 5
    cv_nfev: int = 8
    sparse: bool = True
    neural: bool = True
    stick_slip: bool = True
    equation_error: bool = True
    neural_iterations: int | None = None
    progress: bool = False
    resolution: bool = True

    def wants(self, model: ModelDefinition, name: str) -> bool:
        """Whether round or evidence method ``name`` runs: the family has it, the user kept it."""
        declared = name in model.discovery_rounds or name in model.evidence_methods
        return declared and getattr(self, name, True)


@dataclass
class Finding:
    """One named effect (discovery.json ``findings`` entry)."""

    effect: str
    component: str
    parameters: dict[str, float]
    confidence: float
    evidence: str
    stage: str
    relative_gain: float
    aic_delta: float | None  # None where the criterion is not the output error (stick-slip)
    cv: dict
    # components the same effect could sit in as well: they move as one body with
    # ``component`` in the stage's tests and explain the data alike
    indistinguishable_from: list[str] = field(default_factory=list)
    # other catalogue pairs the campaign does not rule out: resamples of its data
    # prefer them to this one often enough (``acceptance.ranking_bootstrap``)
    alternatives: list[dict] = field(default_factory=list)
    # an ``unexplained`` finding's description: what the residual correlates with, where
    signature: dict | None = None
    # the unexplained round's verdict on a catalogue name: "confirmed" (nothing left in
    # its stage's channels), "partly explained", "in doubt"; "" where the round did not run
    confirmation: str = ""
    # the noise-only standard error of each headline parameter in the extended model's
    # stage fit, and the strengths these tests do not measure (``precision.py``)
    size_std_error: dict[str, float] = field(default_factory=dict)
    size_not_measured: list[str] = field(default_factory=list)

    def record(self) -> dict:
        return {"effect": self.effect, "component": self.component or None,
                "parameters": self.parameters, "confidence": round(self.confidence, 4),
                "evidence": self.evidence, "stage": self.stage,
                "relative_gain": self.relative_gain, "aic_delta": self.aic_delta,
                "cross_validation": self.cv,
                "indistinguishable_from": list(self.indistinguishable_from),
                "alternatives": list(self.alternatives),
                **({"signature": self.signature} if self.signature is not None else {}),
                **({"confirmation": self.confirmation} if self.confirmation else {}),
                **({"size_std_error": self.size_std_error} if self.size_std_error else {}),
                **({"size_not_measured": self.size_not_measured}
                   if self.size_not_measured else {})}


@dataclass
class Proposal:
    """A structure-test winner, named once the sparse and neural evidence are in."""

    best: CandidateScore
    runner: CandidateScore | None
    cv: dict
    weight: float  # Akaike weight among the stage's candidates
    ties: list[tuple[CandidateScore, float]]
    # acceptance.ranking_bootstrap: how often resamples of the stage's data still name it
    bootstrap: dict = field(default_factory=dict)


def total_cost(tests: list[PreparedTest], p: np.ndarray, scales: dict[str, float],
               decimate: int = 2) -> tuple[float, list[np.ndarray]]:
    """Weighted data cost of ``p`` on ``tests`` (as the cascade weighs it) and the residuals."""
    cost, res = 0.0, []
    for pt, (tw,) in zip(tests, twins_of_tests(tests, [p[None]] * len(tests)), strict=True):
        n = len(pt.time_s[::decimate])
        for ch in pt.measured:
            r = (tw[ch] - pt.measured[ch])[::decimate]
            res.append(r)
            w = 1.0 / (scales[ch] * math.sqrt(n))
            cost += 0.5 * float(np.sum((r * w) ** 2))
    return cost, res


@dataclass
class DiscoveryState:
    """The model as discovery has extended it so far, and what each round recorded."""

    campaign: Campaign
    settings: DiscoverSettings
    base: IdentifyResult
    residuals: list[TestResidual]
    regions: list
    ids: list[PreparedTest]
    scales: dict[str, float]
    p: np.ndarray
    cost: float
    timings: dict[str, float]
    base_cost: float  # identification cost of the base model
    base_n_eff: float  # effective samples of its residual
    accepted: list[str] = field(default_factory=list)
    extra_free: dict[str, tuple[str, ...]] = field(default_factory=dict)
    rounds: list[dict] = field(default_factory=list)
    proposals: list[Proposal] = field(default_factory=list)
    findings: list[Finding] = field(default_factory=list)
    resolution: list = field(default_factory=list)
    # what the extended model's residual correlates with, per channel (rounds/unexplained.py)
    signatures: list = field(default_factory=list)
    extended_residuals: list[TestResidual] = field(default_factory=list)
    # the extended model with a reality outside the catalogue refitted in its stage (a
    # sensor's lag, a drift over the campaign: ``rounds/rival_findings.py``); the physics
    # under the "physics + learned" row; ``None``: no such reality found
    rival_physics: np.ndarray | None = None
    # a round or method that failed on the way (reported; never the answer)
    failures: list[str] = field(default_factory=list)
    # the model the structure rounds last searched (``None``: they did not run); a later
    # round whose effect no output-error refit sees (stick-slip, equation error) moves
    # ``p`` on from it, and the resolution step predicts against this one
    p_searched: np.ndarray | None = None

    @classmethod
    def start(cls, campaign: Campaign, settings: DiscoverSettings, base: IdentifyResult,
              residuals: list[TestResidual], regions: list, timings: dict[str, float]
              ) -> DiscoveryState:
        ids = [base.prepared[s.id] for s in campaign.identification_tests()]
        scales = channel_scales(ids)
        p = base.params.copy()
        cost, res = total_cost(ids, p, scales, settings.identify.decimate)
        return cls(campaign, settings, base, residuals, regions, ids, scales, p, cost, timings,
                   cost, effective_samples(res))

    @property
    def model(self) -> ModelDefinition:
        return self.base.model

    @property
    def cascade_free(self) -> dict[str, list[str]]:
        """What the base cascade freed in each stage (the structure test refits the same)."""
        return {st.scenario: list(st.free) for st in self.base.stages}

    def model_free(self, stage: str) -> list[str] | None:
        """What the model as it stands frees in ``stage``: the cascade's set and the
        accepted effects' own parameters (the extension fitted them with the stage);
        ``None`` for a stage the cascade did not fit (``StageScorer``'s default)."""
        if stage not in self.cascade_free:
            return None
        return [*self.cascade_free[stage], *self.extra_free.get(stage, ())]

    @property
    def model_free_by_stage(self) -> dict[str, list[str]]:
        """``model_free`` of every stage the cascade fitted."""
        return {stage: self.model_free(stage) for stage in self.cascade_free}

    def room_for_more(self) -> bool:
        return len(self.accepted) < self.settings.max_effects

    def compensating(self) -> dict[str, float]:
        """Stage parameters that a fit without an effect may have inflated (never the
        ones measured directly), with the typical values a restart resets them to."""
        held = set(self.base.preid.get("held", {}))
        names = [n for _, stage in self.model.cascade for n in stage if n not in held]
        return compensating_parameters(self.p, names, self.model)

    def checkpoint(self) -> dict[str, object]:
        """What the rounds change, copied, so that a round that fails can be undone
        (``restore``): the answer of the rounds before it then stands as they left it."""
        return {name: copy.copy(getattr(self, name)) for name in _ROUND_MUTABLE}

    def restore(self, saved: dict[str, object]) -> None:
        for name, value in saved.items():
            setattr(self, name, value)

    def failed(self, step: str, exc: Exception) -> str:
        """Report a round (or a step of one) that raised: in the log with its traceback and
        in ``failures`` (discovery.md, "What failed"); returns the one-line reason."""
        reason = f"{type(exc).__name__}: {exc}"
        log.error("%s failed (%s); the rounds before it stand", step, reason, exc_info=exc)
        self.failures.append(f"{step}: {reason}; the answer of the rounds before it stands")
        return reason

    def measure_typical_speeds(self, step: str) -> None:
        """Each identification residual's element speeds with what the base fit compensated
        with back at its typical values (``TestResidual.typical_speeds``); none where
        nothing is far from typical. A failure leaves them out and is reported under
        ``step``: the base model's speeds still judge alone."""
        names = set(self.model.element_speeds.values())
        reset = self.compensating()
        if not names or not reset:
            return
        q = self.p.copy()
        for n, v in reset.items():
            q[self.model.param_index[n]] = v
        try:
            by_id = {r.id: r for r in self.residuals}
            for pt, twins in zip(self.ids, twins_of_tests(self.ids, [q[None]] * len(self.ids)),
                                 strict=True):
                if pt.id in by_id:
                    by_id[pt.id].typical_speeds = {
                        n: twins[0][f"internal.{n}"] for n in names
                        if f"internal.{n}" in twins[0]}
        except Exception as exc:  # a judgement aid; it never sinks discovery
            log.warning("typical-value speeds failed: %s: %s", type(exc).__name__, exc)
            self.failures.append(f"{step} (typical-value speeds): {type(exc).__name__}: {exc}")

    def measure_floors(self, step: str) -> None:
        """Each identification test's floor at the current model: the input's noise through
        it beside the sensor's own (``PreparedTest.floor``); if that fails, the floor stays
        the sensor noise alone and the failure is reported under ``step``."""
        try:
            input_noise_floors({pt.id: self.campaign.frame(pt.id) for pt in self.ids},
                               self.ids, self.p, get_system(self.model.name).input_channel,
                               self.settings.identify.seed)
        except Exception as exc:  # the floor refines a judgement; it never sinks discovery
            log.warning("input-noise floor failed: %s: %s", type(exc).__name__, exc)
            self.failures.append(f"{step} (input-noise floor): {type(exc).__name__}: {exc}")

    def refit_cost(self) -> None:
        self.cost, _ = total_cost(self.ids, self.p, self.scales, self.settings.identify.decimate)
