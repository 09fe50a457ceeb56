"""Fisher information of a chosen set of sensors and tests.

With white sensor noise the information on θ = ln(parameters) of a set of
tests is Σ JᵀJ/σ² over every logged sample (the analysis stores it already
divided by σ², at the analysis rate; ``rate_factor`` scales it to the
campaign's logging rate). A sensor offset is one unknown per sensor for
the whole campaign (eps-model.md), so it is eliminated per sensor over all
tests together: Σ JᵀJ − (Σ J)(Σ J)ᵀ/n, the Schur complement of the offset.
Coordinates are relative (ln θ): a standard error of 0.1 is 10 %.

The identification drives its twin with the measured angle, smoothed: the
angle's noise leaves a slow error on the input that no number of samples
averages away within a test (errors in variables). Its effect on the
estimate is propagated as a bias per test, δθ = F⁻¹·Σₙ Jᵀe, with e the twin's
output error from noisy-angle draws (``Sensitivity.input_error``); tests are
independent, so the covariance becomes F⁻¹ + F⁻¹·B·F⁻¹ with B = Σ_tests E[(ΣJᵀe)(ΣJᵀe)ᵀ].
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from mbst.plan.config import PlanConfig
from mbst.plan.sensitivity import Sensitivity
from mbst.plan.sensors import SENSORS

RIDGE = 1e-9  # information (1/σ²) added so that an unseen parameter has a finite, huge σ


def logged_mask(sens: Sensitivity) -> np.ndarray:
    """(C, S): whether sensor s is logged in the scenario of cell c (it moves there)."""
    return np.array([[cell.scenario in SENSORS[s].exists_in for s in sens.sensors]
                     for cell in sens.cells])


def per_sensor_sums(sens: Sensitivity, counts: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Σ over tests (with multiplicity ``counts`` (C,)) of Gram, column sums and samples.

    Returns (K, S, P, P), (K, S, P), (S,).
    """
    counts = np.asarray(counts, float)
    a = np.einsum("c,kcspq->kspq", counts, sens.gram)
    b = np.einsum("c,kcsp->ksp", counts, sens.colsum)
    n = (counts[:, None] * sens.n_samples[:, None] * logged_mask(sens)).sum(axis=0)
    return a, b, n


def offset_eliminated(a: np.ndarray, b: np.ndarray, n: np.ndarray) -> np.ndarray:
    """Per-sensor information with the campaign-wide offset removed (Schur complement)."""
    nn = np.where(n > 0, n, 1.0)
    return a - np.einsum("...sp,...sq->...spq", b, b) / nn[..., :, None, None]


def fisher(sens: Sensitivity, sensors: list[str] | np.ndarray, counts: np.ndarray,
           rate_factor: float) -> np.ndarray:
    """(K, P, P) Fisher information at every sweep point of a sensor set and test counts."""
    mask = _sensor_mask(sens, sensors)
    a, b, n = per_sensor_sums(sens, counts)
    eff = offset_eliminated(a, b, n)
    return rate_factor * np.einsum("s,kspq->kpq", mask.astype(float), eff)


def _sensor_mask(sens: Sensitivity, sensors) -> np.ndarray:
    sensors = list(sensors)
    if sensors and isinstance(sensors[0], (bool, np.bool_)):
        return np.asarray(sensors, bool)
    return np.array([s in sensors for s in sens.sensors])


def covariance(f: np.ndarray, b: np.ndarray | None = None) -> np.ndarray:
    """Inverse of the information (batched), with a tiny ridge for unseen directions.

    With ``b`` (the input-error term, same shape) the sandwich F⁻¹ + F⁻¹·B·F⁻¹.
    """
    p = f.shape[-1]
    cov = np.linalg.inv(f + RIDGE * np.eye(p))
    if b is not None:
        cov = cov + cov @ b @ cov
    return cov


def relative_std(f: np.ndarray, b: np.ndarray | None = None) -> np.ndarray:
    """Predicted relative standard errors (…, P) from information (…, P, P) in ln θ."""
    return np.sqrt(np.maximum(np.diagonal(covariance(f, b), axis1=-2, axis2=-1), 0.0))


def input_error_per_test(sens: Sensitivity, sensors) -> np.ndarray | None:
    """(K, C, P, P): E[(Σ Jᵀe)(Σ Jᵀe)ᵀ] of one test of each cell with these sensors.

    Summed over the logged sensors inside a draw first: one angle error drives all
    channels of a test at once. Campaign-rate sums are ``rate_factor`` × the
    analysis-rate ones; the caller scales by its square.
    """
    if sens.input_error is None:
        return None
    mask = _sensor_mask(sens, sensors)[None, :] & logged_mask(sens)  # (C, S)
    v = np.einsum("kcsmp,cs->kcmp", sens.input_error, mask.astype(float))
    return np.einsum("kcmp,kcmq->kcpq", v, v) / max(v.shape[2], 1)


def input_error_term(sens: Sensitivity, sensors, counts: np.ndarray,
                     rate_factor: float) -> np.ndarray | None:
    """(K, P, P): B of a plan (its sensors, its tests with multiplicity ``counts``)."""
    q = input_error_per_test(sens, sensors)
    if q is None:
        return None
    return rate_factor**2 * np.einsum("c,kcpq->kpq", np.asarray(counts, float), q)


def bits_gained(f: np.ndarray, prior_info: np.ndarray) -> np.ndarray:
    """Information gained over the prior of the ranges, in bits: ½·log₂ det(I + Λ₀⁻¹F)."""
    _, ld = np.linalg.slogdet(f + np.diag(prior_info))
    return 0.5 * (ld - np.sum(np.log(prior_info))) / np.log(2.0)


def prior_information(cfg: PlanConfig) -> np.ndarray:
    """1/σ² of a uniform prior in ln θ over each range."""
    return np.array([1.0 / u.prior_std_log**2 for u in cfg.unknowns])


@dataclass
class Identifiability:
    """What the information of a set says, at the centre and worst over the sweep."""

    relative_std: np.ndarray  # (K, P)
    worst_relative_std: np.ndarray  # (P,)
    correlation: np.ndarray  # (P, P) at the centre of the ranges
    condition_number: float  # of the information at the centre (ln θ coordinates)
    bits: float  # mean over the sweep
    identifiable: np.ndarray  # (P,) bool: worst σ ≤ target

    # per unknown above the target: the combination with its correlated partners that the
    # information does pin down (``weak_combinations``)
    combinations: list[dict] = field(default_factory=list)

    def max_abs_correlation(self) -> float:
        c = np.abs(self.correlation - np.diag(np.diag(self.correlation)))
        return float(c.max()) if c.size else 0.0


# |correlation| beyond which another unknown counts as a partner of one above the target
PARTNER_CORRELATION = 0.7


def identifiability(f: np.ndarray, target: float, prior_info: np.ndarray,
                    b: np.ndarray | None = None) -> Identifiability:
    """Standard errors, correlations and conditioning of information ``f`` (K, P, P).

    ``b``: the input-error term (``input_error_term``), if counted.
    """
    cov = covariance(f, b)
    rel = np.sqrt(np.maximum(np.diagonal(cov, axis1=-2, axis2=-1), 0.0))
    c0 = cov[0]
    d = np.sqrt(np.maximum(np.diag(c0), 1e-300))
    corr = c0 / np.outer(d, d)
    ev = np.linalg.eigvalsh(f[0])
    cond = float(ev[-1] / ev[0]) if ev[0] > 0 else float("inf")
    worst = rel.max(axis=0)
    return Identifiability(rel, worst, corr, cond, float(np.mean(bits_gained(f, prior_info))),
                           worst <= target, weak_combinations(cov, rel, target))


def weak_combinations(cov: np.ndarray, rel: np.ndarray, target: float,
                      partner_correlation: float = PARTNER_CORRELATION) -> list[dict]:
    """What the information says about each unknown it leaves above ``target``.

    At the sweep point where the unknown is worst, its partner is the other
    unknown above the target most correlated with it, beyond
    ``partner_correlation`` (those within the target count as known); the
    best-determined combination of the pair is the covariance's eigenvector of
    least variance, a product of powers θ_a·θ_b^x (ln θ coordinates). For two
    terms of one sum (motor and rack viscous friction, both at the pinion's
    speed) x is the ratio of their shares: the plan identifies the sum, not
    each term.
    """
    out = []
    above = rel.max(axis=0) > target
    for j in np.flatnonzero(above):
        k = int(np.argmax(rel[:, j]))
        c = cov[k]
        d = np.sqrt(np.maximum(np.diag(c), 1e-300))
        corr = c[j] / (d[j] * d)
        # the partner: the unknown above the target most correlated with it (the others
        # within the target count as known); a pair reads as a sum's shares
        group = [j] + [i for i in np.argsort(-np.abs(corr))
                       if i != j and above[i] and abs(corr[i]) >= partner_correlation][:1]
        rec = {"index": int(j), "relative_std": float(rel[k, j]), "sweep_point": k,
               "partners": {int(i): float(corr[i]) for i in group[1:]}}
        if len(group) > 1:
            sub = c[np.ix_(group, group)]
            lam, vec = np.linalg.eigh(sub)
            w = vec[:, 0] / vec[0, 0]
            rec["exponents"] = {int(i): float(x) for i, x in zip(group, w, strict=True)}
            rec["combination_relative_std"] = float(np.sqrt(max(w @ sub @ w, 0.0)))
        out.append(rec)
    return out
