"""Candidate sensors of the EPS rig, derived from the simulator's outputs.

There is one model (``mbst.systems.eps.simulate``); a candidate sensor that is not one
of the campaign-format channels is read from the kernel's internal outputs
(``eps_kernel.OUTPUT_NAMES``) here, in this one place, never from a second
model.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from mbst.systems.eps import kernel as K
from mbst.systems.eps import simulate as eps
from mbst.systems.eps.channels import OUTPUT_CHANNELS, SCENARIOS, TIE_RODS_CONNECTED

# Wheel angle from the wheel-side rack displacement: x_w = arm · δ. A typical
# steering-arm length; it only scales the channel (its noise is given in rad).
STEERING_ARM_M = 0.15

_MOVING = tuple(s for s in SCENARIOS if s != "blocked_column")
_WHEELS = ("suspended", "tires_on_ground")


@dataclass(frozen=True)
class SensorSpec:
    """One candidate measurement.

    ``exists_in`` lists the scenarios where the quantity moves (elsewhere it is
    blocked or disconnected and is not logged); ``campaign_channel`` says
    whether campaign-format.md names it (identification fits only those);
    ``default_noise`` is an rms per sample in the channel's unit.
    """

    name: str
    unit: str
    meaning: str
    exists_in: tuple[str, ...]
    default_noise: float
    campaign_channel: bool


SENSORS: dict[str, SensorSpec] = {s.name: s for s in (
    SensorSpec("steering_angle_rad", "rad", "steering-wheel angle (potentiometer); the model's "
               "input, always logged", SCENARIOS, math.radians(0.05), True),
    SensorSpec("steering_torque_nm", "N·m", "torque at the steering wheel (strain-gauge bridge "
               "on the column)", SCENARIOS, 0.02, True),
    SensorSpec("rack_position_m", "m", "rack displacement (wire-draw sensor)", _MOVING, 2e-5,
               True),
    SensorSpec("tie_rod_force_left_n", "N", "axial force, left tie-rod (strain gauges)",
               TIE_RODS_CONNECTED, 5.0, True),
    SensorSpec("tie_rod_force_right_n", "N", "axial force, right tie-rod (symmetry check)",
               TIE_RODS_CONNECTED, 5.0, True),
    SensorSpec("motor_angle_rad", "rad", "motor rotor angle, motor side (the motor's position "
               "sensor)", _MOVING, 2e-3, True),
    SensorSpec("motor_current_a", "A", "assist motor current (zero with a passive motor)",
               _MOVING, 0.05, True),
    SensorSpec("pinion_angle_rad", "rad", "pinion angle below the torsion bar (encoder on the "
               "pinion shaft)", _MOVING, math.radians(0.05), False),
    SensorSpec("wheel_angle_rad", "rad", "road-wheel steer angle (encoder on the spindle)",
               _WHEELS, math.radians(0.05), False),
    SensorSpec("torsion_bar_torque_nm", "N·m", "torque below the column sensor: torsion-bar "
               "twist torque, without column friction", SCENARIOS, 0.02, False),
)}
SENSOR_NAMES: tuple[str, ...] = tuple(SENSORS)
INPUT_SENSOR = "steering_angle_rad"


def sensor_signals(raw: np.ndarray, p: np.ndarray, scenario: str,
                   angle_rad: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """Every candidate sensor's signal from raw model outputs ``(N, N_OUTPUTS)``.

    Parameters
    ----------
    raw
        ``eps.simulate_raw`` / ``eps_kernel.simulate_batch`` output of one run.
    p
        The parameter vector of that run (sensor offsets are applied to the
        campaign-format channels, as the bench does).
    scenario
        Scenario name (the blocked column pins everything below the sensor).
    angle_rad
        The imposed steering angle; zeros if omitted (it carries no parameter
        information: the bench imposes it).

    Returns
    -------
    dict
        Channel name → signal, for every name in ``SENSOR_NAMES``.
    """
    out = eps.sensors_from_raw(raw, p, scenario)
    n = raw.shape[0]
    out["steering_angle_rad"] = (np.zeros(n) if angle_rad is None
                                 else np.asarray(angle_rad, float))
    out["pinion_angle_rad"] = raw[:, K.O_THP]
    out["wheel_angle_rad"] = raw[:, K.O_XW] / STEERING_ARM_M
    # the torque sensor reads T_tb + column friction; below it only the bar's twist torque
    out["torsion_bar_torque_nm"] = raw[:, K.O_TTB]
    return {name: out[name] for name in SENSOR_NAMES}


def logged_channels(scenario: str, sensors: list[str] | tuple[str, ...]) -> list[str]:
    """The chosen sensors that move in ``scenario``, in catalogue order."""
    return [s for s in SENSOR_NAMES if s in sensors and scenario in SENSORS[s].exists_in]


def identification_channels() -> tuple[str, ...]:
    """Channels the identification fits (the campaign format's model outputs)."""
    return OUTPUT_CHANNELS
