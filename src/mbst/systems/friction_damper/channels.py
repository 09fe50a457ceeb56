"""Channel table and scenario of a banded rotary friction damper (band brake).

The third system family beside the steering rig and the prismatic axis
(docs/friction-damper.md): an actuator imposes the displacement, a load cell
measures the friction force the device answers — the steering rig's blocked
column turned around. A campaign of this family keeps the shape of
campaign.yaml; only the channels and the scenario differ.
"""

from __future__ import annotations

from mbst.core.family import ALL_SCENARIOS, ChannelSpec, SystemFamily, register

SYSTEM_NAME = "friction-damper"

# one way to run the device: the actuator imposes the displacement
SCENARIOS = ("imposed_displacement",)

CHANNELS = (
    ChannelSpec("time_s", "s", "time, strictly increasing, uniform within 1 %", ALL_SCENARIOS),
    ChannelSpec("displacement_m", "m", "displacement imposed by the actuator", ALL_SCENARIOS),
    ChannelSpec("friction_force_n", "N", "friction force of the device (load cell)",
                ALL_SCENARIOS),
    ChannelSpec("velocity_m_per_s", "m/s", "actuator velocity as recorded", ()),
    ChannelSpec("actuator_position_1_m", "m", "position of the first actuator (the data "
                "set's eight-column files)", ()),
    ChannelSpec("actuator_position_2_m", "m", "position of the second actuator", ()),
    ChannelSpec("actuator_force_1_n", "N", "force of the first actuator", ()),
    ChannelSpec("actuator_force_2_n", "N", "force of the second actuator", ()),
)

OUTPUT_CHANNELS = ("friction_force_n",)


def friction_damper_family() -> SystemFamily:
    return SystemFamily(
        name=SYSTEM_NAME,
        description="banded rotary friction damper: displacement imposed by an actuator, "
        "friction force measured",
        scenarios=SCENARIOS,
        channels=CHANNELS,
        input_channel="displacement_m",
        output_channels=OUTPUT_CHANNELS,
        motor_modes=("actuator",),
        model_module="mbst.systems.friction_damper.definition",
    )


register(SYSTEM_NAME, friction_damper_family)
