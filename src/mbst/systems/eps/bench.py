"""Virtual test bench (seed 000, "simulation for testing").

Runs the one EPS model on a test plan and writes what a real rig would: a
campaign in the spec format with sensor noise and campaign-wide offsets. The
ground truth goes to ``truth.json`` beside the campaign, never inside it, so
nothing downstream can peek.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pandas as pd
import yaml

from mbst.core.family import get_system
from mbst.core.model import ModelDefinition
from mbst.core.sensors import measure
from mbst.io.campaign import TestSpec, write_campaign
from mbst.io.outputs import write_json
from mbst.systems.eps import simulate as eps
from mbst.systems.eps.assist import conditions, mode_param, route, speed_param
from mbst.systems.eps.channels import SYSTEM_NAME, TIE_RODS_CONNECTED
from mbst.systems.eps.model import EPS_MODEL
from mbst.systems.eps.params import EFFECTS, FRICTION_ELEMENTS, N_PARAMS, effect, friction_base
from mbst.systems.eps.realism import (
    BenchRealism,
    draw_effect_sizes,
    draw_rig,
    jittered_input,
    sharper_friction,
    warm_up_factor,
    written_known,
)

# Sensor noise, rms (eps-model.md "Measured-data realities")
NOISE_RMS = {
    "steering_angle_rad": math.radians(0.05),
    "steering_torque_nm": 0.02,
    "rack_position_m": 2e-5,
    "tie_rod_force_left_n": 5.0,
    "tie_rod_force_right_n": 5.0,
    "motor_angle_rad": 2e-3,
    "motor_current_a": 0.05,
}

# The demo rig: inside the typical ranges of eps-model.md, not at the model defaults,
# so identification has something to find.
KNOWN = {
    "pinion_radius_m": 7.5e-3,
    "worm_gear_ratio": 16.5,
    "column_inertia_kgm2": 2.1e-3,
    "motor_inertia_kgm2": 4.5e-5,
    "wheel_mass_kg": 80.0,
}
DEMO_RIG = {
    **KNOWN,
    "torsion_bar.stiffness_nm_per_rad": 92.0,
    "worm_gear.stiffness_nm_per_rad": 1.5e4,
    "worm_gear.damping_nms_per_rad": 1.1,
    "tie_rods.stiffness_n_per_m": 6.5e5,
    "tie_rods.damping_ns_per_m": 2800.0,
    "tires.centring_stiffness_n_per_m": 2.2e4,
    "steering_column.coulomb_nm": 0.07,
    "steering_column.viscous_nms_per_rad": 0.012,
    "motor.coulomb_nm": 0.025,
    "motor.viscous_nms_per_rad": 2.0e-4,
    "rack.coulomb_n": 240.0,
    "rack.viscous_ns_per_m": 4000.0,
    "tires.coulomb_n": 2600.0,
    "tires.viscous_ns_per_m": 3000.0,
}
DEMO_OFFSETS = {
    "offset.steering_torque_nm": 0.04,
    "offset.rack_position_m": 4e-4,
    "offset.tie_rod_force_left_n": 25.0,
    "offset.tie_rod_force_right_n": -18.0,
    "offset.motor_angle_rad": 0.7,
    "offset.motor_current_a": 0.03,
}
DEFAULT_SENSORS = (
    "steering_angle_rad",
    "steering_torque_nm",
    "rack_position_m",
    "tie_rod_force_left_n",
    "tie_rod_force_right_n",
)
OPTIONAL_SENSORS = ("motor_angle_rad", "motor_current_a")
DEMO_EFFECTS = ("backlash:worm_gear",)


# Seed 001 Table 2 (EPS): the two assistance programs and the active damping per speed.
DEMO_ASSIST_CURVES = {
    "normal": {"c1": 0.21, "c2": 0.34, "c3": 1.84},
    "city": {"c1": 0.29, "c2": 1.22, "c3": 1.68},
}
DEMO_ASSIST_DAMPING = {60.0: 0.015, 100.0: 0.05, 120.0: 0.09}
DEMO_HPS_CURVE = {"c1": 0.5}


@dataclass(frozen=True)
class PlannedTest:
    """One bench test: scenario, input profile and role (and, powered, mode and speed)."""

    id: str
    scenario: str
    input: dict
    role: str = "identification"
    motor: str = "passive"
    vehicle_speed_kph: float | None = None
    assist_mode: str | None = None
    sample_rate_hz: float | None = None
    # a sensor of this test other than the bench's (channel -> noise rms, absolute)
    noise_rms: dict[str, float] | None = None


def demo_plan() -> list[PlannedTest]:
    """Seed 000's campaign: scenarios (1) blocked column, (2) free tie-rods, (3) tires on ground.

    0.2 and 0.8 Hz sines on each, slow ramps on (2) and (3), a 0.8 Hz free
    tie-rods test held out as control (and one on the full system).
    """
    sine = lambda a, f, c: {"kind": "sine", "amplitude_deg": a, "frequency_hz": f, "cycles": c}  # noqa: E731
    ramp = lambda a, r: {"kind": "ramp", "amplitude_deg": a, "rate_deg_per_s": r}  # noqa: E731
    return [
        PlannedTest("s1_sine_0p2hz", "blocked_column", sine(5, 0.2, 2)),
        PlannedTest("s1_sine_0p8hz", "blocked_column", sine(5, 0.8, 5)),
        PlannedTest("s2_sine_0p2hz", "free_tie_rods", sine(30, 0.2, 2)),
        PlannedTest("s2_sine_0p8hz", "free_tie_rods", sine(30, 0.8, 5)),
        PlannedTest("s2_ramp", "free_tie_rods", ramp(40, 20)),
        PlannedTest("s2_sine_0p8hz_ctrl", "free_tie_rods", sine(45, 0.8, 5), role="control"),
        PlannedTest("s3_sine_0p2hz", "tires_on_ground", sine(120, 0.2, 2)),
        PlannedTest("s3_sine_0p8hz", "tires_on_ground", sine(100, 0.8, 5)),
        PlannedTest("s3_ramp", "tires_on_ground", ramp(120, 40)),
        PlannedTest("s3_sine_0p5hz_ctrl", "tires_on_ground", sine(110, 0.5, 3), role="control"),
    ]


def plan_from_campaign(path: str | Path) -> list[PlannedTest]:
    """The tests of a ``campaign.yaml`` (a planned one: no data needed) as a bench plan.

    ``mbst plan --resolve`` writes the campaign with its next tests appended; the bench
    runs it with the campaign's seed and repeats the logged tests (same order, same noise).
    """
    path = Path(path)
    if path.is_dir():
        path = path / "campaign.yaml"
    try:
        doc = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError) as exc:
        raise ValueError(f"{path}: cannot read the campaign ({exc})") from None
    tests = doc.get("tests") if isinstance(doc, dict) else None
    if not tests:
        raise ValueError(f"{path}: no 'tests:' list")
    out = []
    for i, t in enumerate(tests):
        missing = [k for k in ("id", "scenario", "input") if k not in (t or {})]
        if missing:
            raise ValueError(f"{path}: test {i + 1} ({(t or {}).get('id', '?')}) has no "
                             f"{', '.join(missing)}")
        out.append(PlannedTest(str(t["id"]), str(t["scenario"]), dict(t["input"]),
                               role=str(t.get("role", "identification")),
                               motor=str(t.get("motor", "passive")),
                               vehicle_speed_kph=t.get("vehicle_speed_kph"),
                               assist_mode=t.get("assist_mode"),
                               noise_rms={str(k): float(v) for k, v in
                                          (t.get("sensor_noise_rms") or {}).items()} or None))
    return out


def compact_plan() -> list[PlannedTest]:
    """A short campaign for quick checks: blocked column and free tie-rods, one control.

    A third of the demo's duration; discovery on it searches every effect that
    can act without tie-rods and tires.
    """
    sine = lambda a, f, c: {"kind": "sine", "amplitude_deg": a, "frequency_hz": f, "cycles": c}  # noqa: E731
    return [
        PlannedTest("s1_sine_0p5hz", "blocked_column", sine(5, 0.5, 3)),
        PlannedTest("s1_sine_1hz", "blocked_column", sine(5, 1.0, 4)),
        PlannedTest("s2_sine_0p25hz", "free_tie_rods", sine(30, 0.25, 2)),
        PlannedTest("s2_sine_0p8hz", "free_tie_rods", sine(30, 0.8, 4)),
        PlannedTest("s2_ramp", "free_tie_rods",
                    {"kind": "ramp", "amplitude_deg": 40, "rate_deg_per_s": 20}),
        PlannedTest("s2_sine_0p8hz_ctrl", "free_tie_rods", sine(45, 0.8, 4), role="control"),
    ]


def assist_plan(quasi_static_hz: float = 0.01, speeds: tuple[float, ...] = (60.0, 100.0, 120.0),
                modes: tuple[str, ...] = ("normal", "city"), free_wheels_on: bool = True
                ) -> list[PlannedTest]:
    """Seed 001's layout: engine off / on, free / loaded wheels, 0.01, 0.5 and 1 Hz.

    Free wheels are ``suspended``, loaded wheels ``tires_on_ground``. With the
    engine off the rig gives friction and stiffness; with it on, the 0.01 Hz
    (quasi-static) tests give one assist curve per mode and the 1 Hz tests the
    active damping at each vehicle speed. Held out: an engine-off 0.8 Hz test and
    engine-on 0.5 Hz tests in both modes.

    Seed 001 reuses the passive rig's parameters: the campaign starts with
    seed 000's cut-outs (blocked column, free tie-rods) with the motor passive,
    so stiffness and friction come from where they are isolated.
    """
    tag = f"{quasi_static_hz:g}".replace(".", "p")
    slow = {"kind": "sine", "amplitude_deg": 120, "frequency_hz": quasi_static_hz,
            "cycles": 1.25, "taper_cycles": 0.25}
    fast = lambda f, c: {"kind": "sine", "amplitude_deg": 90, "frequency_hz": f, "cycles": c}  # noqa: E731
    # the slow tests are long: 200 Hz is what a quasi-static channel needs
    slow_hz = 200.0
    v0 = speeds[0]
    out = [pt for pt in compact_plan() if pt.role == "identification"] + [
        PlannedTest(f"off_free_{tag}hz", "suspended", slow, sample_rate_hz=slow_hz),
        PlannedTest(f"off_loaded_{tag}hz", "tires_on_ground", slow, sample_rate_hz=slow_hz),
        PlannedTest("off_loaded_0p5hz", "tires_on_ground", fast(0.5, 3)),
        PlannedTest("off_loaded_1hz", "tires_on_ground", fast(1.0, 4)),
        PlannedTest("off_loaded_0p8hz_ctrl", "tires_on_ground", fast(0.8, 4), role="control"),
    ]
    for m in modes:
        if free_wheels_on:  # seed 001: friction bounds from engine off and on, free wheels
            out.append(PlannedTest(f"on_free_{tag}hz_{m}", "suspended", slow, motor="assist",
                                   vehicle_speed_kph=v0, assist_mode=m, sample_rate_hz=slow_hz))
        out.append(PlannedTest(f"on_loaded_{tag}hz_{m}", "tires_on_ground", slow, motor="assist",
                               vehicle_speed_kph=v0, assist_mode=m, sample_rate_hz=slow_hz))
    for v in speeds:
        out.append(PlannedTest(f"on_loaded_1hz_{modes[0]}_{v:g}kph", "tires_on_ground",
                               fast(1.0, 4), motor="assist", vehicle_speed_kph=v,
                               assist_mode=modes[0]))
    for i, m in enumerate(modes):
        v = speeds[(i + 1) % len(speeds)]
        out.append(PlannedTest(f"on_loaded_0p5hz_{m}_{v:g}kph_ctrl", "tires_on_ground",
                               fast(0.5, 3), role="control", motor="assist",
                               vehicle_speed_kph=v, assist_mode=m))
    return out


def compact_assist_plan() -> list[PlannedTest]:
    """Seed 001's layout shortened for quick checks: 0.05 Hz as the quasi-static
    frequency, two speeds."""
    return assist_plan(quasi_static_hz=0.05, speeds=(60.0, 120.0))


PLANS = {"demo": demo_plan, "compact": compact_plan, "assist": assist_plan,
         "compact-assist": compact_assist_plan}


# sines summed in a ``random`` input (``_random_input``)
RANDOM_COMPONENTS = 12


def input_profile(spec: dict, sample_rate_hz: float) -> tuple[np.ndarray, np.ndarray]:
    """Time and steering angle (rad) of an input profile, starting and ending at rest."""
    kind = spec["kind"]
    a = math.radians(float(spec.get("amplitude_deg", 30.0)))
    lead = 0.5  # s at rest before the motion: the initial state is then known
    if kind == "sine":
        f = float(spec["frequency_hz"])
        dur = float(spec.get("cycles", 3)) / f
        t = np.arange(0.0, lead + dur + lead, 1.0 / sample_rate_hz)
        tm = np.clip(t - lead, 0.0, dur)
        # a cosine taper (one cycle unless told) keeps the angle and its rate continuous
        taper = np.minimum(1.0, np.minimum(tm, dur - tm) * f / float(spec.get("taper_cycles", 1)))
        taper = 0.5 - 0.5 * np.cos(np.pi * taper)
        ang = a * taper * np.sin(2 * np.pi * f * tm)
    elif kind in ("ramp", "triangle"):
        rate = math.radians(float(spec.get("rate_deg_per_s", 20.0)))
        hold = float(spec.get("hold_s", 1.0)) if kind == "ramp" else 0.0
        tr = a / rate
        # 0 → +A, hold, +A → −A, hold, −A → 0
        knots_t = np.cumsum([0, lead, tr, hold, 2 * tr, hold, tr, lead])
        knots_a = [0, 0, a, a, -a, -a, 0, 0]
        t = np.arange(0.0, knots_t[-1], 1.0 / sample_rate_hz)
        ang = np.interp(t, knots_t, knots_a)
        # round the corners (1 % of a ramp) so the rate has no jumps the sensor could not see
        k = max(1, int(0.01 * tr * sample_rate_hz))
        ang = np.convolve(np.pad(ang, k, mode="edge"), np.ones(2 * k + 1) / (2 * k + 1), "valid")
    elif kind == "sweep":
        f0, f1 = float(spec.get("f0_hz", 0.1)), float(spec.get("f1_hz", 2.0))
        dur = float(spec.get("duration_s", 20.0))
        t = np.arange(0.0, lead + dur + lead, 1.0 / sample_rate_hz)
        tm = np.clip(t - lead, 0.0, dur)
        phase = 2 * np.pi * (f0 * tm + 0.5 * (f1 - f0) / dur * tm**2)
        ang = a * _fade(tm, dur) * np.sin(phase)
    elif kind == "step":
        dur = float(spec.get("duration_s", 6.0))
        t = np.arange(0.0, lead + dur, 1.0 / sample_rate_hz)
        rise = float(spec.get("rise_s", 0.05))
        ang = a * np.clip((t - lead) / rise, 0.0, 1.0)
    elif kind == "random":
        t, ang = _random_input(spec, a, lead, sample_rate_hz)
    else:
        raise ValueError(f"the bench cannot generate input kind '{kind}'")
    return t, ang


def _fade(tm: np.ndarray, dur: float) -> np.ndarray:
    """A linear fade in and out over a second (a quarter of a shorter input)."""
    return np.clip(np.minimum(tm, dur - tm) / min(1.0, dur / 4), 0.0, 1.0)


def _random_input(spec: dict, a: float, lead: float, sample_rate_hz: float
                  ) -> tuple[np.ndarray, np.ndarray]:
    """A band-limited random steering input: ``RANDOM_COMPONENTS`` sines spread evenly over
    ``f0_hz``–``f1_hz`` at 1/f amplitudes and phases drawn from the entry's ``seed``, faded
    in and out over a second, peaking at the amplitude. Reversals at every size and speed
    the band holds, where a sine has one of each."""
    f0, f1 = float(spec.get("f0_hz", 0.05)), float(spec.get("f1_hz", 1.0))
    dur = float(spec.get("duration_s", 20.0))
    if not 0 < f0 <= f1:
        raise ValueError(f"a random input needs 0 < f0_hz <= f1_hz (got {f0}, {f1})")
    phases = np.random.default_rng(int(spec.get("seed", 0))).uniform(
        0.0, 2 * np.pi, RANDOM_COMPONENTS)
    t = np.arange(0.0, lead + dur + lead, 1.0 / sample_rate_hz)
    tm = np.clip(t - lead, 0.0, dur)
    freqs = np.linspace(f0, f1, RANDOM_COMPONENTS)
    ang = sum(f0 / f * np.sin(2 * np.pi * f * tm + ph) for f, ph in zip(freqs, phases))
    ang = ang * _fade(tm, dur)
    peak = float(np.max(np.abs(ang)))
    return t, (a / peak * ang if peak > 0 else ang)


def parse_effect_given(text: str) -> tuple[str, dict[str, float]]:
    """``EFFECT:COMPONENT[:param=value,...]`` → (catalogue key, the headline values given)."""
    parts = text.split(":")
    if len(parts) < 2:
        raise ValueError(f"--effect '{text}': expected EFFECT:COMPONENT[:param=value,...]")
    spec = effect(parts[0], parts[1])
    given: dict[str, float] = {}
    if len(parts) > 2 and parts[2]:
        for item in ":".join(parts[2:]).split(","):
            if "=" not in item:
                raise ValueError(f"--effect '{text}': '{item}' is not param=value")
            k, v = item.split("=", 1)
            k = k.strip()
            if k not in spec.headline:
                raise ValueError(
                    f"--effect '{text}': '{k}' is not a parameter of {spec.key} "
                    f"(it has: {', '.join(spec.headline)})"
                )
            try:
                given[k] = float(v)
            except ValueError:
                raise ValueError(f"--effect '{text}': '{v}' is not a number") from None
    return spec.key, given


def parse_effect(text: str) -> tuple[str, dict[str, float]]:
    """``EFFECT:COMPONENT[:param=value,...]`` → (catalogue key, named model values).

    Parameters not given take the catalogue's realistic default size.
    """
    key, given = parse_effect_given(text)
    spec = EFFECTS[key]
    return key, {**spec.default_size, **{spec.headline[h]: v for h, v in given.items()}}


@dataclass
class BenchRecipe:
    """What to put on the virtual rig."""

    effects: list[str] = field(default_factory=lambda: list(DEMO_EFFECTS))
    seed: int = 0
    noise_scale: float = 1.0
    sensors: tuple[str, ...] = DEFAULT_SENSORS
    sample_rate_hz: float = 500.0
    plan: list[PlannedTest] | None = None
    name: str = "demo-eps"
    rig: dict[str, float] = field(default_factory=lambda: dict(DEMO_RIG))
    offsets: dict[str, float] = field(default_factory=lambda: dict(DEMO_OFFSETS))
    # powered tests: the characteristic family, its curve per assist mode, damping per speed
    assist_characteristic: str = "eps"
    assist_curves: dict[str, dict[str, float]] | None = None
    assist_damping: dict[float, float] = field(default_factory=lambda: dict(DEMO_ASSIST_DAMPING))
    realism: BenchRealism = field(default_factory=BenchRealism)

    def effect_values(self) -> list[tuple[str, dict[str, float]]]:
        if not self.realism.draw_sizes:
            return [parse_effect(e) for e in self.effects]
        out = []
        for i, text in enumerate(self.effects):
            key, given = parse_effect_given(text)
            out.append((key, draw_effect_sizes(self.seed, i, key, given)))
        return out

    def rig_values(self) -> dict[str, float]:
        """The rig on the bench: parameters and sensor offsets (drawn per seed if asked)."""
        r = self.realism
        rig = draw_rig(self.seed, self.offsets) if r.draw_rig else {**self.rig, **self.offsets}
        if r.cogging_nm:
            rig["motor.cogging_torque_nm"] = r.cogging_nm
            rig["motor.cogging_periods_per_rev"] = float(r.cogging_order)
        if r.rack_ratio_variation:
            rig["rack_pinion.ratio_variation_per_rad2"] = r.rack_ratio_variation
        return sharper_friction(rig, r.smoothing) if r.smoothing != 1.0 else rig

    def known(self) -> dict[str, float]:
        """The known values ``campaign.yaml`` states (off by ``realism.known_error``)."""
        rig = self.rig_values()
        return written_known(self.seed, {k: rig[k] for k in KNOWN}, self.realism.known_error)

    def priors(self) -> dict[str, float]:
        """Sigma of each known value written as a prior (``realism.known_sigma``)."""
        sigma = self.realism.known_sigma
        return {k: sigma * abs(v) for k, v in self.known().items()} if sigma > 0 else {}

    def planned(self) -> list[PlannedTest]:
        plan = self.plan or demo_plan()
        return [replace(pt, input=jittered_input(pt.input, self.seed, i, self.realism.plan_jitter))
                for i, pt in enumerate(plan)]

    def specs(self) -> list[TestSpec]:
        return [TestSpec(id=pt.id, file=f"tests/{pt.id}.csv", scenario=pt.scenario,
                         input=dict(pt.input), motor=pt.motor, role=pt.role,
                         vehicle_speed_kph=pt.vehicle_speed_kph, assist_mode=pt.assist_mode)
                for pt in self.planned()]

    def campaign_extra(self) -> dict:
        powered = any(s.motor == "assist" for s in self.specs())
        return {"assist_characteristic": self.assist_characteristic} if powered else {}

    def model(self) -> ModelDefinition:
        """The model the campaign will be read with (one curve per mode, damping per speed)."""
        stand_in = SimpleNamespace(name=self.name, tests=self.specs(), extra=self.campaign_extra())
        return EPS_MODEL.for_campaign(stand_in)

    def curves(self) -> dict[str, dict[str, float]]:
        if self.assist_curves is not None:
            return self.assist_curves
        if self.assist_characteristic == "hps":
            return {m: dict(DEMO_HPS_CURVE) for m in DEMO_ASSIST_CURVES}
        return DEMO_ASSIST_CURVES

    def true_params(self) -> np.ndarray:
        """The rig's parameters in ``model()``'s layout."""
        model = self.model()
        values = self.rig_values()
        for _, v in self.effect_values():
            values.update(v)
        idx = model.param_index
        for mode, c in self.curves().items():
            for q, v in c.items():
                if mode_param(mode, q) in idx:
                    values[mode_param(mode, q)] = v
        for speed, v in self.assist_damping.items():
            if speed_param(speed) in idx:
                values[speed_param(speed)] = v
        modes, speeds = conditions(self.specs())
        missing = [m for m in modes if mode_param(m, "c1") not in values] + [
            f"{v:g} km/h" for v in speeds if speed_param(v) not in values]
        if missing:
            raise ValueError(f"the bench has no assist truth for: {', '.join(missing)}")
        return model.vector_from(values)


# pause between two tests of a campaign (the rig warms up over the campaign's running time)
SETUP_TIME_S = 30.0


def simulate_plan(recipe: BenchRecipe) -> list[tuple[TestSpec, pd.DataFrame]]:
    """Noisy measured tests of the recipe's plan, deterministic in the seed."""
    model = recipe.model()
    p = recipe.true_params()
    for s in recipe.sensors:
        if s not in NOISE_RMS:
            raise ValueError(f"unknown sensor '{s}' (known: {', '.join(NOISE_RMS)})")
    tests = []
    campaign_time_s = 0.0
    for i, (pt, spec) in enumerate(zip(recipe.planned(), recipe.specs())):
        rng = np.random.default_rng([recipe.seed, i])  # per test: order-independent
        rate = pt.sample_rate_hz or recipe.sample_rate_hz
        # the test's own assist curve and damping, in the kernel's layout
        p_test = route(model, spec, p[None])[0][:N_PARAMS]
        t, ang, sim = _run_test(pt, p_test, rate, recipe.realism, campaign_time_s)
        _check_finite(spec, t, sim)
        cols = {"time_s": t}
        for ch in _channels_for(pt.scenario, recipe.sensors):
            if ch == "motor_current_a" and pt.motor != "assist":
                continue  # engine off: the current channel is flat, nothing is logged
            clean = ang if ch == "steering_angle_rad" else sim[ch]
            sigma = (pt.noise_rms or {}).get(ch, NOISE_RMS[ch]) * recipe.noise_scale
            cols[ch] = measure(clean, t, sigma, rng,
                               recipe.realism.sensor(ch), campaign_time_s)
        tests.append((spec, pd.DataFrame(cols)))
        campaign_time_s += float(t[-1] - t[0]) + SETUP_TIME_S
    return tests


def _run_test(pt: PlannedTest, p_test: np.ndarray, rate_hz: float, realism: BenchRealism,
              campaign_time_s: float) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]:
    """Time, true angle and clean channels of one test, on the bench's own integration grid."""
    k = max(1, int(realism.oversample))
    if realism.friction_drift > 0:
        p_test = p_test.copy()
        factor = warm_up_factor(realism.friction_drift, campaign_time_s)
        for elem in FRICTION_ELEMENTS:
            p_test[friction_base(elem)] *= factor
    t, ang = input_profile(pt.input, rate_hz * k)
    sim = eps.simulate(pt.scenario, pt.motor, t, ang, p_test)
    if k > 1:  # integrated between the samples, logged at the sample rate
        t, ang = t[::k], ang[::k]
        sim = {ch: v[::k] for ch, v in sim.items()}
    return t, ang, sim


def _check_finite(spec: TestSpec, t: np.ndarray, sim: dict[str, np.ndarray]) -> None:
    """Refuse a test whose simulated rig diverged: no campaign of NaNs is written.

    The model has no motor torque limit, so where the rig itself is unstable its signals
    grow without bound: an HPS curve's gain c1·e^|T| past a torsion-bar stop (the
    divergence comes at the same instant at 1–32× the sub-steps, so it is the rig's, not
    the integration's; most likely the assist's gain, fed back from the torsion bar to the
    motor through the compliant worm gear).
    """
    first = {ch: int(np.argmin(np.isfinite(v))) for ch, v in sim.items()
             if not np.all(np.isfinite(v))}
    if not first:
        return
    ch = min(first, key=first.get)
    hint = (" A powered test: the assist's gain fed back through the worm gear can make "
            "the loop unstable where the torque grows (the model has no motor torque limit); "
            "try the eps characteristic, a smaller effect or a passive plan."
            if spec.motor == "assist" else "")
    raise ValueError(
        f"test '{spec.id}' ({spec.scenario}): the simulated rig diverged at "
        f"t = {t[first[ch]]:.3f} s ({ch.removeprefix('internal.')} first not finite at "
        f"sample {first[ch]}); no campaign was written.{hint}")


def _channels_for(scenario: str, sensors: tuple[str, ...]) -> list[str]:
    """The chosen sensors that exist in this cut-out, plus the ones the format requires."""
    out = []
    for ch in sensors:
        if ch == "rack_position_m" and scenario == "blocked_column":
            continue
        if ch.startswith("tie_rod_force") and scenario not in TIE_RODS_CONNECTED:
            continue
        if ch.startswith("motor_") and scenario == "blocked_column":
            continue
        out.append(ch)
    # a campaign the reader rejects is no campaign: required channels are always logged
    for req in get_system(SYSTEM_NAME).required_channels(scenario):
        if req != "time_s" and req not in out:
            out.append(req)
    return out


def truth_record(recipe: BenchRecipe) -> dict:
    """Ground truth: every parameter, the hidden effects with headline sizes, offsets."""
    p = recipe.true_params()
    model = recipe.model()
    effects = []
    for key, values in recipe.effect_values():
        spec = EFFECTS[key]
        effects.append({
            "effect": spec.effect,
            "component": spec.component,
            "parameters": {h: values[n] for h, n in spec.headline.items()},
        })
    return {
        "format": "mbst-bench-truth/1",
        "campaign": recipe.name,
        "seed": recipe.seed,
        "noise_scale": recipe.noise_scale,
        "noise_rms": {k: v * recipe.noise_scale for k, v in NOISE_RMS.items()},
        "effects": effects,
        "realism": recipe.realism.as_record(),
        "known_written": recipe.known(),
        "known_sigma_written": recipe.priors(),
        "params": model.as_dict(p),
    }


def run_bench(out_dir: str | Path, recipe: BenchRecipe, overwrite: bool = True) -> Path:
    """Write ``out_dir/campaign/`` and ``out_dir/truth.json``; return the campaign path."""
    tests = simulate_plan(recipe)  # first: a rig that diverges leaves no folder behind
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    camp = write_campaign(
        out / "campaign", name=recipe.name, system=SYSTEM_NAME, known=recipe.known(), tests=tests,
        extra={"generated_by": "mbst bench", "seed": recipe.seed, **recipe.campaign_extra()},
        overwrite=overwrite, priors=recipe.priors(),
    )
    write_json(out / "truth.json", truth_record(recipe))
    return camp


