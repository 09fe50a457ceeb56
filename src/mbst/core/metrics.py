"""Correlation metrics between a measured channel and its simulated twin."""

from __future__ import annotations

import numpy as np


def fit_percent(y: np.ndarray, y_hat: np.ndarray) -> float:
    """FIT % = 100·(1 − ‖y − ŷ‖/‖y − mean(y)‖) (campaign-format.md).

    NaN when the measurement is constant or the prediction is not finite (a
    model that blew up has no FIT, not −∞).
    """
    y, y_hat = np.asarray(y, float), np.asarray(y_hat, float)
    d = np.linalg.norm(y - y.mean())
    if d == 0.0 or not np.all(np.isfinite(y_hat)):
        return float("nan")
    return float(100.0 * (1.0 - np.linalg.norm(y - y_hat) / d))


def error_scores(y: np.ndarray, y_hat: np.ndarray) -> dict[str, float]:
    """FIT %, RMSE (in the channel's unit) and NRMSE (RMSE over the measured range), the
    three numbers published benchmarks report."""
    y, y_hat = np.asarray(y, float), np.asarray(y_hat, float)
    rmse = float(np.sqrt(np.mean((y - y_hat) ** 2)))
    span = float(np.ptp(y))
    return {"fit_percent": fit_percent(y, y_hat), "rmse": rmse,
            "nrmse": rmse / span if span > 0 else float("nan")}


def correlation_row(y: np.ndarray, y_hat: np.ndarray) -> dict[str, float]:
    """FIT %, NRMSE (rms error over the measured range), Pearson r, R², max |error|."""
    y = np.asarray(y, float)
    y_hat = np.asarray(y_hat, float)
    e = y - y_hat
    rng = float(np.ptp(y))
    ss_tot = float(np.sum((y - y.mean()) ** 2))
    with np.errstate(invalid="ignore", divide="ignore"):
        r = float(np.corrcoef(y, y_hat)[0, 1]) if np.std(y) > 0 and np.std(y_hat) > 0 else np.nan
    return {
        "fit_percent": fit_percent(y, y_hat),
        "nrmse": float(np.sqrt(np.mean(e**2)) / rng) if rng > 0 else float("nan"),
        "pearson_r": r,
        "r2": float(1.0 - np.sum(e**2) / ss_tot) if ss_tot > 0 else float("nan"),
        "max_abs_error": float(np.max(np.abs(e))),
    }
