"""A model definition: parameters, effect catalogue, cascade and simulator of one family.

A model is data plus functions (python-control style), not a class
hierarchy. Identification, discovery and the reports ask the campaign's
family for its ``ModelDefinition`` and never import a particular rig, so a
second system family (the prismatic axis of the EMPS benchmark) runs through
the same code paths as the steering rig.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from mbst.core.candidates import LibraryFactory


@dataclass(frozen=True)
class ParamSpec:
    """One model parameter.

    ``kind`` is ``known`` (from campaign.yaml, fixed), ``base`` (identified in
    the nominal model), ``effect`` (belongs to a catalogue effect), ``fixed``
    (numerical or assumed constant) or ``offset`` (a campaign-wide sensor
    offset).
    """

    name: str
    unit: str
    default: float
    lower: float
    upper: float
    kind: str
    component: str
    log_scale: bool = False


@dataclass(frozen=True)
class EffectSpec:
    """One (effect, component) pair of a catalogue.

    ``headline`` maps the spec's headline parameter names to model parameter
    names; ``free`` lists the parameters a refit frees when the effect is
    inserted; ``default_size`` is a realistic size for the bench;
    ``absorbed_by`` names base parameters that a fit without the effect
    inflates to stand in for it (the element's own Coulomb level carries a
    missing Stribeck rise), which the structure test restarts at their typical
    values for a candidate that shows evidence. ``size_parameters`` are the
    parameters that set the effect's strength from their neutral value (default:
    every free parameter whose realistic size differs from its neutral value);
    ``discovery/resolution.py`` scales them to find the smallest size a
    campaign resolves. Those in ``inverse_size`` make the effect stronger as
    they shrink (a Dahl stiffness: the presliding displacement is F_c/σ).
    ``bounds``: a search range of the spec's own that replaces the family's for these
    parameters (a rival that moves the campaign's stated values within their tolerance).
    ``other_side_size``: for an effect that acts either way from neutral with another
    shape (a power-law exponent below or above 1), the realistic size on the other
    side; the resolution step states a detection limit for each side. ``level``: the
    element's Coulomb level a ratio-type size is relative to (a Stribeck rise F_s/F_c, an
    asymmetry F+/F−); named in a part that moves as one body with another, the finding
    states the body's size (``discovery/lumped.py``). ``damping``: for an exponent on the
    element's speed (a power law b·|v|^a), the damping coefficient whose units the exponent
    changes: a start that moves the exponent moves it too, to keep the damping force over
    the speeds the tests run at (``StageScorer.keep_damping_force``).
    """

    effect: str
    component: str
    headline: dict[str, str]
    free: tuple[str, ...]
    default_size: dict[str, float]
    absorbed_by: tuple[str, ...] = ()
    size_parameters: tuple[str, ...] = ()
    inverse_size: tuple[str, ...] = ()
    other_side_size: dict[str, float] = field(default_factory=dict)
    level: str = ""
    bounds: dict[str, tuple[float, float]] = field(default_factory=dict)
    damping: str = ""

    @property
    def key(self) -> str:
        return f"{self.effect}:{self.component}"


@dataclass(frozen=True)
class Ripple:
    """A torque ripple periodic in a rotating part's angle: ``sine``·sin(N·θ) +
    ``cosine``·cos(N·θ), N the ``order`` parameter (periods per revolution), θ the
    ``angle`` state of ``component``; ``typical`` its refit's starting amplitude."""

    angle: str
    component: str
    sine: str
    cosine: str
    order: str
    typical: float


# simulate_batch(pt, ps) -> one dict per row of ps: sensor channels (unfiltered, offsets
# applied) plus internal signals under "internal.*"
BatchSimulator = Callable[[Any, np.ndarray], list[dict[str, np.ndarray]]]
# prepare_inputs(frame, dt_s, spec, window_s) -> (driving input, its rate, other inputs)
InputPreparer = Callable[[Any, float, Any, float],
                         tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]]
# pre_identify(campaign, prepared identification tests, p) -> {"values", "upper", "notes", ...}
PreIdentifier = Callable[[Any, list, np.ndarray], dict]


@dataclass
class ModelDefinition:
    """Everything identification and discovery need to know about one model family.

    Parameters
    ----------
    name
        The system family (``campaign.yaml: system``).
    param_specs
        Every parameter of the flat vector, effects at their neutral value.
    catalogue
        The (effect, component) pairs discovery may insert.
    cascade
        ``(scenario, parameters it isolates)`` in identification order.
    offset_channels
        Sensor-offset parameter → the channel it shifts.
    output_channels
        Channels the model predicts, in report order.
    simulate_batch
        Simulates one prepared test for many parameter vectors.
    prepare_inputs
        Derives the model's inputs from a test's frame.
    pre_identify
        Starting values and bounds from signal processing: a dict with
        ``values`` (starts), ``upper`` (bounds), ``notes`` and optionally
        ``held`` (name → std error: values measured directly, which the
        cascade keeps instead of fitting).
    carries_over
        Whether a parameter of a stage with no test is handed to the next stage.
    search_lower
        Lower bounds that discovery uses instead of the spec's (e.g. to keep a
        Stribeck velocity above the sample resolution).
    component_scenarios
        Where each component acts: the earliest of these scenarios with
        identification tests is the cascade stage that isolates it.
    hysteresis
        ``(x channel or "input", y channel, x label, y label, x scale)`` of the
        loop plot engineers read (steering angle vs torque for EPS).
    evidence_methods
        Which regressions run beside the structure test (``sparse``, ``neural``).
    candidate_library
        The family's one candidate library (``core.candidates``), built from its
        internal states: the sparse regression ranks the catalogue with it and the
        neural residual is read back with it. A family without one runs neither.
    discovery_rounds
        The discovery rounds this family runs, in order (``discovery.pipeline.ROUNDS``):
        ``structure`` (the catalogue's output-error test), ``stick_slip`` (the
        phase-free test for Stribeck friction), ``equation_error`` (for families with
        an inverse model, ``equation_error`` below), ``resolution``.
    benchmark
        ``benchmark(base_result, extended_params, learner) -> dict`` of
        family-specific figures of merit (EMPS: the published error measures),
        written as ``benchmark.json`` beside ``discovery.json``. ``learner``
        (``discovery.evidence.hybrid.neural_correction``, or ``None``) trains a
        neural residual on identification runs for a physics + neural row.
    stages_of
        The cascade stages a prepared test serves (default: its scenario's;
        the EPS rig sends powered tests to its assist stages, and engine-off
        tests of the same cut-outs there too, as seed 001 Table 1 does).
    informed_by
        Whether a stage's tests inform a parameter at all (default: yes); a
        parameter they do not inform is handed on to the next stage, e.g. the
        assist curve of a mode no test of the stage runs in.
    refines
        Parameters a stage refits although an earlier stage fixed them (seed
        001 Table 1: the dry friction with the assist curve, the viscous
        terms with the active damping).
    carry_through
        Stages that fit only what they isolate and hand parameters carried from
        a skipped stage on to the next one (the EPS rig's ``suspended``: free
        wheels load the tie-rods too lightly to pin their stiffness).
    equation_error
        ``equation_error(prepared_test) -> residual(p)`` (or ``None``): the
        inverse model's residual of a test as a function of the parameters
        (EMPS: the authors' IDIM force error on the moving samples), for rigs
        whose output-error fit has too high a floor to see part of the model;
        discovery then runs an equation-error round.
    simulate_tests
        ``simulate_tests(prepared_tests, ps_per_test) -> rows per test``: several
        tests at once, each with its own parameter rows, the same numbers as
        ``simulate_batch`` test by test but spread over the cores as one set of
        simulations (``mbst.core.threads``). ``None``: test by test.
    row_steps
        ``row_steps(prepared_test, ps) -> int array``: the integration steps each
        row of ``ps`` needs on the test, where ``simulate_batch`` runs a whole batch
        at the finest of its rows (the EPS rig's sub-steps). A row then gives the
        same numbers alone as in a batch only when its count equals the batch's,
        and the fitter reuses a simulation only then. ``None``: rows are
        independent (a fixed step).
    element_speeds
        Friction element (component) → the base model's internal signal of its
        speed (``TestResidual.states``). Discovery compares them to tell when
        two components move as one body in a stage's tests, so that an effect
        fitted in either explains the data alike and the finding says so.
    coulomb_level
        ``coulomb_level(p, component, speed) -> float``: the Coulomb level of a
        friction element at ``speed`` in its own coordinate, with its direction
        (asymmetry) and low-speed rise (Stribeck) as the family's law has them; the
        finding of an effect named in one part of a body states the body's size from
        it (``discovery/lumped.py``). ``None``: no such statement.
    ties
        Parameter → (partner, ratio): two levels the family's tests see only as their sum
        (a motor and a rack geared as one body), and their typical ratio. A fit that
        frees both and is told neither holds the first at partner × their ratio at its
        start (the typical one, where the start has none) and fits the sum; a value or
        prior the campaign states for either sets the split instead.
    sensor_lags
        Measured channel → the parameter of its sensor's own first-order lag (s), held at
        0 by identification and never a finding: the structure rounds refit it as a rival
        of each winner, and a misfit the lag explains as well is not named
        (``discovery/rivals.py``).
    campaign_drift
        (drift parameter, the levels it scales): the rig's friction levels as a test sees
        them at its place in the campaign's running order (−½ first … ½ last), each
        level × (1 + drift · place). Held at 0 by identification and never a catalogue
        name: the structure rounds refit it as a rival of each winner (the rig warming
        up, ``discovery/rivals.py``); ``None``: the family declares no such drift.
    ripple
        A torque ripple locked to a rotating part's angle (a motor's cogging,
        ``Ripple``), held at 0 by identification and never a catalogue name: the
        unexplained round refits it at the order the residual's fast part repeats with
        (``discovery/rounds/ripple.py``); ``None``: the family declares none.
    stated_tolerance
        How far (relative) a known value the campaign states as fixed may be off the rig's
        (CAD inertias, datasheet ratios: eps-model.md, "a few to 15 % off"): the structure
        rounds refit the stated values within it as a rival of each winner, and a misfit
        they explain as well is not named (``discovery/rivals.py``). 0: stated values
        are exact (a controller's gains), no such rival.
    stated_tolerance_by_name
        The stated values known better than ``stated_tolerance`` (name → relative
        tolerance): geometry from a drawing, a gear's tooth ratio.
    specialise
        ``specialise(model, campaign) -> ModelDefinition`` adds the parameters
        a particular campaign brings (one assist curve per ``assist_mode``, one
        active damping per vehicle speed); ``None`` if the family has none.
    """

    name: str
    param_specs: tuple[ParamSpec, ...]
    catalogue: tuple[EffectSpec, ...]
    cascade: tuple[tuple[str, tuple[str, ...]], ...]
    offset_channels: dict[str, str]
    output_channels: tuple[str, ...]
    simulate_batch: BatchSimulator
    prepare_inputs: InputPreparer
    pre_identify: PreIdentifier
    carries_over: Callable[[str], bool] = lambda name: not name.startswith("offset.")
    search_lower: dict[str, float] = field(default_factory=dict)
    component_scenarios: dict[str, tuple[str, ...]] = field(default_factory=dict)
    hysteresis: tuple[str, str, str, str, float] | None = None
    evidence_methods: tuple[str, ...] = ()
    candidate_library: LibraryFactory | None = None
    discovery_rounds: tuple[str, ...] = ("structure", "resolution")
    benchmark: Callable[..., dict] | None = None
    stages_of: Callable[[Any], tuple[str, ...]] = lambda pt: (pt.scenario,)
    informed_by: Callable[[str, list], bool] = lambda name, tests: True
    specialise: Callable[[ModelDefinition, Any], ModelDefinition] | None = None
    refines: dict[str, tuple[str, ...]] = field(default_factory=dict)
    carry_through: tuple[str, ...] = ()
    equation_error: Callable[[Any], Callable[[np.ndarray], np.ndarray] | None] | None = None
    element_speeds: dict[str, str] = field(default_factory=dict)
    coulomb_level: Callable[[np.ndarray, str, float], float] | None = None
    simulate_tests: Callable[[list, list[np.ndarray]], list[list[dict]]] | None = None
    row_steps: Callable[[Any, np.ndarray], np.ndarray] | None = None
    ties: dict[str, tuple[str, float]] = field(default_factory=dict)
    sensor_lags: dict[str, str] = field(default_factory=dict)
    campaign_drift: tuple[str, tuple[str, ...]] | None = None
    ripple: Ripple | None = None
    stated_tolerance: float = 0.0
    stated_tolerance_by_name: dict[str, float] = field(default_factory=dict)
    param_index: dict[str, int] = field(init=False)
    effects: dict[str, EffectSpec] = field(init=False)

    def __post_init__(self) -> None:
        self.param_index = {s.name: i for i, s in enumerate(self.param_specs)}
        self.effects = {e.key: e for e in self.catalogue}
        if self.evidence_methods and self.candidate_library is None:
            raise ValueError(f"family '{self.name}' declares evidence methods "
                             f"{self.evidence_methods} but no candidate_library to read them with")

    @property
    def n_params(self) -> int:
        return len(self.param_specs)

    def spec(self, name: str) -> ParamSpec:
        return self.param_specs[self.param_index[name]]

    def size_parameters(self, effect: EffectSpec) -> tuple[str, ...]:
        """Parameters that set the strength of ``effect`` (``EffectSpec.size_parameters``,
        else every free one whose realistic size differs from its neutral value)."""
        if effect.size_parameters:
            return effect.size_parameters
        return tuple(n for n in effect.free
                     if effect.default_size[n] != self.spec(n).default)

    def default_vector(self) -> np.ndarray:
        return np.array([s.default for s in self.param_specs], dtype=np.float64)

    def vector_from(self, values: dict[str, float] | None = None,
                    base: np.ndarray | None = None) -> np.ndarray:
        """A parameter vector from defaults (or ``base``) updated with named ``values``."""
        p = self.default_vector() if base is None else np.array(base, dtype=np.float64, copy=True)
        for name, v in (values or {}).items():
            if name not in self.param_index:
                raise KeyError(f"unknown {self.name} model parameter '{name}'")
            p[self.param_index[name]] = float(v)
        return p

    def at_place(self, ps: np.ndarray, place: float) -> np.ndarray:
        """Parameter rows ``ps`` as a test at ``place`` in the running order runs them
        (``campaign_drift``); ``ps`` itself where no row drifts."""
        if self.campaign_drift is None or place == 0.0:
            return ps
        drift, levels = self.campaign_drift
        ps = np.atleast_2d(ps)
        d = ps[:, self.param_index[drift]]
        if not np.any(d):
            return ps
        out = np.array(ps, dtype=np.float64, copy=True)
        idx = [self.param_index[n] for n in levels]
        out[:, idx] *= (1.0 + d * place)[:, None]
        return out

    def as_dict(self, p: np.ndarray, kinds: tuple[str, ...] | None = None) -> dict[str, float]:
        return {s.name: float(p[i]) for i, s in enumerate(self.param_specs)
                if kinds is None or s.kind in kinds}

    def stage_free(self) -> dict[str, tuple[str, ...]]:
        return dict(self.cascade)

    def stage_tests(self, stage: str, tests: list) -> list:
        """The tests of ``tests`` that serve cascade stage ``stage``."""
        return [pt for pt in tests if stage in self.stages_of(pt)]

    def for_campaign(self, campaign: Any) -> ModelDefinition:
        """This definition with the parameters ``campaign`` brings (itself if none)."""
        return self if self.specialise is None else self.specialise(self, campaign)
