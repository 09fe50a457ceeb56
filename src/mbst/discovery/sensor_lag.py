"""A sensor's own lag: the rival every structure-test winner must beat, never a name.

eps-model.md: "a torque sensor's own filter lags by a few ms", and discovery must not force
such a reality into a catalogue effect. A look-alike can take it up: on a clean realistic
rig with white noise and a 3 ms torque lag (bench seed 958, ``--noise-ar1 0``) a column
Stribeck rise of 2.7 was named at confidence 0.66, removing 24.3 % of the blocked-column
stage; the lag refitted with the stage's parameters removes 26.8 % there, and without the
lag on the bench nothing was named in that stage.

A family names the channels whose sensors may lag and the parameter of each lag
(``ModelDefinition.sensor_lags``, held at 0 by identification). In every round the
winner's stage refits each such lag like a candidate (``StageScorer.score``). A lag that
removes as much as the winner leaves the winner unnamed: the stage's misfit is the
sensor's, and the unexplained round describes what is left. A lag that comes near is a
rival in the ranking bootstrap like any other, so the winner's confidence says how often
the data prefer it to the sensor.
"""

from __future__ import annotations

from mbst.core.model import EffectSpec, ModelDefinition
from mbst.discovery.structure import CandidateScore, StageScorer

EFFECT = "sensor_lag"
# where the lag's refit starts (× 0.3, 1, 3: ``structure.start_grid``): a sensor filter's
# few milliseconds
TYPICAL_LAG_S = 0.003


def lag_spec(channel: str, parameter: str) -> EffectSpec:
    """The lag of ``channel``'s sensor as a candidate the structure test can refit."""
    return EffectSpec(effect=EFFECT, component=channel, headline={"lag_s": parameter},
                      free=(parameter,), default_size={parameter: TYPICAL_LAG_S})


def rivals(scorer: StageScorer, model: ModelDefinition, n_eff: float) -> list[CandidateScore]:
    """Each lag the family declares for a channel the stage's tests measure, refitted with
    the stage's parameters."""
    measured = {ch for pt in scorer.tests for ch in pt.measured}
    return [scorer.score(lag_spec(ch, name), n_eff)
            for ch, name in model.sensor_lags.items() if ch in measured]


def matching(best: CandidateScore, lags: list[CandidateScore]) -> CandidateScore | None:
    """The lag that removes at least as much of the stage as ``best``, if any."""
    return next((s for s in sorted(lags, key=lambda s: -s.relative_gain)
                 if not s.fell_back and s.relative_gain >= best.relative_gain), None)


def declined(best: CandidateScore, lag: CandidateScore) -> dict:
    """The record of a winner a sensor's lag matched."""
    ms = 1e3 * lag.headline.get("lag_s", 0.0)
    return {"key": best.key, "stage": best.stage, "relative_gain": best.relative_gain,
            "sensor": lag.component, "lag_ms": ms, "lag_relative_gain": lag.relative_gain,
            "reason": (f"{best.key} removes {100 * best.relative_gain:.1f} % of the "
                       f"{best.stage} cost, and a {ms:.1f} ms lag of the {lag.component} "
                       f"sensor alone {100 * lag.relative_gain:.1f} %: what the stage "
                       "misses is the measurement's, not a catalogue effect (the "
                       "unexplained round reads what is left)")}
