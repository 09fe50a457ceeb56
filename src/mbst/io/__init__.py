"""Reading and writing: the campaign format, atomic outputs, provenance."""
