"""Channel table and scenarios of a prismatic axis (one mass on a ball screw, motor force).

The second system family beside the steering rig: the EMPS benchmark
(docs/prismatic-axis.md). A campaign of this family keeps the shape of
campaign.yaml; only the channels and scenarios differ.
"""

from __future__ import annotations

from mbst.core.family import ALL_SCENARIOS, ChannelSpec, SystemFamily, register

SYSTEM_NAME = "prismatic-axis"

# closed_loop: the rig runs under its position controller, the model is driven by the
# position reference; open_loop: the model is driven by the measured motor force.
SCENARIOS = ("closed_loop", "open_loop")

CHANNELS = (
    ChannelSpec("time_s", "s", "time, strictly increasing, uniform within 1 %", ALL_SCENARIOS),
    ChannelSpec("position_m", "m", "load position (motor encoder, load side)", ALL_SCENARIOS),
    ChannelSpec("motor_force_n", "N", "motor force on the load side (drive gain × command)",
                ALL_SCENARIOS),
    ChannelSpec("position_reference_m", "m", "position reference of the controller",
                ("closed_loop",)),
    ChannelSpec("injected_force_n", "N", "disturbance force added after the controller's "
                "saturation (already inside motor_force_n)", ()),
    ChannelSpec("drive_command_v", "V", "controller output before the drive gain", ()),
)

OUTPUT_CHANNELS = ("position_m", "motor_force_n")


def prismatic_family() -> SystemFamily:
    return SystemFamily(
        name=SYSTEM_NAME,
        description="prismatic axis: one mass driven by a motor through a ball screw, "
        "optionally under a cascaded P/P position controller",
        scenarios=SCENARIOS,
        channels=CHANNELS,
        input_channel="position_reference_m",
        output_channels=OUTPUT_CHANNELS,
        motor_modes=("drive",),
        model_module="mbst.systems.prismatic.definition",
    )



register(SYSTEM_NAME, prismatic_family)
