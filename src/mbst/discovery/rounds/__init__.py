"""Discovery rounds: each proposes findings from the discovery state (structure test, stick-slip, equation error, resolution)."""
