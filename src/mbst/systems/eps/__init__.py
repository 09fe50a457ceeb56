"""The electric power steering rig (docs/eps-model.md): channels, parameters, kernel, bench."""
