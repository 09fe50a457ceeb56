"""A test as the rig would log it if the model were right: what "noise alone" looks like.

The rig is driven by the true input; the model by the measured one, smoothed. A
replicate is simulated from the model on a clean input and gets every channel's
noise at the level measured on it — the input channel's too, which the model is then
driven by — and goes through the very preprocessing a logged test gets. The test
designer uses it to predict a test not yet run (``plan/resolve/candidates.py``).
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from mbst.core.filtering import filtered_noise_gain, white_noise_std
from mbst.core.model import ModelDefinition
from mbst.identify.fitting import PreparedTest, prepare_frame
from mbst.io.campaign import TestSpec


def logged_like(model: ModelDefinition, spec: TestSpec, time_s: np.ndarray,
                true_input: np.ndarray, p: np.ndarray, channels: tuple[str, ...],
                input_channel: str, noise: dict[str, float], tau_s: float,
                rng: np.random.Generator) -> PreparedTest:
    """The model ``p`` on ``true_input``, logged with raw white noise ``noise`` per channel."""
    frame = pd.DataFrame({"time_s": time_s, input_channel: true_input})
    for ch in channels:
        if ch not in frame:
            frame[ch] = 0.0
    # the rig: no input noise and no input smoothing (a window of one sample)
    rig = prepare_frame(model, frame, spec, 0.0, input_window_s=0.0)
    sim = model.simulate_batch(rig, p[None])[0]
    frame[input_channel] = true_input + noise.get(input_channel, 0.0) * rng.standard_normal(
        len(time_s))
    for ch in channels:
        if ch != input_channel:
            frame[ch] = sim[ch] + noise.get(ch, 0.0) * rng.standard_normal(len(time_s))
    return prepare_frame(model, frame, spec, tau_s)


def raw_noise(frames: dict[str, pd.DataFrame], tests: list[PreparedTest], input_channel: str
              ) -> dict[str, float]:
    """Each channel's white-noise rms before the filter, the input's too (median over tests).

    The input matters most: on a blocked column its noise through the torsion bar is
    the floor (six times the torque sensor's own).
    """
    per: dict[str, list[float]] = {}
    for pt in tests:
        gain = filtered_noise_gain(pt.dt_s, pt.tau_s)
        for ch, v in pt.noise.items():
            per.setdefault(ch, []).append(v / gain if gain > 0 else v)
        raw = frames[pt.id][input_channel].to_numpy(float)
        per.setdefault(input_channel, []).append(white_noise_std(raw, pt.dt_s))
    return {ch: float(np.median(v)) for ch, v in per.items()}
