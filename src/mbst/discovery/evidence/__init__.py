"""Evidence beside the structure test: sparse regression (pysindy) and the neural residual."""
