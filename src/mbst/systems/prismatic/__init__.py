"""The EMPS prismatic axis (docs/prismatic-axis.md): channels, model, benchmark, importer."""
