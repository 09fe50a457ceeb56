"""System families: a model definition plus its channel table.

A campaign's ``system:`` key names the family. Everything downstream (reader,
bench, identification, discovery, reports) asks the family for its channels,
scenarios and simulator instead of hard-coding the EPS rig.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from mbst.core.model import ModelDefinition

ALL_SCENARIOS = "*"


@dataclass(frozen=True)
class ChannelSpec:
    """One column of a test file.

    ``required_in`` lists the scenarios in which the column must be present;
    ``ALL_SCENARIOS`` means every scenario, an empty tuple means optional.
    """

    name: str
    unit: str
    meaning: str
    required_in: tuple[str, ...] | str = ()

    def required_for(self, scenario: str) -> bool:
        if self.required_in == ALL_SCENARIOS:
            return True
        return scenario in self.required_in


@dataclass(frozen=True)
class SystemFamily:
    """What the pipeline needs to know about one kind of rig."""

    name: str
    description: str
    scenarios: tuple[str, ...]
    channels: tuple[ChannelSpec, ...]
    time_channel: str = "time_s"
    input_channel: str = "steering_angle_rad"
    output_channels: tuple[str, ...] = ()
    motor_modes: tuple[str, ...] = ("passive", "assist")
    extras: dict = field(default_factory=dict)
    # the module whose ``MODEL`` is the family's definition, imported on first use:
    # reading a campaign must not load a simulator (importing one takes ~1 s)
    model_module: str | None = None

    def channel(self, name: str) -> ChannelSpec:
        for ch in self.channels:
            if ch.name == name:
                return ch
        raise KeyError(name)

    def model(self) -> ModelDefinition:
        """The family's model definition (parameters, catalogue, cascade, simulator)."""
        if self.model_module is None:
            raise KeyError(f"system '{self.name}' has no model definition")
        return importlib.import_module(self.model_module).MODEL

    def required_channels(self, scenario: str) -> list[str]:
        return [ch.name for ch in self.channels if ch.required_for(scenario)]


_REGISTRY: dict[str, Callable[[], SystemFamily]] = {}


def register(name: str, factory: Callable[[], SystemFamily]) -> None:
    _REGISTRY[name] = factory


def known_systems() -> list[str]:
    _load_builtin()
    return sorted(_REGISTRY)


def get_system(name: str) -> SystemFamily:
    """Return the family called ``name``; ``KeyError`` if there is none."""
    _load_builtin()
    return _REGISTRY[name]()


# The built-in families, by the module that registers each. Loaded by name, on first
# use, so that the core never imports a family (reading a campaign does not compile
# a simulator) and a new family is one line here plus its own subpackage.
BUILTIN_FAMILIES = ("mbst.systems.eps.channels", "mbst.systems.prismatic.channels",
                    "mbst.systems.friction_damper.channels")


def _load_builtin() -> None:
    for module in BUILTIN_FAMILIES:
        importlib.import_module(module)
