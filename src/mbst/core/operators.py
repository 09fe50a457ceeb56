"""Memory operators behind a family's named candidate terms (``core.candidates``).

Backlash and Dahl friction have memory: they are not functions of the current
state, so a family's candidate library (one per family, read by both the sparse
regression and the neural residual) builds its terms from these operators.
"""

from __future__ import annotations

import numpy as np


def play(x: np.ndarray, half_width: float) -> np.ndarray:
    """Backlash (play) operator: the far side follows ``x`` only once the gap is closed."""
    y = np.empty_like(np.asarray(x, dtype=np.float64))
    yi = float(x[0])
    for i, xi in enumerate(np.asarray(x, dtype=np.float64).tolist()):
        yi = min(max(yi, xi - half_width), xi + half_width)
        y[i] = yi
    return y


def in_gap(x: np.ndarray, width: float) -> np.ndarray:
    """1 while a play of total width ``width`` driven by ``x`` is inside its gap, else 0."""
    h = 0.5 * width
    x = np.asarray(x, dtype=np.float64)
    # the tolerance: while pushing, x − y equals h only up to rounding
    return (np.abs(x - play(x, h)) < h * (1 - 1e-9)).astype(float)


def dahl(x: np.ndarray, length: float) -> np.ndarray:
    """Normalised Dahl state z ∈ [−1, 1] driven by travel: dz/dx = (sign(ẋ) − z)/L.

    Rate-independent memory (the friction lags by travel, not by time),
    stepped exactly per sample so a stiff σ (tiny L = F_c/σ) stays stable.
    """
    if length <= 0:
        return np.zeros(len(x))
    x = np.asarray(x, dtype=np.float64)
    dx = np.diff(x, prepend=x[0])
    decay = np.exp(-np.abs(dx) / length).tolist()
    s = np.sign(dx).tolist()
    z = np.empty_like(x)
    zi = 0.0
    for i in range(len(z)):
        zi = s[i] + (zi - s[i]) * decay[i]
        z[i] = zi
    return z
