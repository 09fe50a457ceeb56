"""The planning config (``PLAN.yaml``, format ``mbst-plan/1``) and its validation.

Every problem is one line naming the file and the key, e.g.
``config/plan.yaml, key 'sensors[3].name': unknown sensor 'rack_angle'``.
See ``config/plan.yaml`` for a commented example and docs/plan.md for the
meaning of each key.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml

from mbst.plan.inputs import INPUT_KINDS
from mbst.plan.sensors import INPUT_SENSOR, SENSORS
from mbst.systems.eps.channels import SCENARIOS
from mbst.systems.eps.params import PARAM_INDEX, PARAM_SPECS, vector_from

FORMAT = "mbst-plan/1"
TOP_KEYS = ("format", "name", "seed", "known", "sample_rate_hz", "analysis_rate_hz",
            "model_error_fraction", "unknowns",
            "sweep", "sensors", "scenarios", "inputs", "selection", "naive", "effects",
            "figures", "proof")


class PlanError(ValueError):
    """A bad planning config, as one line naming the file and the key."""

    def __init__(self, path: str | Path, key: str, message: str) -> None:
        self.path, self.key = str(path), key
        super().__init__(f"{path}, key '{key}': {message}" if key else f"{path}: {message}")


@dataclass(frozen=True)
class Unknown:
    """An unknown parameter: its range (SI units) and the value simulated at the centre."""

    name: str
    low: float
    high: float
    nominal: float
    # a stated prior's σ/value (``known: {value, sigma}``); None: the range is the prior
    stated_std_log: float | None = None

    @property
    def prior_std_log(self) -> float:
        """Std of ln θ: the stated prior's, else a uniform prior in ln θ over the range."""
        if self.stated_std_log is not None:
            return self.stated_std_log
        return (math.log(self.high) - math.log(self.low)) / math.sqrt(12.0)


def stated_prior(name: str, value: float, sigma: float) -> Unknown:
    """A known value given as a prior ``{value, sigma}``: an unknown the prior informs.

    Its sweep range is the uniform one with the prior's σ in ln θ (±√3 σ).
    """
    s = sigma / value
    return Unknown(name, value * math.exp(-math.sqrt(3.0) * s),
                   value * math.exp(math.sqrt(3.0) * s), value, s)


@dataclass(frozen=True)
class SensorCandidate:
    name: str
    noise: float
    cost: float
    mandatory: bool


@dataclass(frozen=True)
class ScenarioCandidate:
    """A cut-out with its motor mode; ``cost`` is paid once (setting it up)."""

    id: str
    scenario: str
    motor: str
    cost: float
    amplitude_deg: float


@dataclass(frozen=True)
class InputCandidate:
    """An input shape; ``cost`` is paid per test that uses it."""

    id: str
    kind: str
    amplitude_scale: float
    cost: float
    options: dict = field(hash=False, compare=False)


@dataclass
class PlanConfig:
    """Everything ``mbst plan`` reads from PLAN.yaml, validated."""

    path: str
    name: str
    seed: int
    known: dict[str, float]
    sample_rate_hz: float
    analysis_rate_hz: float
    model_error_fraction: float
    unknowns: list[Unknown]
    sweep_points: int
    fd_step: float
    sensors: list[SensorCandidate]
    scenarios: list[ScenarioCandidate]
    inputs: list[InputCandidate]
    budget: float
    target_relative_std: float
    max_tests_per_scenario: int
    controls: bool
    naive_scenario: str
    naive_input: str
    naive_sensors: int
    effects_enabled: bool
    effects_default_sensors: list[str]
    effects_min_evidence: float
    effects_min_unexplained: float
    effects_list: list[str] | None
    fig_scenario: str
    fig_inputs: tuple[str, str]
    proof_enabled: bool
    proof_seed: int
    proof_effects: list[str]
    proof_multistart: int = 2
    proof_joint_refinement: bool = True
    proof_range_prior: bool = True
    # noisy-angle draws per cell for the input-reconstruction error (0: the input is exact)
    input_draws: int = 4

    @property
    def unknown_names(self) -> list[str]:
        return [u.name for u in self.unknowns]

    def nominal_vector(self) -> np.ndarray:
        """Model vector at the centre of the ranges (other parameters at their defaults)."""
        return vector_from({**self.known, **{u.name: u.nominal for u in self.unknowns}})

    def stated_priors(self) -> dict[str, float]:
        """Sigma (SI) of each known value the config gives as a prior ``{value, sigma}``."""
        return {u.name: u.nominal * u.stated_std_log for u in self.unknowns
                if u.stated_std_log is not None}

    def campaign_known(self, defaults: dict[str, float]) -> dict[str, float]:
        """The ``known`` values a planned campaign states (``defaults`` where none is given)."""
        priors = self.stated_priors()
        base = {k: v for k, v in defaults.items() if k not in priors} if not self.known else {}
        return {**base, **self.known, **{u.name: u.nominal for u in self.unknowns
                                         if u.name in priors}}

    def sensor(self, name: str) -> SensorCandidate:
        return next(s for s in self.sensors if s.name == name)

    def scenario(self, sid: str) -> ScenarioCandidate:
        return next(s for s in self.scenarios if s.id == sid)

    def input(self, iid: str) -> InputCandidate:
        return next(i for i in self.inputs if i.id == iid)


# ------------------------------------------------------------------------------------
# validation helpers
# ------------------------------------------------------------------------------------
class _Reader:
    def __init__(self, path: str) -> None:
        self.path = path

    def fail(self, key: str, message: str) -> PlanError:
        return PlanError(self.path, key, message)

    def mapping(self, obj, key: str, allowed: tuple[str, ...] | None = None) -> dict:
        if not isinstance(obj, dict):
            raise self.fail(key, f"expected a mapping, got {type(obj).__name__}")
        if allowed is not None:
            for k in obj:
                if k not in allowed:
                    raise self.fail(f"{key}.{k}" if key else str(k),
                                    f"unknown key (allowed: {', '.join(allowed)})")
        return obj

    def number(self, obj, key: str, lo: float | None = None, hi: float | None = None,
               strict_lo: bool = False) -> float:
        if isinstance(obj, bool) or not isinstance(obj, (int, float)) or not math.isfinite(obj):
            raise self.fail(key, f"expected a finite number, got {obj!r}")
        v = float(obj)
        if lo is not None and (v < lo or (strict_lo and v == lo)):
            raise self.fail(key, f"must be {'>' if strict_lo else '≥'} {lo:g}, got {v:g}")
        if hi is not None and v > hi:
            raise self.fail(key, f"must be ≤ {hi:g}, got {v:g}")
        return v

    def integer(self, obj, key: str, lo: int) -> int:
        if isinstance(obj, bool) or not isinstance(obj, int) or obj < lo:
            raise self.fail(key, f"expected an integer ≥ {lo}, got {obj!r}")
        return int(obj)

    def text(self, obj, key: str, choices: tuple[str, ...] | list[str] | None = None) -> str:
        if not isinstance(obj, str) or not obj:
            raise self.fail(key, f"expected a non-empty string, got {obj!r}")
        if choices is not None and obj not in choices:
            raise self.fail(key, f"'{obj}' is not one of: {', '.join(choices)}")
        return obj

    def seq(self, obj, key: str, min_len: int = 1) -> list:
        if not isinstance(obj, list) or len(obj) < min_len:
            raise self.fail(key, f"expected a list of at least {min_len} entries")
        return obj


def _known(r: _Reader, doc) -> tuple[dict[str, float], list[Unknown]]:
    """``known:``: fixed values, and the priors ``{value, sigma}`` (unknowns they inform)."""
    known, priors = {}, []
    for k, v in r.mapping(doc, "known").items():
        if k not in PARAM_INDEX or PARAM_SPECS[PARAM_INDEX[k]].kind != "known":
            raise r.fail(f"known.{k}", "not an a-priori parameter of the EPS model")
        if isinstance(v, dict):
            entry = r.mapping(v, f"known.{k}", ("value", "sigma"))
            value = r.number(entry.get("value"), f"known.{k}.value", lo=0.0, strict_lo=True)
            sigma = r.number(entry.get("sigma"), f"known.{k}.sigma", lo=0.0, strict_lo=True)
            priors.append(stated_prior(k, value, sigma))
        else:
            known[k] = r.number(v, f"known.{k}", lo=0.0, strict_lo=True)
    return known, priors


def _unknowns(r: _Reader, doc) -> list[Unknown]:
    doc = r.mapping(doc, "unknowns")
    if not doc:
        raise r.fail("unknowns", "no unknown parameter given")
    out = []
    for name, entry in doc.items():
        key = f"unknowns.{name}"
        if name not in PARAM_INDEX:
            raise r.fail(key, f"unknown EPS model parameter '{name}' (names: docs/eps-model.md, "
                         "src/mbst/systems/eps_params.py)")
        spec = PARAM_SPECS[PARAM_INDEX[name]]
        if spec.kind in ("offset", "fixed"):
            raise r.fail(key, f"'{name}' is a {spec.kind} parameter; sensor offsets are "
                         "estimated anyway, numerical constants are not identified")
        entry = r.mapping(entry, key, ("range", "nominal"))
        rng = entry.get("range")
        if not isinstance(rng, list) or len(rng) != 2:
            raise r.fail(f"{key}.range", "expected [low, high]")
        lo = r.number(rng[0], f"{key}.range", lo=0.0, strict_lo=True)
        hi = r.number(rng[1], f"{key}.range")
        if not hi > lo:
            raise r.fail(f"{key}.range", f"high {hi:g} must exceed low {lo:g}")
        nominal = math.sqrt(lo * hi)  # centre in log: ranges span factors, not offsets
        if "nominal" in entry:
            nominal = r.number(entry["nominal"], f"{key}.nominal")
            if not lo <= nominal <= hi:
                raise r.fail(f"{key}.nominal", f"{nominal:g} is outside the range [{lo:g}, {hi:g}]")
        out.append(Unknown(name, lo, hi, nominal))
    return out


def _sensors(r: _Reader, doc) -> list[SensorCandidate]:
    out, seen = [], set()
    for k, entry in enumerate(r.seq(doc, "sensors")):
        key = f"sensors[{k}]"
        entry = r.mapping(entry, key, ("name", "noise", "cost", "mandatory"))
        name = r.text(entry.get("name"), f"{key}.name")
        if name not in SENSORS:
            raise r.fail(f"{key}.name", f"unknown sensor '{name}' (known: {', '.join(SENSORS)})")
        if name in seen:
            raise r.fail(f"{key}.name", f"sensor '{name}' is listed twice")
        seen.add(name)
        noise = r.number(entry.get("noise", SENSORS[name].default_noise), f"{key}.noise",
                         lo=0.0, strict_lo=True)
        cost = r.number(entry.get("cost"), f"{key}.cost", lo=0.0)
        mandatory = entry.get("mandatory", name == INPUT_SENSOR)
        if not isinstance(mandatory, bool):
            raise r.fail(f"{key}.mandatory", "expected true or false")
        out.append(SensorCandidate(name, noise, cost, mandatory or name == INPUT_SENSOR))
    if INPUT_SENSOR not in seen:
        raise r.fail("sensors", f"'{INPUT_SENSOR}' must be listed: it is the model's input")
    return out


def _scenarios(r: _Reader, doc) -> list[ScenarioCandidate]:
    out, seen = [], set()
    for k, entry in enumerate(r.seq(doc, "scenarios")):
        key = f"scenarios[{k}]"
        entry = r.mapping(entry, key, ("id", "scenario", "motor", "cost", "amplitude_deg"))
        scen = r.text(entry.get("scenario"), f"{key}.scenario", SCENARIOS)
        sid = r.text(entry.get("id", scen), f"{key}.id")
        if sid in seen:
            raise r.fail(f"{key}.id", f"scenario id '{sid}' is listed twice")
        seen.add(sid)
        motor = r.text(entry.get("motor", "passive"), f"{key}.motor", ("passive", "assist"))
        cost = r.number(entry.get("cost"), f"{key}.cost", lo=0.0)
        amp = r.number(entry.get("amplitude_deg"), f"{key}.amplitude_deg", lo=0.0,
                       strict_lo=True, hi=720.0)
        out.append(ScenarioCandidate(sid, scen, motor, cost, amp))
    return out


def _inputs(r: _Reader, doc) -> list[InputCandidate]:
    out, seen = [], set()
    for k, entry in enumerate(r.seq(doc, "inputs")):
        key = f"inputs[{k}]"
        entry = r.mapping(entry, key)
        kind = r.text(entry.get("kind"), f"{key}.kind", tuple(INPUT_KINDS))
        iid = r.text(entry.get("id"), f"{key}.id")
        if iid in seen:
            raise r.fail(f"{key}.id", f"input id '{iid}' is listed twice")
        seen.add(iid)
        allowed = ("id", "kind", "amplitude_scale", "cost", "cycles", "hold_s", "count",
                   "spacing_s") + INPUT_KINDS[kind]
        r.mapping(entry, key, allowed)
        opts = {}
        for req in INPUT_KINDS[kind]:
            opts[req] = r.number(entry.get(req), f"{key}.{req}", lo=0.0, strict_lo=True)
        for opt in ("cycles", "count"):
            if opt in entry:
                opts[opt] = r.integer(entry[opt], f"{key}.{opt}", 1)
        for opt in ("hold_s", "spacing_s"):
            if opt in entry:
                opts[opt] = r.number(entry[opt], f"{key}.{opt}", lo=0.0)
        if kind == "sweep" and not opts["f1_hz"] > opts["f0_hz"]:
            raise r.fail(f"{key}.f1_hz", "the sweep must end above f0_hz")
        scale = r.number(entry.get("amplitude_scale", 1.0), f"{key}.amplitude_scale", lo=0.0,
                         strict_lo=True, hi=2.0)
        cost = r.number(entry.get("cost"), f"{key}.cost", lo=0.0)
        out.append(InputCandidate(iid, kind, scale, cost, opts))
    return out


def parse_plan(doc, path: str | Path = "PLAN.yaml") -> PlanConfig:
    """Validate a loaded planning document; raise ``PlanError`` naming the key."""
    r = _Reader(str(path))
    doc = r.mapping(doc, "", TOP_KEYS)
    if doc.get("format", FORMAT) != FORMAT:
        raise r.fail("format", f"expected '{FORMAT}', got {doc.get('format')!r}")
    known, priors = _known(r, doc.get("known", {}))
    unknowns = _unknowns(r, doc.get("unknowns")) + priors
    for u in unknowns:
        if u.name in known:
            raise r.fail(f"unknowns.{u.name}", "is also listed under 'known'")
    sensors = _sensors(r, doc.get("sensors"))
    scenarios = _scenarios(r, doc.get("scenarios"))
    inputs = _inputs(r, doc.get("inputs"))
    sections = {
        "sweep": r.mapping(doc.get("sweep", {}), "sweep", ("points", "fd_step", "input_draws")),
        "selection": r.mapping(doc.get("selection", {}), "selection",
                               ("budget", "target_relative_std", "max_tests_per_scenario",
                                "controls")),
        "naive": r.mapping(doc.get("naive", {}), "naive", ("scenario", "input", "sensors")),
        "effects": r.mapping(doc.get("effects", {}), "effects",
                             ("enabled", "default_sensors", "min_evidence", "min_unexplained",
                              "only")),
        "figures": r.mapping(doc.get("figures", {}), "figures", ("frequency_comparison",)),
        "proof": r.mapping(doc.get("proof", {}), "proof",
                           ("enabled", "seed", "effects", "multistart", "joint_refinement",
                            "range_prior")),
    }
    naive, eff = sections["naive"], sections["effects"]
    scen_ids = [s.id for s in scenarios]
    input_ids = [i.id for i in inputs]
    sines = sorted((i for i in inputs if i.kind == "sine"), key=lambda i: i.options["frequency_hz"])
    naive_scen = r.text(naive.get("scenario", scen_ids[-1]), "naive.scenario", scen_ids)
    default_slow = sines[0].id if sines else input_ids[0]
    naive_input = r.text(naive.get("input", default_slow), "naive.input", input_ids)
    eff_sensors, only = _effect_choice(r, eff, [s.name for s in sensors])
    fig_scen, fig_in = _frequency_figure(r, sections["figures"], scen_ids, input_ids, sines)
    proof_effects = _proof_effects(r, sections["proof"])
    bools = _switches(r, sections)
    n_selectable = sum(not s.mandatory for s in sensors)
    return PlanConfig(
        path=str(path),
        name=r.text(doc.get("name", Path(path).stem), "name"),
        known={k: float(v) for k, v in known.items()},
        unknowns=unknowns,
        sensors=sensors,
        scenarios=scenarios,
        inputs=inputs,
        controls=bools["selection.controls"],
        naive_scenario=naive_scen,
        naive_input=naive_input,
        naive_sensors=r.integer(naive.get("sensors", min(3, n_selectable)), "naive.sensors", 0),
        effects_enabled=bools["effects.enabled"],
        effects_default_sensors=list(eff_sensors),
        effects_list=list(only) if only is not None else None,
        fig_scenario=fig_scen,
        fig_inputs=(fig_in[0], fig_in[1]),
        proof_enabled=bools["proof.enabled"],
        proof_effects=list(proof_effects),
        proof_joint_refinement=bools["proof.joint_refinement"],
        proof_range_prior=bools["proof.range_prior"],
        **_numbers(r, doc, sections),
    )


def _effect_choice(r: _Reader, eff: dict, sensor_names: list[str]) -> tuple[list, list | None]:
    """``effects.default_sensors`` and ``effects.only``, each checked against what exists."""
    default_eff = [s for s in ("steering_angle_rad", "steering_torque_nm", "rack_position_m",
                               "tie_rod_force_left_n") if s in sensor_names]
    eff_sensors = r.seq(eff.get("default_sensors", default_eff), "effects.default_sensors")
    for k, s in enumerate(eff_sensors):
        r.text(s, f"effects.default_sensors[{k}]", sensor_names)
    only = eff.get("only")
    if only is not None:
        from mbst.systems.eps.params import EFFECTS
        for k, e in enumerate(r.seq(only, "effects.only")):
            r.text(e, f"effects.only[{k}]", sorted(EFFECTS))
    return eff_sensors, only


def _frequency_figure(r: _Reader, fig: dict, scen_ids: list[str], input_ids: list[str],
                      sines: list) -> tuple[str, list]:
    """``figures.frequency_comparison``: its scenario and its two inputs."""
    fc = r.mapping(fig.get("frequency_comparison", {}), "figures.frequency_comparison",
                   ("scenario", "inputs"))
    default_fs = "free_tie_rods" if "free_tie_rods" in scen_ids else scen_ids[0]
    fig_scen = r.text(fc.get("scenario", default_fs), "figures.frequency_comparison.scenario",
                      scen_ids)
    fig_in = fc.get("inputs", [sines[0].id, sines[-1].id] if len(sines) >= 2 else input_ids[:2])
    if not isinstance(fig_in, list) or len(fig_in) != 2:
        raise r.fail("figures.frequency_comparison.inputs", "expected two input ids")
    for k, i in enumerate(fig_in):
        r.text(i, f"figures.frequency_comparison.inputs[{k}]", input_ids)
    return fig_scen, fig_in


def _proof_effects(r: _Reader, proof: dict) -> list:
    proof_effects = r.seq(proof.get("effects", []), "proof.effects", min_len=0)
    from mbst.systems.eps.bench import parse_effect

    for k, e in enumerate(proof_effects):
        try:
            parse_effect(r.text(e, f"proof.effects[{k}]"))
        except (KeyError, ValueError) as exc:
            raise r.fail(f"proof.effects[{k}]", str(exc).strip("'\"")) from None
    return proof_effects


def _switches(r: _Reader, sections: dict[str, dict]) -> dict[str, bool]:
    """The yes/no keys, each true unless set."""
    bools = {}
    for key in ("selection.controls", "effects.enabled", "proof.enabled",
                "proof.joint_refinement", "proof.range_prior"):
        section, name = key.split(".")
        v = sections[section].get(name)
        v = True if v is None else v
        if not isinstance(v, bool):
            raise r.fail(key, "expected true or false")
        bools[key] = v
    return bools


def _numbers(r: _Reader, doc: dict, sections: dict[str, dict]) -> dict:
    """The numeric settings, each checked against its range (``PlanConfig`` fields)."""
    sweep, sel, eff = sections["sweep"], sections["selection"], sections["effects"]
    proof = sections["proof"]
    return dict(
        seed=r.integer(doc.get("seed", 0), "seed", 0),
        sample_rate_hz=r.number(doc.get("sample_rate_hz", 500.0), "sample_rate_hz", lo=10.0),
        analysis_rate_hz=r.number(doc.get("analysis_rate_hz", 200.0), "analysis_rate_hz",
                                  lo=10.0),
        model_error_fraction=r.number(doc.get("model_error_fraction", 0.01),
                                      "model_error_fraction", lo=0.0, hi=0.5),
        sweep_points=r.integer(sweep.get("points", 4), "sweep.points", 1),
        fd_step=r.number(sweep.get("fd_step", 0.02), "sweep.fd_step", lo=1e-4, hi=0.5),
        input_draws=r.integer(sweep.get("input_draws", 4), "sweep.input_draws", 0),
        budget=r.number(sel.get("budget", math.inf), "selection.budget", lo=0.0, strict_lo=True),
        target_relative_std=r.number(sel.get("target_relative_std", 0.1),
                                     "selection.target_relative_std", lo=0.0, strict_lo=True),
        max_tests_per_scenario=r.integer(sel.get("max_tests_per_scenario", 3),
                                         "selection.max_tests_per_scenario", 1),
        effects_min_evidence=r.number(eff.get("min_evidence", 10.0), "effects.min_evidence",
                                      lo=0.0),
        effects_min_unexplained=r.number(eff.get("min_unexplained", 0.5),
                                         "effects.min_unexplained", lo=0.0, hi=1.0),
        proof_seed=r.integer(proof.get("seed", 0), "proof.seed", 0),
        proof_multistart=r.integer(proof.get("multistart", 2), "proof.multistart", 1),
    )


def load_plan(path: str | Path) -> PlanConfig:
    """Read and validate PLAN.yaml; ``PlanError`` (one line) on any problem."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise PlanError(path, "", f"cannot read the planning config ({exc.strerror})") from None
    try:
        doc = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" at line {mark.line + 1}" if mark is not None else ""
        raise PlanError(path, "", f"not valid YAML{where}") from None
    return parse_plan(doc, path)
