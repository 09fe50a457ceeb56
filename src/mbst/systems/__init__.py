"""Rig families, one subpackage each: ``eps/`` (the steering rig) and ``prismatic/`` (EMPS).

A family is data (parameters, catalogue, cascade, channels) plus one batch
simulator. Nothing outside ``systems/<family>/`` imports a family directly:
the registry (``mbst.core.family``) loads it by name when a campaign asks for it.
"""
