"""The preprocessing step made visible: what the fit actually compares.

Identification and discovery filter every measured channel (and every
simulated twin) with the same exponential filter and drive the model with an
input derived from the measurement (``fitting.prepare_test``). This module
writes that prepared data out, so an engineer can inspect it and plot it
with their own tools:

- ``campaign/``: a valid campaign (same tests, roles and ``known``) whose
  channels are the *filtered* measurements, plus the model's driving input as
  extra columns ``model_input`` and ``model_input_rate``. Its ``campaign.yaml``
  says ``preprocessed: {filter: exponential, tau_s: …}``, and fitting it again
  with τ > 0 is refused: the measurement would be filtered twice, its twin once.
- ``noise.csv`` / ``preprocess.md``: per test and channel, the sensor noise
  before and after the filter and the signal's spread (how far above the
  noise each channel's information lies).
- ``figures/filter.png``: raw vs filtered around a reversal, per channel.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from mbst.core.filtering import exponential_filter, filtered_noise_gain
from mbst.identify.fitting import PREPROCESSED_KEY, PreparedTest, prepare_test
from mbst.io.campaign import Campaign, write_campaign
from mbst.io.outputs import atomic_output_dir, write_markdown


def preprocessed_frame(campaign: Campaign, pt: PreparedTest) -> pd.DataFrame:
    """Every channel of one test through the filter, and the input the model is driven by.

    Output channels are exactly what the fit compares (``pt.measured``); the other
    channels of the family (the steering angle, for one) get the same filter, so the
    file is a valid campaign test with every channel treated alike.
    """
    family = campaign.family
    raw = campaign.frame(pt.id)
    cols: dict[str, np.ndarray] = {family.time_channel: pt.time_s}
    for ch in family.channels:
        if ch.name == family.time_channel or ch.name not in raw.columns:
            continue
        cols[ch.name] = pt.measured.get(ch.name)
        if cols[ch.name] is None:
            cols[ch.name] = exponential_filter(raw[ch.name].to_numpy(float), pt.dt_s, pt.tau_s)
    cols["model_input"] = pt.input_signal
    cols["model_input_rate"] = pt.input_rate
    return pd.DataFrame(cols)


def noise_table(tests: list[PreparedTest]) -> pd.DataFrame:
    """Sensor noise before/after the filter and the signal spread, per test and channel."""
    rows = []
    for pt in tests:
        for ch, y in pt.measured.items():
            filtered_noise = float(pt.noise.get(ch, 0.0))
            gain = filtered_noise_gain(pt.dt_s, pt.tau_s)
            raw_noise = filtered_noise / gain if gain > 0 else 0.0
            spread = float(np.std(y))
            rows.append({
                "test": pt.id,
                "role": pt.spec.role,
                "channel": ch,
                "noise_std_raw": raw_noise,
                "noise_std_filtered": filtered_noise,
                "signal_std": spread,
                "signal_to_noise": spread / filtered_noise if filtered_noise > 0 else float("inf"),
            })
    return pd.DataFrame(rows)


def write_preprocessed(campaign: Campaign, out_dir: str | Path, tau_s: float,
                       figures: bool = True) -> Path:
    """Write the preprocessed campaign, its noise table and figure into ``out_dir`` atomically.

    Parameters
    ----------
    campaign
        A validated campaign (raw measurements).
    out_dir
        Output folder; replaced whole once everything is written.
    tau_s
        Time constant of the exponential filter, as given to ``mbst identify``.
    figures
        Also draw ``figures/filter.png``.
    """
    tests = [prepare_test(campaign, spec, tau_s) for spec in campaign.tests]
    table = noise_table(tests)
    with atomic_output_dir(out_dir) as tmp:
        extra = dict(campaign.extra)
        extra[PREPROCESSED_KEY] = {"filter": "exponential", "tau_s": float(tau_s),
                                   "from": str(campaign.path)}
        write_campaign(
            tmp / "campaign", name=campaign.name, system=campaign.system, known=campaign.known,
            tests=[(pt.spec, preprocessed_frame(campaign, pt)) for pt in tests],
            extra=extra, priors=campaign.priors,
        )
        table.to_csv(tmp / "noise.csv", index=False, float_format="%.6g")
        write_markdown(tmp / "preprocess.md", _markdown(campaign, tau_s, table))
        if figures:
            from mbst.report.plots import filter_effect

            name = campaign.family.input_channel
            inputs = {pt.id: (name, campaign.frame(pt.id)[name].to_numpy(float))
                      for pt in tests if name in campaign.frame(pt.id).columns}
            filter_effect(tests, tmp / "figures" / "filter.png", measured_inputs=inputs)
    return Path(out_dir)


def _markdown(campaign: Campaign, tau_s: float, table: pd.DataFrame) -> str:
    lines = [
        f"# Preprocessing: {campaign.name}",
        "",
        f"Exponential filter y[n] = y[n−1] + α·(x[n] − y[n−1]), τ = {tau_s * 1e3:g} ms, on every "
        "measured channel and on every simulated twin (same phase lag on both sides).",
        "The model is driven by `model_input` (the measured input, prepared as the model "
        "family says) and `model_input_rate`.",
        "",
        "Noise is the white sensor noise estimated from what a 0.1 s local cubic leaves out; "
        "`signal/noise` is the filtered channel's spread over its filtered noise. On fast "
        "tests the cubic also leaves out real fast dynamics, so the estimate reads high there; "
        "the slow tests give the sensor's own noise.",
        "",
        "| test | role | channel | noise raw | noise filtered | signal std | signal/noise |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in table.itertuples(index=False):
        lines.append(f"| {r.test} | {r.role} | {r.channel} | {r.noise_std_raw:.3g} | "
                     f"{r.noise_std_filtered:.3g} | {r.signal_std:.3g} | "
                     f"{r.signal_to_noise:.0f} |")
    return "\n".join(lines) + "\n"
