"""Exponential filtering (seed 000) and the signals derived from it.

The same first-order filter runs on every measured channel and on every
simulated twin before any comparison, so the phase lag is the same on both
sides (eps-model.md, "Preprocessing").
"""

from __future__ import annotations

import math

import numpy as np
from scipy.signal import butter, lfilter, savgol_coeffs, savgol_filter, sosfiltfilt

# Width of the window that smooths the measured driving input (steering angle) into
# the model's input and its rate (eps-model.md, "Preprocessing").
INPUT_WINDOW_S = 0.1


def filter_alpha(dt_s: float, tau_s: float) -> float:
    """α = 1 − exp(−Δt/τ); τ = 0 means no filtering (α = 1)."""
    if tau_s <= 0:
        return 1.0
    return 1.0 - math.exp(-dt_s / tau_s)


def exponential_filter(x: np.ndarray, dt_s: float, tau_s: float) -> np.ndarray:
    """y[n] = y[n−1] + α·(x[n] − y[n−1]), started at y[0] = x[0] (no start-up transient).

    Works along the first axis, so a (samples, channels) array filters every
    channel identically.
    """
    x = np.asarray(x, dtype=np.float64)
    a = filter_alpha(dt_s, tau_s)
    if a >= 1.0:
        return x.copy()
    # y[n] − (1−α)·y[n−1] = α·x[n], with the initial condition y[−1] = x[0]
    zi = (1.0 - a) * x[:1]
    y, _ = lfilter([a], [1.0, -(1.0 - a)], x, axis=0, zi=zi)
    return y


def filtered_noise_gain(dt_s: float, tau_s: float) -> float:
    """Standard deviation of the filtered output per unit of white input noise: √(α/(2−α))."""
    a = filter_alpha(dt_s, tau_s)
    return math.sqrt(a / (2.0 - a))


def cubic_window(n_samples: int, dt_s: float, window_s: float) -> int | None:
    """Odd length of a local-cubic (Savitzky–Golay) window, or None if the signal is too short."""
    n = int(round(window_s / dt_s)) | 1
    return n if 5 <= n < n_samples else None


def white_noise_std(x: np.ndarray, dt_s: float, window_s: float = 0.1) -> float:
    """Sensor-noise level of a sampled signal, from what a local cubic leaves out.

    The robust spread (MAD) of ``x`` minus its Savitzky–Golay fit over
    ``window_s``, corrected for the share of the noise the fit keeps. Smooth
    signal content and rare steps do not count; 0 for a clean signal.
    """
    x = np.asarray(x, float)
    n = cubic_window(len(x), dt_s, window_s)
    if n is None:
        return 0.0
    left = x - savgol_filter(x, n, 3, mode="interp")
    h0 = savgol_coeffs(n, 3)[n // 2]
    return 1.4826 * float(np.median(np.abs(left - np.median(left)))) / math.sqrt(1.0 - h0)



def signal_resolution(x: np.ndarray, dt_s: float) -> float:
    """What a logged signal can resolve: the larger of its white-noise level and its
    smallest step (a quantised channel at rest has no noise a cubic sees, only steps)."""
    x = np.asarray(x, float)
    steps = np.abs(np.diff(x))
    steps = steps[steps > 0]
    return max(white_noise_std(x, dt_s), float(steps.min()) if steps.size else 0.0)

def filter_channels(
    channels: dict[str, np.ndarray], dt_s: float, tau_s: float
) -> dict[str, np.ndarray]:
    """The same exponential filter on every channel of a dict."""
    return {k: exponential_filter(v, dt_s, tau_s) for k, v in channels.items()}


def angular_velocity(time_s: np.ndarray, filtered_angle_rad: np.ndarray) -> np.ndarray:
    """Rate of the filtered measured angle.

    Central differences (second order, no extra phase lag) of the already
    filtered angle: the exponential filter has removed the sensor noise that
    differentiation would amplify, and the column friction sees the same
    lagged speed in the model as in the filtered torque it is compared with.
    """
    return np.gradient(np.asarray(filtered_angle_rad, dtype=np.float64), time_s)


def motion_reversals(rate: np.ndarray, deadband: float = 0.05) -> np.ndarray:
    """Indices where the steering direction changes, ignoring jitter while at rest."""
    rate = np.asarray(rate, float)
    big = np.abs(rate) > deadband * np.max(np.abs(rate))
    if not big.any():
        return np.zeros(0, int)
    sign = np.where(big, np.sign(rate), 0.0)
    idx = np.flatnonzero(sign)
    changes = idx[1:][np.diff(sign[idx]) != 0]
    return changes


# the fast part of a signal: above the drive (≤ 1 Hz and its first harmonics), below a
# stick-slip's sawtooth or a ripple at the motor's speed
FAST_HZ = 3.0


def highpass(y: np.ndarray, dt_s: float, cutoff_hz: float = FAST_HZ) -> np.ndarray:
    """The part of ``y`` above ``cutoff_hz`` (4th-order Butterworth, zero phase)."""
    sos = butter(4, cutoff_hz, "highpass", fs=1.0 / dt_s, output="sos")
    return sosfiltfilt(sos, np.asarray(y, float))
