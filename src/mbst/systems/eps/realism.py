"""A bench that is not the model: drawn rigs, sizes off the grids, real sensors.

Everything here is what identification does *not* assume: rig parameters drawn
per seed across eps-model.md's typical ranges, known values written a few per
cent off, effect sizes drawn from production to worn (never the catalogue's
default sizes that the start grids hold), sensors that lag, wander and count
in steps, and an integrator with other sub-steps and sharper friction than
identification's. Only the bench reads this module.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, replace

import numpy as np

from mbst.core.sensors import SensorRealities
from mbst.systems.eps.params import (
    EFFECTS,
    FRICTION_ELEMENTS,
    PARAM_INDEX,
    PARAM_SPECS,
    friction_param,
)

# eps-model.md, "Typical values": (low, high, log-uniform?)
RIG_RANGES: dict[str, tuple[float, float, bool]] = {
    "pinion_radius_m": (7e-3, 8e-3, False),
    "worm_gear_ratio": (15.5, 17.5, False),
    "column_inertia_kgm2": (1.6e-3, 2.6e-3, False),
    "motor_inertia_kgm2": (3.5e-5, 5.5e-5, False),
    "wheel_mass_kg": (60.0, 100.0, False),
    "torsion_bar.stiffness_nm_per_rad": (50.0, 110.0, False),
    "worm_gear.stiffness_nm_per_rad": (5e3, 2.5e4, True),
    "tie_rods.stiffness_n_per_m": (4e5, 1e6, True),
    "tires.centring_stiffness_n_per_m": (1e4, 4e4, False),
    "steering_column.coulomb_nm": (0.04, 0.09, False),
    "steering_column.viscous_nms_per_rad": (0.005, 0.02, False),
    "motor.coulomb_nm": (0.015, 0.045, False),
    "motor.viscous_nms_per_rad": (1e-4, 4e-4, False),
    "rack.coulomb_n": (180.0, 360.0, False),
    "rack.viscous_ns_per_m": (3000.0, 6000.0, False),
    "tires.coulomb_n": (2200.0, 3500.0, False),
    "tires.viscous_ns_per_m": (2000.0, 5000.0, False),
    # the rack as its own body (only with rack-pinion backlash): identification keeps
    # the model's fixed values, so a drawn rig has them "a bit off"
    "rack_pinion.rack_mass_kg": (2.0, 3.5, False),
    "rack_pinion.mesh_stiffness_nm_per_rad": (1.5e4, 3e4, False),
}
# damping ratios of the mesh mode and of the wheels on the tie-rods (eps-model.md)
DAMPING_RATIO = (0.1, 0.3)

# Effect sizes from new production hardware to worn (eps-model.md, "Sizes production rigs
# show"); each entry: headline → (low, high, log-uniform?) or two such ranges either side
# of neutral. None of them is centred on a start-grid node.
_FRICTION_SIZES = {
    "stribeck_friction": {"static_to_coulomb_ratio": [(1.15, 2.0, False)],
                          "stribeck_velocity": [(0.5, 2.0, True)]},  # × typical v_s
    "presliding_hysteresis": {"stiffness": [(0.3, 3.0, True)]},  # × typical σ
    "power_law_damping": {"exponent": [(0.4, 0.8, False), (1.3, 1.7, False)]},
    "asymmetric_friction": {"ratio": [(0.7, 0.88, False), (1.12, 1.4, False)]},
}
_OTHER_SIZES = {
    "backlash:worm_gear": {"width_rad": [(0.005, 0.035, True)]},  # 0.3°–2°
    "backlash:rack_pinion": {"width_rad": [(0.003, 0.0175, True)]},  # 0.17°–1°
    "load_dependent_friction:rack": {"coefficient": [(0.03, 0.08, False)]},
    "load_dependent_friction:steering_column": {"coefficient": [(0.01, 0.03, False)]},
    "position_dependent_friction:rack": {"position_m": [(-0.02, 0.02, False)],
                                         "amplitude": [(0.4, 1.5, False)]},
    "stiffness_limit_stop:torsion_bar": {"stop_angle_rad": [(0.02, 0.06, False)],
                                         "stiffness_ratio": [(6.0, 15.0, False)]},
    "coulomb_friction:tie_rods": {"level": [(60.0, 200.0, False)]},
}
_RELATIVE = {"stribeck_velocity", "stiffness"}  # drawn as a multiple of the typical value

# Sensors as a production rig has them (eps-model.md): a 13-bit angle encoder, 12-bit
# ADCs on torque and current, a resolver on the motor, and a torque sensor whose own
# filter lags by a few ms.
SENSOR_QUANTUM = {
    "steering_angle_rad": 2 * math.pi / 8192,
    "steering_torque_nm": 20.0 / 4096,
    "rack_position_m": 1e-5,
    "tie_rod_force_left_n": 2.5,
    "tie_rod_force_right_n": 2.5,
    "motor_angle_rad": 2 * math.pi / 4096,
    "motor_current_a": 0.01,
}
TORQUE_SENSOR_LAG_S = 0.003


# each reality's admissible values: (bound, inclusive?) low and high, and what it means;
# outside them the bench would write a rig no one has, or fail deep inside with no word
# of which flag (--plan-jitter 2 drew a negative frequency: a bare IndexError)
_COGGING = PARAM_SPECS[PARAM_INDEX["motor.cogging_torque_nm"]]
_LIMITS: dict[str, tuple[tuple[float, bool], tuple[float, bool], str]] = {
    "known_error": ((0.0, True), (1.0, False), "a fraction of each known value"),
    "known_sigma": ((0.0, True), (1.0, False), "a fraction of each known value"),
    "noise_ar1": ((-1.0, False), (1.0, False), "the noise's AR(1) coefficient per sample"),
    "torque_lag_s": ((0.0, True), (1.0, False), "the torque sensor's time constant in s"),
    "offset_drift": ((0.0, True), (math.inf, False), "noise rms"),
    "friction_drift": ((0.0, True), (1.0, False),
                       "the fraction the Coulomb levels fall by: 1 would leave none"),
    "cogging_nm": ((-_COGGING.upper, True), (_COGGING.upper, True),
                   "N·m at the motor, the cogging parameter's range; production motors "
                   "show a few mN·m"),
    "cogging_order": ((1.0, True), (64.0, True), "periods per motor revolution"),
    "rack_ratio_variation": ((-1.0, True), (1.0, True),
                             "1/rad², the rack travel per pinion radian r·(1 + a·θ²)"),
    "angle_eccentricity_deg": ((-10.0, True), (10.0, True), "degrees of angle error"),
    "oversample": ((1.0, True), (1000.0, True), "integration steps per sample"),
    "smoothing": ((0.0, False), (100.0, True), "times the regularisation velocities"),
    "plan_jitter": ((0.0, True), (1.0, False), "a fraction of each test's amplitude and "
                    "frequency"),
}


@dataclass(frozen=True)
class BenchRealism:
    """What the bench does differently from identification (all off: the plain bench).

    ``draw_rig``: rig parameters drawn per seed. ``known_error``: the known values
    written to ``campaign.yaml`` off by up to ± this fraction; ``known_sigma``: they
    are written as priors ``{value, sigma}`` with sigma this fraction of the
    value (0: plain numbers, held fixed). ``draw_sizes``:
    effect sizes not given on ``--effect`` drawn from production to worn.
    ``noise_ar1``, ``quantise``, ``torque_lag_s``, ``offset_drift``: sensor
    realities. ``friction_drift``: Coulomb levels that fall by this fraction as the
    rig warms up over the campaign, ``cogging_nm``, the motor's detent torque
    (``motor.cogging_torque_nm``) at ``cogging_order`` periods per revolution, and ``rack_ratio_variation``, a variable-ratio
    rack quicker off centre (``rack_pinion.ratio_variation_per_rad2``), and
    ``angle_eccentricity_deg``, a steering-angle encoder whose reading is off by
    this much once per revolution (the angle the model is driven with), are not
    catalogue effects: discovery can only describe them (an ``unexplained`` finding). ``oversample`` and
    ``smoothing``: the bench integrates on a finer grid than it samples and with
    regularisation velocities times ``smoothing``. ``plan_jitter``: test
    amplitudes and frequencies drawn up to ± this fraction off the plan's.
    """

    draw_rig: bool = False
    known_error: float = 0.0
    known_sigma: float = 0.0
    draw_sizes: bool = False
    noise_ar1: float = 0.0
    quantise: bool = False
    torque_lag_s: float = 0.0
    offset_drift: float = 0.0
    friction_drift: float = 0.0
    cogging_nm: float = 0.0
    cogging_order: int = 18
    rack_ratio_variation: float = 0.0
    angle_eccentricity_deg: float = 0.0
    oversample: int = 1
    smoothing: float = 1.0
    plan_jitter: float = 0.0

    def __post_init__(self) -> None:
        for name, ((lo, lo_in), (hi, hi_in), meaning) in _LIMITS.items():
            v = getattr(self, name)
            above = v >= lo if lo_in else v > lo
            below = v <= hi if hi_in else v < hi
            if not (math.isfinite(v) and above and below):
                span = f"{'[' if lo_in else '('}{lo:g}, {hi:g}{']' if hi_in else ')'}"
                raise ValueError(f"--{name.replace('_', '-')} must be in {span} ({meaning}), "
                                 f"got {v:g}")

    @classmethod
    def realistic(cls, **changes) -> BenchRealism:
        """Every reality at a size a production rig shows (``mbst bench --realistic``)."""
        base = cls(draw_rig=True, known_error=0.1, draw_sizes=True, noise_ar1=0.9,
                   quantise=True, torque_lag_s=TORQUE_SENSOR_LAG_S, offset_drift=1.0,
                   oversample=3, smoothing=0.5, plan_jitter=0.15)
        return replace(base, **changes)

    def as_record(self) -> dict:
        return asdict(self)

    def sensor(self, channel: str) -> SensorRealities:
        return SensorRealities(
            noise_ar1=self.noise_ar1,
            lag_s=self.torque_lag_s if channel == "steering_torque_nm" else 0.0,
            quantum=SENSOR_QUANTUM.get(channel, 0.0) if self.quantise else 0.0,
            drift=self.offset_drift if channel != "steering_angle_rad" else 0.0,
            eccentricity=(math.radians(self.angle_eccentricity_deg)
                          if channel == "steering_angle_rad" else 0.0),
        )


def _rng(seed: int, stream: int) -> np.random.Generator:
    # one stream per kind of draw: drawing sizes does not change the rig a seed gives
    return np.random.default_rng([seed, 7000 + stream])


def _draw(rng: np.random.Generator, ranges: list[tuple[float, float, bool]]) -> float:
    lo, hi, log = ranges[int(rng.integers(len(ranges)))]
    return float(math.exp(rng.uniform(math.log(lo), math.log(hi))) if log else rng.uniform(lo, hi))


def draw_rig(seed: int, offsets: dict[str, float]) -> dict[str, float]:
    """A rig drawn across the typical ranges; damping from drawn damping ratios."""
    rng = _rng(seed, 1)
    rig = {name: _draw(rng, [rng_]) for name, rng_ in RIG_RANGES.items()}
    n2_jm = rig["worm_gear_ratio"] ** 2 * rig["motor_inertia_kgm2"]
    j_mesh = rig["column_inertia_kgm2"] * n2_jm / (rig["column_inertia_kgm2"] + n2_jm)
    rig["worm_gear.damping_nms_per_rad"] = (
        2 * rng.uniform(*DAMPING_RATIO) * math.sqrt(rig["worm_gear.stiffness_nm_per_rad"] * j_mesh))
    rig["tie_rods.damping_ns_per_m"] = (
        2 * rng.uniform(*DAMPING_RATIO)
        * math.sqrt(rig["tie_rods.stiffness_n_per_m"] * rig["wheel_mass_kg"]))
    # offsets: the same sizes as the demo's, drawn sign and scale
    rig.update({k: v * rng.uniform(-1.5, 1.5) for k, v in offsets.items()})
    return rig


# inertias and masses come from estimates and CAD (eps-model.md: "a few to 15 % off");
# a gear ratio and a pinion radius from drawings, ten times closer
_GEOMETRY = ("pinion_radius_m", "worm_gear_ratio")


def written_known(seed: int, known: dict[str, float], error: float) -> dict[str, float]:
    """Known values as an engineer writes them from inspection: inertias up to ±error off."""
    if error <= 0:
        return dict(known)
    rng = _rng(seed, 2)
    out = {}
    for k, v in known.items():
        e = error / 10 if k in _GEOMETRY else error
        out[k] = v * (1.0 + rng.uniform(-e, e))
    return out


def draw_effect_sizes(seed: int, index: int, key: str, given: dict[str, float]
                      ) -> dict[str, float]:
    """Model values of one planted effect: the given headline values, the rest drawn.

    ``given`` maps headline names to values; the answer maps model names.
    """
    spec = EFFECTS[key]
    rng = _rng(seed, 10 + index)
    ranges = _OTHER_SIZES.get(key) or _FRICTION_SIZES[spec.effect]
    values = dict(spec.default_size)
    for headline, name in spec.headline.items():
        if headline in given:
            values[name] = given[headline]
        elif headline in ranges:
            v = _draw(rng, ranges[headline])
            if headline in _RELATIVE:
                v *= spec.default_size[name]
            values[name] = v
    return values


def sharper_friction(rig: dict[str, float], smoothing: float) -> dict[str, float]:
    """Regularisation velocities times ``smoothing``: the bench's friction laws are not
    identification's (defaults from the parameter table)."""
    out = {}
    for elem in FRICTION_ELEMENTS:
        name = friction_param(elem, "regularisation_velocity")
        out[name] = PARAM_SPECS[PARAM_INDEX[name]].default * smoothing
    return {**rig, **out}


def warm_up_factor(drift: float, campaign_time_s: float, tau_s: float = 300.0) -> float:
    """Coulomb levels after ``campaign_time_s`` of running, relative to cold: they fall by
    ``drift`` as the grease warms."""
    return 1.0 - drift * (1.0 - math.exp(-campaign_time_s / tau_s))


def jittered_input(spec: dict, seed: int, index: int, jitter: float) -> dict:
    """A test's input with amplitude and frequency (or rate) drawn up to ±jitter off."""
    if jitter <= 0:
        return dict(spec)
    rng = _rng(seed, 100 + index)
    out = dict(spec)
    for key in ("amplitude_deg", "frequency_hz", "rate_deg_per_s"):
        if key in out:
            out[key] = float(f"{out[key] * (1.0 + rng.uniform(-jitter, jitter)):.4g}")
    return out
