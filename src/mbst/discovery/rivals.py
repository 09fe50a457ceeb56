"""Realities no catalogue effect is: rivals every structure-test winner must beat, never names.

A sensor's own lag. eps-model.md: "a torque sensor's own filter lags by a few ms", and
discovery must not force such a reality into a catalogue effect. A look-alike can take it
up: on a clean realistic rig with white noise and a 3 ms torque lag (bench seed 958,
``--noise-ar1 0``) a column Stribeck rise of 2.7 was named at confidence 0.66, removing
24.3 % of the blocked-column stage; the lag refitted with the stage's parameters removes
26.8 % there, and without the lag on the bench nothing was named in that stage.

A rig that drifts over the campaign. Grease warms, parts wear: the friction levels of the
last test are not the first's. The compact plan with Coulomb levels falling 30 % as the
rig warms (bench ``--friction-drift 0.3``, seed 1) had a position-dependent rack friction
named at 0.30, removing 22.5 % of the free-tie-rods stage: a level that differs from one
test to the next read as a level that differs along the travel.

A family names the channels whose sensors may lag and the parameter of each lag
(``ModelDefinition.sensor_lags``) and the parameter of a drift of its friction levels
over the running order (``ModelDefinition.campaign_drift``), all held at 0 by
identification. In every round the winner's stage refits each like a candidate
(``StageScorer.score``). A rival that removes as much as the winner leaves the winner
unnamed: the stage's misfit is the sensor's or the campaign's, and the unexplained round
describes what is left. A rival that comes near is in the ranking bootstrap like any
other candidate, so the winner's confidence says how often the data prefer it.

A ripple locked to a rotating part (``ModelDefinition.ripple``, a motor's cogging) is
refitted at the order the residual's fast part reads (``rounds/ripple.py``): the rival of
a stick-slip name, and described by the unexplained round.
"""

from __future__ import annotations

from mbst.core.model import EffectSpec, ModelDefinition, Ripple
from mbst.discovery.structure import CandidateScore, StageScorer

LAG = "sensor_lag"
DRIFT = "friction_drift"
RIPPLE = "torque_ripple"
# where the lag's refit starts (× 0.3, 1, 3: ``structure.start_grid``): a sensor filter's
# few milliseconds
TYPICAL_LAG_S = 0.003
# where the drift's refit starts: levels 5 % apart from the first test to the last (it
# goes either way from there: its bounds straddle 0)
TYPICAL_DRIFT = 0.05


def lag_spec(channel: str, parameter: str) -> EffectSpec:
    """The lag of ``channel``'s sensor as a candidate the structure test can refit."""
    return EffectSpec(effect=LAG, component=channel, headline={"lag_s": parameter},
                      free=(parameter,), default_size={parameter: TYPICAL_LAG_S})


def drift_spec(parameter: str) -> EffectSpec:
    """Friction levels that change over the campaign's running order, as a candidate."""
    return EffectSpec(effect=DRIFT, component="campaign", headline={"change": parameter},
                      free=(parameter,), default_size={parameter: TYPICAL_DRIFT})


def ripple_spec(ripple: Ripple) -> EffectSpec:
    """A torque ripple (``ModelDefinition.ripple``) as a candidate: its sine and cosine
    parts, at the order set in the scorer's base vector."""
    return EffectSpec(effect=RIPPLE, component=ripple.component,
                      headline={"sine_nm": ripple.sine, "cosine_nm": ripple.cosine},
                      free=(ripple.sine, ripple.cosine),
                      default_size={ripple.sine: ripple.typical, ripple.cosine: ripple.typical})


def specs(tests: list, model: ModelDefinition) -> list[EffectSpec]:
    """Each lag the family declares for a channel ``tests`` measure, and its drift where
    the tests stand at two places in the running order or more."""
    measured = {ch for pt in tests for ch in pt.measured}
    out = [lag_spec(ch, name) for ch, name in model.sensor_lags.items() if ch in measured]
    if model.campaign_drift is not None and len({pt.place for pt in tests}) > 1:
        out.append(drift_spec(model.campaign_drift[0]))
    return out


def parameters(model: ModelDefinition) -> set[str]:
    """The parameters of every rival the family declares."""
    drift = {model.campaign_drift[0]} if model.campaign_drift is not None else set()
    ripple = {model.ripple.sine, model.ripple.cosine} if model.ripple is not None else set()
    return set(model.sensor_lags.values()) | drift | ripple


def rivals(scorer: StageScorer, model: ModelDefinition, n_eff: float) -> list[CandidateScore]:
    """Every rival of the stage (``specs``), refitted with the stage's parameters."""
    return [scorer.score(spec, n_eff) for spec in specs(scorer.tests, model)]


def matching(best: CandidateScore, found: list[CandidateScore]) -> CandidateScore | None:
    """The rival that removes at least as much of the stage as ``best``, if any."""
    return next((s for s in sorted(found, key=lambda s: -s.relative_gain)
                 if not s.fell_back and s.relative_gain >= best.relative_gain), None)


def reading(rival: CandidateScore) -> str:
    """What a rival's refit says, in the rig's terms."""
    if rival.effect == DRIFT:
        change = rival.headline.get("change", 0.0)
        return (f"friction levels {'rising' if change > 0 else 'falling'} "
                f"{100 * abs(change):.1f} % from the campaign's first test to its last")
    return f"a {1e3 * rival.headline.get('lag_s', 0.0):.1f} ms lag of the {rival.component} sensor"


def declined(best: CandidateScore, rival: CandidateScore) -> dict:
    """The record of a winner a rival matched."""
    whose = "the campaign's" if rival.effect == DRIFT else "the measurement's"
    out = {"key": best.key, "stage": best.stage, "relative_gain": best.relative_gain,
           "rival": rival.key, "rival_relative_gain": rival.relative_gain,
           "rival_size": dict(rival.headline),
           "reason": (f"{best.key} removes {100 * best.relative_gain:.1f} % of the "
                      f"{best.stage} cost, and {reading(rival)} alone "
                      f"{100 * rival.relative_gain:.1f} %: what the stage misses is "
                      f"{whose}, not a catalogue effect (the unexplained round reads what "
                      "is left)")}
    if rival.effect == LAG:
        out.update(sensor=rival.component, lag_ms=1e3 * rival.headline.get("lag_s", 0.0))
    return out
