"""The prismatic axis as a model definition: the equations of ``model.py``, its catalogue
and cascade, and the EMPS figures of merit (``benchmark.py``) that discovery reports."""

from __future__ import annotations

from mbst.core.model import ModelDefinition
from mbst.systems.prismatic.benchmark import benchmark_record
from mbst.systems.prismatic.channels import OUTPUT_CHANNELS, SYSTEM_NAME
from mbst.systems.prismatic.model import (
    CASCADE,
    CATALOGUE,
    PARAM_SPECS,
    equation_error,
    pre_identify,
    prepare_inputs,
    simulate_batch,
)

PRISMATIC_MODEL = ModelDefinition(
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
    component_scenarios={"ball_screw": ("closed_loop", "open_loop"),
                         "drive": ("closed_loop", "open_loop")},
    hysteresis=("rate:position_m", "motor_force_n", "velocity [mm/s] (measured)",
                "motor force [N]", 1e3),
    evidence_methods=(),
    discovery_rounds=("structure", "equation_error", "unexplained", "resolution"),
    benchmark=benchmark_record,
    equation_error=equation_error,
)

# the family's definition, as the registry looks it up (core.family.SystemFamily.model)
MODEL = PRISMATIC_MODEL
