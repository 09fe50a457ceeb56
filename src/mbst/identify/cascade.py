"""Cascaded grey-box identification and held-out correlation (seed 000, seed 001 Table 1).

1. Preprocess: the exponential filter on every channel (``fitting.prepare_test``).
2. Pre-identify from signal processing: torsion-bar stiffness and column
   friction from the blocked-column regression, the friction budget from the
   half-width of the angle–torque hysteresis loop, the rack-to-angle ratio.
3. Fit scenario by scenario (blocked column → free tie-rods → blocked rack →
   suspended → tires on ground), each stage freeing what its scenario
   isolates and freezing what earlier stages found; identification tests only.
4. Correlate the fitted model on the held-out control tests.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace

import numpy as np
import pandas as pd

from mbst.core.metrics import correlation_row
from mbst.core.model import ModelDefinition
from mbst.identify.fitting import (
    FitProblem,
    FitResult,
    PreparedTest,
    channel_scales,
    prepare_test,
    solve,
    twins_of_tests,
)
from mbst.identify.priors import (
    KnownCheck,
    campaign_priors,
    check_fixed_known,
    check_priors,
    known_notes,
    prior_stages,
)
from mbst.io.campaign import Campaign, CampaignError, data_warnings


@dataclass
class IdentifySettings:
    """Settings of the cascade (config: ``preprocess.tau_s``, ``identify.*``)."""

    tau_s: float = 0.005
    seed: int = 0
    multistart: int = 2
    max_nfev: int = 40
    decimate: int = 2
    progress: bool = False
    # after the cascade, refit everything it found on all identification tests at once
    joint_refinement: bool = False
    # up to this many more random starts while a stage's cost stays far above its noise's
    extra_starts: int = 0
    # name → (value, std of ln θ): a Gaussian prior instead of the weak pull to the start
    prior: dict[str, tuple[float, float]] | None = None


JOINT_STAGE = "joint"
# parameters pre-identification measured directly and the cascade holds (``preid["held"]``)
HELD_STAGE = "measured_points"
# a stage cost above this multiple of what the sensor noise alone leaves is not the optimum
# of a right model: on the compact plan the wrong basin sat at 200x, the right one at 0.7x
FAR_ABOVE_NOISE = 10.0
# a residual variance beyond this multiple of the sensor noise's re-weighs the stated priors
PRIOR_REWEIGH = 1.5


@dataclass
class StageResult:
    scenario: str
    tests: list[str]
    free: list[str]
    cost: float
    n_residuals: int
    starts: list[float]
    wall_s: float
    std_error: dict[str, float]
    correlation: list[list[float]]
    at_bound: dict[str, bool]
    identifiable: dict[str, bool]


@dataclass
class Cascade:
    """What ``run_cascade`` found: the parameters and how each stage got them."""

    params: np.ndarray
    stages: list[StageResult]
    preid: dict
    warnings: list[str]
    prepared: dict[str, PreparedTest]
    # the campaign's priors against their fitted values
    known_checks: list[KnownCheck] = field(default_factory=list)


@dataclass
class IdentifyResult:
    campaign: str
    params: np.ndarray
    stages: list[StageResult]
    preid: dict
    warnings: list[str]
    correlation: pd.DataFrame
    identification_fit: pd.DataFrame
    wall_s: float
    prepared: dict[str, PreparedTest] = field(repr=False, default_factory=dict)
    twins: dict[str, dict[str, np.ndarray]] = field(repr=False, default_factory=dict)
    model: ModelDefinition | None = field(repr=False, default=None)
    # stated known values (priors and fixed ones) against what the data say of them
    known_checks: list[KnownCheck] = field(default_factory=list)

    def summary(self) -> str:
        lines = [f"identified '{self.campaign}' in {self.wall_s:.1f} s "
                 f"({len(self.stages)} stages)"]
        if len(self.correlation):
            for (test, ch), row in self.correlation.set_index(["test", "channel"]).iterrows():
                lines.append(f"  control {test:<22} {ch:<22} FIT {row.fit_percent:6.1f} %")
        for w in self.warnings:
            lines.append(f"  warning: {w}")
        return "\n".join(lines)


# -------------------------------------------------------------------------------------
# the cascade
# -------------------------------------------------------------------------------------
def _flatline_channels(pt: PreparedTest) -> list[str]:
    bad = []
    for ch, y in pt.raw.items():
        if np.std(y) < 1e-12 or np.unique(np.round(y, 12)).size < 3:
            bad.append(ch)
    return bad


def prepare_campaign(campaign: Campaign, tau_s: float
                     ) -> tuple[dict[str, PreparedTest], list[str]]:
    """Every test filtered and its model input derived; flat-lined channels left out
    (with a warning each), as the cascade fits them."""
    warnings = []
    prepared = {s.id: prepare_test(campaign, s, tau_s) for s in campaign.tests}
    for pt in prepared.values():
        warnings += data_warnings(campaign, pt.id)
        for ch in _flatline_channels(pt):
            warnings.append(f"test '{pt.id}': channel '{ch}' is flat-lined; it is not used")
            pt.measured.pop(ch, None)
    return prepared, warnings


def stage_channels(pt: PreparedTest) -> list[str]:
    return [ch for ch in pt.measured]


@dataclass
class _Start:
    """Where the stages start: the known values, the stated priors and pre-identification."""

    p: np.ndarray
    # stated priors (name → value, σ of ln θ), fitted in the stage that isolates them
    priors: dict
    # stated values held as stated (not priors)
    held: set[str]
    preid: dict
    extra_free: dict[str, tuple[str, ...]]
    settings: IdentifySettings


def run_cascade(
    campaign: Campaign,
    settings: IdentifySettings,
    base: np.ndarray | None = None,
    extra_free: dict[str, tuple[str, ...]] | None = None,
    only: set[str] | None = None,
    work_reference: np.ndarray | None = None,
) -> Cascade:
    """Fit the identification tests stage by stage; return the parameter vector and records.

    ``extra_free`` adds parameters (e.g. of an inserted effect) to the stage
    of a scenario: discovery uses it to refit an extended model. ``only``
    restricts the fit to these parameters (and the sensor offsets), the rest
    staying at ``base``: the planner's proof identifies just a plan's unknowns.
    ``work_reference``: the parameters at whose integration step each stage's work
    budget is counted (``work.py``; discovery: the base model, without the effects);
    by default each stage's start.
    """
    id_specs = campaign.identification_tests()
    if not id_specs:
        raise CampaignError("no test has role 'identification': nothing to fit",
                            campaign=campaign.name)
    prepared, warnings = prepare_campaign(campaign, settings.tau_s)
    id_tests = [prepared[s.id] for s in id_specs]
    scales = channel_scales(id_tests)
    model = campaign.model()
    start = _cascade_start(campaign, model, id_tests, settings, base, extra_free, only,
                           warnings)
    p, settings, preid = start.p, start.settings, start.preid
    stated = frozenset(start.priors)

    # what pre-identification measured better than an output-error fit would (the model says)
    fixed: set[str] = {n for n in preid.get("held", {}) if only is None or n in only}
    stages: list[StageResult] = []
    carried: list[str] = []
    rng = np.random.default_rng(settings.seed)
    for scenario, isolates in model.cascade:
        tests = model.stage_tests(scenario, id_tests)
        passed_on = []
        if tests and scenario in model.carry_through:
            passed_on, carried = list(carried), []
        wanted = list(carried) + [n for n in isolates if n not in fixed]
        refit = list(model.refines.get(scenario, ())) if tests else []
        fixed.difference_update(refit)
        wanted += refit
        wanted += list(start.extra_free.get(scenario, ()))
        if not tests:
            # a later scenario may inform these too (the model says which)
            carried = [n for n in wanted if model.carries_over(n)]
            continue
        free, uninformed = _stage_free(model, tests, wanted, fixed | start.held, only)
        carried = uninformed + passed_on
        if not free:
            for pt in tests:
                warnings.append(f"test '{pt.id}' ({scenario}) informs no free parameter")
            continue
        p, stage, notes = _fit_stage(model, scenario, tests, free, p, scales, preid["upper"],
                                     settings, rng, stated=stated, reference=work_reference)
        fixed.update(free)
        stages.append(stage)
        warnings += notes
        _progress(settings, stage)
    if settings.joint_refinement and stages:
        # every parameter the stages found, refitted on every identification test together:
        # a stage sees only its own cut-out, the joint information sees them all
        free = list(dict.fromkeys(n for st in stages for n in st.free))
        p, stage, notes = _fit_stage(model, JOINT_STAGE, id_tests, free, p, scales,
                                     preid["upper"], settings, rng, stated=stated,
                                     reference=work_reference)
        stages.append(stage)
        warnings += notes
        _progress(settings, stage)
    for n in carried:
        if only is None or n in only:
            warnings.append(f"'{n}' could not be identified: no test of a scenario that "
                            "informs it")
    checks = check_priors(campaign, model, p, stages)
    warnings += known_notes(checks)
    return Cascade(p, stages, preid, warnings, prepared, checks)


def _cascade_start(campaign: Campaign, model: ModelDefinition, id_tests: list[PreparedTest],
                   settings: IdentifySettings, base: np.ndarray | None,
                   extra_free: dict[str, tuple[str, ...]] | None, only: set[str] | None,
                   warnings: list[str]) -> _Start:
    """The vector the stages start from: known values over ``base``, then what
    pre-identification measured (warnings appended to ``warnings``)."""
    for k in campaign.known:
        if k not in model.param_index:
            warnings.append(f"known '{k}' is not a parameter of the {model.name} model; "
                            "it is not used")
    p = model.vector_from({k: v for k, v in campaign.known.items() if k in model.param_index},
                          base=base if base is not None else None)
    # a stated prior is fitted in the stage that isolates its component, held by its σ
    priors = {k: v for k, v in campaign_priors(campaign, model).items()
              if only is None or k in only}
    extra_free = dict(extra_free or {})
    for scenario, names in prior_stages(model, priors, id_tests).items():
        extra_free[scenario] = tuple(extra_free.get(scenario, ())) + names
    settings = replace(settings, prior={**(settings.prior or {}), **priors}) if priors else settings
    # a stated value of a parameter the cascade would fit is held as stated
    # (campaign-format.md); ``check_fixed_known`` then asks the data about it
    held = {k for k in campaign.known if k in model.param_index and k not in campaign.priors}
    preid = model.pre_identify(campaign, id_tests, p)
    for k, v in preid["values"].items():
        if (only is not None and k not in only) or k in held:
            continue
        spec = model.spec(k)
        p[model.param_index[k]] = float(np.clip(v, spec.lower, spec.upper))
    warnings += preid["notes"]
    return _Start(p, priors, held, preid, extra_free, settings)


def _stage_free(model: ModelDefinition, tests: list[PreparedTest], wanted: list[str],
                not_free: set[str], only: set[str] | None) -> tuple[list[str], list[str]]:
    """A stage's free parameters, and those of ``wanted`` its tests do not inform.

    ``not_free``: found by earlier stages, measured by pre-identification or stated.
    """
    channels_here = {ch for pt in tests for ch in pt.measured}
    free = []
    uninformed = []
    for n in dict.fromkeys(wanted):
        if n in not_free or (only is not None and n not in only
                             and not n.startswith("offset.")):
            continue
        if n.startswith("offset.") and model.offset_channels[n] not in channels_here:
            continue
        if not model.informed_by(n, tests):
            uninformed.append(n)
            continue
        free.append(n)
    # an offset seen for the first time here, estimated by a later stage's channels
    for n, ch in model.offset_channels.items():
        if ch in channels_here and n not in not_free and n not in free:
            free.append(n)
    return free, uninformed


def _progress(settings: IdentifySettings, stage: StageResult) -> None:
    if settings.progress:
        print(f"  stage {stage.scenario:<16} {len(stage.free)} params, "
              f"{len(stage.tests)} tests, cost {stage.cost:.4g}, {stage.wall_s:.1f} s",
              flush=True)


def _fit_stage(model: ModelDefinition, scenario: str, tests: list[PreparedTest], free: list[str],
               p: np.ndarray, scales: dict[str, float], upper: dict[str, float],
               settings: IdentifySettings, rng: np.random.Generator,
               stated: frozenset[str] = frozenset(), reference: np.ndarray | None = None
               ) -> tuple[np.ndarray, StageResult, list[str]]:
    """Fit ``free`` on ``tests`` from ``p`` (plus random restarts); flag bounds and blind spots.

    ``stated``: parameters whose prior the campaign states (it counts in their std errors).
    ``reference``: where the work budget's step is counted (``run_cascade``).
    """
    t0 = time.perf_counter()
    prob = FitProblem(tests, {pt.id: stage_channels(pt) for pt in tests}, free, p, scales,
                      upper=upper, decimate=settings.decimate, prior=settings.prior,
                      stated=stated)
    # an effect whose step is far finer than the model's before it (a tyre Stribeck dip:
    # 89 sub-steps a sample against 4) would otherwise set its own budget, and one
    # extension ran 24 min in that stage (realistic rig 2704)
    prob.count_work_at(reference)
    p_start = p.copy()

    def random_start() -> np.ndarray:
        return _random_start(model, free, p_start, rng)

    starts = [p.copy()] + [random_start() for _ in range(max(settings.multistart, 1) - 1)]
    # a cost far above what the noise explains is a wrong basin (or a missing effect)
    fr = solve(prob, starts, max_nfev=settings.max_nfev, more_starts=random_start,
               max_more=settings.extra_starts, good_cost=FAR_ABOVE_NOISE * prob.noise_cost())
    if prob.stated.any() and fr.noise_inflation > PRIOR_REWEIGH:
        # the stated priors were weighed against sensor noise; the residual says how much
        # less the data know: weigh them again and refit from where the first fit ended
        prob.inflate_stated(fr.noise_inflation)
        first = fr.starts
        fr = solve(prob, [fr.p], max_nfev=settings.max_nfev)
        fr.starts = first + fr.starts
    p = fr.p
    stage = StageResult(
        scenario=scenario, tests=[pt.id for pt in tests], free=list(free), cost=fr.cost,
        n_residuals=fr.n_residuals, starts=fr.starts, wall_s=time.perf_counter() - t0,
        std_error=fr.std_error, correlation=fr.correlation.round(4).tolist(),
        at_bound=fr.at_bound, identifiable=fr.identifiable,
    )
    return p, stage, _stage_notes(model, scenario, prob, fr, p)


def _random_start(model: ModelDefinition, free: list[str], p_start: np.ndarray,
                  rng: np.random.Generator) -> np.ndarray:
    """``p_start`` with each free parameter but the sensor offsets moved at random: up to
    ×/÷ 2 for a log-scale one, ±30 % (plus 1.5 % of its range) for another."""
    q = p_start.copy()
    for n in free:
        i = model.param_index[n]
        spec = model.param_specs[i]
        if n.startswith("offset."):
            continue
        if spec.log_scale and q[i] > 0:
            q[i] = float(np.clip(q[i] * math.exp(rng.uniform(-0.7, 0.7)),
                                 spec.lower, spec.upper))
        else:
            q[i] = float(np.clip(q[i] + rng.uniform(-0.3, 0.3) *
                                 (abs(q[i]) + 0.05 * (spec.upper - spec.lower)),
                                 spec.lower, spec.upper))
    return q


def _stage_notes(model: ModelDefinition, scenario: str, prob: FitProblem, fr: FitResult,
                 p: np.ndarray) -> list[str]:
    """What the stage's fit says about its parameters: diverged evaluations, parameters
    held at a partner's ratio, on a bound, or not identifiable."""
    notes = []
    if fr.n_diverged:
        notes.append(f"stage {scenario}: {fr.n_diverged} of {fr.n_eval} evaluations simulated "
                     "a diverging trajectory; each counted as a large finite cost the "
                     "optimiser stepped back from")
    tied = {prob.free[j]: prob.free[k] for j, (k, *_) in prob.ties.items()}
    for n in prob.free:
        spec = model.spec(n)
        if n in tied:
            notes.append(
                f"'{n}' held at {tied[n]} × their ratio at the start "
                f"({p[model.param_index[n]]:.4g} {spec.unit}): the {scenario} tests move "
                "them as one body and see only their sum; a value or prior stated for "
                "either sets the split")
        elif fr.at_bound[n]:
            notes.append(
                f"LOUD: '{n}' ended on a bound ({p[model.param_index[n]]:.4g} {spec.unit}, "
                f"bounds [{spec.lower:.3g}, {prob_upper(prob, n):.3g}]) in stage {scenario}: "
                "the base model may lack an effect and be compensating with this parameter"
            )
        elif not fr.identifiable[n]:
            notes.append(
                f"'{n}' is not identifiable from the {scenario} tests given "
                f"(std error {fr.std_error[n]:.3g} for value {p[model.param_index[n]]:.4g})"
            )
    return notes


def prob_upper(prob: FitProblem, name: str) -> float:
    j = prob.free.index(name)
    return float(prob._from_u(prob.ub)[j])


def correlate(
    tests: list[PreparedTest], p: np.ndarray
) -> tuple[pd.DataFrame, dict[str, dict[str, np.ndarray]]]:
    """Per test and channel metrics of the model ``p`` (filtered sim vs filtered data)."""
    rows, twins = [], {}
    for pt, (tw,) in zip(tests, twins_of_tests(tests, [p[None]] * len(tests)), strict=True):
        twins[pt.id] = tw
        for ch, y in pt.measured.items():
            rows.append({"test": pt.id, "channel": ch, **correlation_row(y, tw[ch])})
    cols = ["test", "channel", "fit_percent", "nrmse", "pearson_r", "r2", "max_abs_error"]
    return pd.DataFrame(rows, columns=cols), twins


def identify(campaign: Campaign, settings: IdentifySettings | None = None,
             controls: bool = True, check_known: bool = True) -> IdentifyResult:
    """Run the cascade, check the stated known values and correlate on the control tests.

    ``controls=False`` leaves the control tests alone (discovery's base model: they
    are simulated only once everything is decided). ``check_known=False`` skips the
    refits that test the fixed known values (priors are always checked).
    """
    settings = settings or IdentifySettings()
    t0 = time.perf_counter()
    fit = run_cascade(campaign, settings)
    p, prepared, warnings = fit.params, fit.prepared, fit.warnings
    model = campaign.model()
    fixed = (check_fixed_known(campaign, model, p, fit.stages, prepared, settings.decimate)
             if check_known else [])
    warnings += known_notes(fixed)
    checks = fit.known_checks + fixed
    id_fit, id_twins = correlate([prepared[s.id] for s in campaign.identification_tests()], p)
    if not controls:
        return IdentifyResult(campaign.name, p, fit.stages, fit.preid, warnings,
                              id_fit.iloc[0:0], id_fit, time.perf_counter() - t0, prepared,
                              id_twins, model, checks)
    control_tests = [prepared[s.id] for s in campaign.control_tests()]
    if not control_tests:
        warnings.append("the campaign has no control test: the fit cannot be correlated "
                        "on held-out data")
    corr, twins = correlate(control_tests, p)
    twins.update(id_twins)
    return IdentifyResult(campaign.name, p, fit.stages, fit.preid, warnings, corr, id_fit,
                          time.perf_counter() - t0, prepared, twins, model, checks)
