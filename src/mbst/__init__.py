"""mbst: model-based system testing for steering rigs and other mechatronic test benches."""

__version__ = "0.1.0"
