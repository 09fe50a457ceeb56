"""What a real sensor does to a signal: lag, wandering noise, quantisation, warm-up drift.

A bench that only adds white noise to the model's own output lets discovery
pass by sharing the model's assumptions (eps-model.md, "Sizes production rigs
show, and what real data adds"). These are the sensor realities a bench adds
on top, for any rig family.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.signal import lfilter

from mbst.core.filtering import exponential_filter


@dataclass(frozen=True)
class SensorRealities:
    """How one channel is measured beyond white noise (all off by default).

    ``noise_ar1``: the noise's AR(1) coefficient per sample (0: white; 0.95
    at 500 Hz wanders over ~40 ms) at the same rms. ``lag_s``: the sensor's
    own first-order filter. ``quantum``: the resolution (an encoder's count,
    an ADC's step). ``drift``: the offset's warm-up change in units of the
    noise rms, reached with time constant ``drift_tau_s`` of campaign time.
    ``eccentricity``: an angle sensor's error once per revolution of what it
    reads (a code disc mounted off its shaft's axis), ``e·sin(θ + phase)`` in
    the channel's unit.
    """

    noise_ar1: float = 0.0
    lag_s: float = 0.0
    quantum: float = 0.0
    drift: float = 0.0
    drift_tau_s: float = 120.0
    eccentricity: float = 0.0
    eccentricity_phase: float = 1.0


def coloured_noise(n: int, rms: float, ar1: float, rng: np.random.Generator) -> np.ndarray:
    """Stationary AR(1) noise of the given rms: e[k] = a·e[k−1] + √(1−a²)·rms·w[k]."""
    w = rng.standard_normal(n)
    if ar1 <= 0.0:
        return rms * w
    if ar1 >= 1.0:
        raise ValueError(f"the noise's AR(1) coefficient must be below 1, got {ar1}")
    gain = math.sqrt(1.0 - ar1 * ar1)
    e, _ = lfilter([gain * rms], [1.0, -ar1], w, zi=[ar1 * rms * w[0]])
    return e


def measure(clean: np.ndarray, time_s: np.ndarray, rms: float, rng: np.random.Generator,
            realities: SensorRealities = SensorRealities(),
            campaign_time_s: float = 0.0) -> np.ndarray:
    """The logged channel of a clean signal: lag, drift, noise, then the sensor's resolution.

    ``campaign_time_s`` is when the test starts in the campaign's running time
    (warm-up drift goes on across tests).
    """
    t = np.asarray(time_s, dtype=np.float64)
    dt = float((t[-1] - t[0]) / max(len(t) - 1, 1))
    y = exponential_filter(clean, dt, realities.lag_s) if realities.lag_s > 0 else np.array(clean)
    if realities.eccentricity:
        y = y + realities.eccentricity * np.sin(np.asarray(clean) + realities.eccentricity_phase)
    if realities.drift:
        elapsed = campaign_time_s + (t - t[0])
        y = y + realities.drift * rms * (1.0 - np.exp(-elapsed / realities.drift_tau_s))
    y = y + coloured_noise(len(t), rms, realities.noise_ar1, rng)
    if realities.quantum > 0:
        y = realities.quantum * np.round(y / realities.quantum)
    return y
