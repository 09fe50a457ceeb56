"""Channel table and scenarios of the column-assist EPS rig (campaign-format.md)."""

from __future__ import annotations

from mbst.core.family import ALL_SCENARIOS, ChannelSpec, SystemFamily, register

SYSTEM_NAME = "eps-column-assist"

SCENARIOS = ("blocked_column", "free_tie_rods", "blocked_rack", "suspended", "tires_on_ground")
TIE_RODS_CONNECTED = ("blocked_rack", "suspended", "tires_on_ground")

CHANNELS = (
    ChannelSpec("time_s", "s", "time, strictly increasing, uniform within 1 %", ALL_SCENARIOS),
    ChannelSpec("steering_angle_rad", "rad", "steering-wheel angle; the model's input", ALL_SCENARIOS),
    ChannelSpec("steering_torque_nm", "N·m", "torque at the steering wheel", ALL_SCENARIOS),
    ChannelSpec(
        "rack_position_m",
        "m",
        "rack displacement",
        tuple(s for s in SCENARIOS if s != "blocked_column"),
    ),
    ChannelSpec("tie_rod_force_left_n", "N", "axial force, left tie-rod", TIE_RODS_CONNECTED),
    ChannelSpec("tie_rod_force_right_n", "N", "axial force, right tie-rod", ()),
    ChannelSpec("motor_current_a", "A", "assist motor current", ()),
    ChannelSpec("motor_angle_rad", "rad", "motor rotor angle (motor side)", ()),
)

# Channels a model predicts and a fit compares, in report order.
OUTPUT_CHANNELS = (
    "steering_torque_nm",
    "rack_position_m",
    "tie_rod_force_left_n",
    "tie_rod_force_right_n",
    "motor_angle_rad",
    "motor_current_a",
)


def eps_family() -> SystemFamily:
    return SystemFamily(
        name=SYSTEM_NAME,
        description="column-assist electric power steering on an angle-driven bench",
        scenarios=SCENARIOS,
        channels=CHANNELS,
        output_channels=OUTPUT_CHANNELS,
        model_module="mbst.systems.eps.model",
    )



register(SYSTEM_NAME, eps_family)
