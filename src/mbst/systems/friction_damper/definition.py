"""The friction damper as a model definition: the equations of ``model.py``, its
catalogue and cascade, and the makers' published LuGre scores (``benchmark.py``)."""

from __future__ import annotations

from mbst.core.model import ModelDefinition
from mbst.systems.friction_damper.benchmark import benchmark_record
from mbst.systems.friction_damper.channels import OUTPUT_CHANNELS, SYSTEM_NAME
from mbst.systems.friction_damper.model import (
    CASCADE,
    CATALOGUE,
    PARAM_SPECS,
    pre_identify,
    prepare_inputs,
    simulate_batch,
)

FRICTION_DAMPER_MODEL = ModelDefinition(
    name=SYSTEM_NAME,
    param_specs=PARAM_SPECS,
    catalogue=CATALOGUE,
    cascade=CASCADE,
    offset_channels={},
    output_channels=OUTPUT_CHANNELS,
    simulate_batch=simulate_batch,
    prepare_inputs=prepare_inputs,
    pre_identify=pre_identify,
    carries_over=lambda name: True,
    component_scenarios={"band": ("imposed_displacement",),
                         "load_cell": ("imposed_displacement",)},
    hysteresis=("input", "friction_force_n", "displacement [mm]", "friction force [N]", 1e3),
    evidence_methods=(),
    discovery_rounds=("structure", "unexplained", "resolution"),
    benchmark=benchmark_record,
)

# the family's definition, as the registry looks it up (core.family.SystemFamily.model)
MODEL = FRICTION_DAMPER_MODEL
