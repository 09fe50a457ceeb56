"""Sparse regression (SINDy) for discovery, and a SINDy-only comparison model.

Two things live here:

``residual_regression``
    Regresses the base model's output residual (measured − simulated) on a
    physics-informed candidate library built from the base model's *own*
    internal signals. Every candidate stands for one (effect, component)
    catalogue key (the family's library, ``ModelDefinition.candidate_library``;
    for the EPS rig ``systems/eps/library.py``), so the variance its terms explain
    ranks the catalogue. The re-tuning the base model itself could do
    (Coulomb/viscous per friction element, stiffness misfits, the offset) is
    projected out first as a nuisance block: what is left is what the base
    structure cannot express.

    What it can and cannot see (demo campaign): effects whose discrepancy is
    phase-locked to the base model's motion are found and ranked first
    (position-dependent, load-dependent, asymmetric friction, limit stop, a
    planted Stribeck term). Reversal-memory effects (worm-gear or rack-pinion
    backlash, rack or motor presliding) explain nearly the same torque and
    tie in ``key_scores``: the gap width is recovered, the component is not
    decided here. Kinematically tied components (motor and rack without
    backlash) tie as well. Stribeck stick-slip on the rig is a limit cycle
    whose phase the base model does not share, so a linear regression on the
    model's signals explains almost none of it.

``SindyControlModel``
    A black-box comparison family: pysindy with control input on the raw
    measured channels, no physics at all, simulated open loop.
"""

from __future__ import annotations

import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import pysindy as ps
from scipy.integrate import odeint

from mbst.core.candidates import Candidate, CandidateLibrary, LibraryFactory
from mbst.core.filtering import exponential_filter
from mbst.discovery.data import TestResidual

__all__ = [
    "SindyControlModel",
    "SparseEvidence",
    "SparseTerm",
    "residual_regression",
]

def _filter_tau(t: TestResidual, channel: str) -> float:
    """The exponential-filter τ the channels went through, recovered from the twin.

    ``simulated[ch]`` is the filtered raw model output (plus a constant offset), so
    s[n] − s[n−1] = α·(raw[n] + offset − s[n−1]) is an exact linear relation; the
    candidates must see the same filter as the residual they explain.
    """
    others = sorted(set(t.states) & set(t.simulated) - {channel})
    for ch in (channel, *others):
        raw, sim = t.states.get(ch), t.simulated.get(ch)
        if raw is None or sim is None or len(sim) < 10:
            continue
        dy = np.diff(sim)
        dx = raw[1:] - sim[:-1]
        A = np.column_stack([dx, np.ones_like(dx)])
        coef, *_ = np.linalg.lstsq(A, dy, rcond=None)
        a = float(coef[0])
        fit_err = np.max(np.abs(A @ coef - dy))
        if 0 < a < 1 and fit_err <= 1e-6 * (np.max(np.abs(dy)) + 1e-300):
            return -t.dt_s / np.log(1 - a)
        if abs(a - 1) < 1e-9:
            return 0.0
    return 0.0


# --------------------------------------------------------------------------------------
# Residual regression
# --------------------------------------------------------------------------------------


@dataclass
class SparseTerm:
    """One selected candidate term.

    ``coefficient`` multiplies the raw candidate (in residual units per candidate
    unit); ``variance_share`` is the share of the pooled residual variance it
    explains at the point it joins (orthogonal contributions, so shares add up).
    """

    name: str
    key: str
    coefficient: float
    variance_share: float


@dataclass
class SparseEvidence:
    """What the sparse regression of one residual channel found.

    Shares are of the pooled, centred residual variance (the campaign-wide
    offset is never attributed).

    ``variance_explained``
        Share explained by the selected catalogue terms together: the evidence
        for a missing effect. Small on a campaign at the noise floor.
    ``nuisance_variance_explained``
        Share the forced base-model block explains (re-tuning the base model's
        own friction, stiffness and softer friction switches could do that).
    ``ranking``
        Catalogue keys with selected terms, by the summed share of their terms
        (joint selection, so among near-collinear keys the first one in takes
        the shared part). Empty or carrying little variance at the noise
        floor: reported as such, no choice is forced.
    ``key_scores``
        Each catalogue key's share when its candidates alone (up to three
        terms) are fitted after the nuisance block: order-free, and shows when
        two keys explain the same thing (a tie in torque alone).
    ``explained_rms``
        ``sqrt(variance_explained)·residual_rms``, in the channel's unit.
    """

    channel: str
    terms: list[SparseTerm]
    variance_explained: float
    nuisance_variance_explained: float
    ranking: list[tuple[str, float]]
    key_scores: dict[str, float]
    residual_rms: float
    n_samples: int
    n_candidates: int
    test_ids: list[str] = field(default_factory=list)
    optimizer: str = "frols"

    @property
    def total_variance_explained(self) -> float:
        """Nuisance block plus catalogue terms."""
        return self.nuisance_variance_explained + self.variance_explained

    @property
    def explained_rms(self) -> float:
        """RMS of the part the catalogue terms explain, in the channel's unit."""
        return float(np.sqrt(max(self.variance_explained, 0.0)) * self.residual_rms)

    def top(self, n: int = 3) -> list[tuple[str, float]]:
        """The ``n`` best-ranked catalogue keys with their variance shares."""
        return self.ranking[:n]

    def to_dict(self) -> dict:
        """JSON-ready view."""
        return {
            "channel": self.channel,
            "optimizer": self.optimizer,
            "variance_explained": self.variance_explained,
            "nuisance_variance_explained": self.nuisance_variance_explained,
            "total_variance_explained": self.total_variance_explained,
            "explained_rms": self.explained_rms,
            "residual_rms": self.residual_rms,
            "n_samples": self.n_samples,
            "n_candidates": self.n_candidates,
            "tests": list(self.test_ids),
            "ranking": [{"key": k, "variance_share": v} for k, v in self.ranking],
            "key_scores": dict(self.key_scores),
            "terms": [vars(t).copy() for t in self.terms],
        }


def _orthonormal_basis(A: np.ndarray, rtol: float = 1e-9) -> np.ndarray:
    """Orthonormal basis of the column space of ``A`` (rank-revealing, via SVD)."""
    if A.shape[1] == 0:
        return np.zeros((A.shape[0], 0))
    scale = np.linalg.norm(A, axis=0)
    A = A[:, scale > 0] / scale[scale > 0]
    if A.shape[1] == 0:
        return np.zeros((A.shape[0], 0))
    U, s, _ = np.linalg.svd(A, full_matrices=False)
    return U[:, s > rtol * s[0]]


def _forward_select(Z: np.ndarray, r0: np.ndarray, sst: float, signs: np.ndarray,
                    min_share: float, max_terms: int,
                    allowed: np.ndarray | None = None) -> tuple[list[int], list[float]]:
    """Sign-constrained forward orthogonal least squares (FROLS, Billings 2013).

    Each step adds the candidate with the largest error-reduction ratio whose
    coefficient has its physical sign and does not flip an earlier term's sign.
    The ERR at joining is the term's share of ``sst``.
    """
    n_feat = Z.shape[1]
    ok = np.ones(n_feat, bool) if allowed is None else allowed.copy()
    Zr, r = Z.copy(), r0.copy()
    norm0 = np.sum(Z**2, axis=0)
    chosen: list[int] = []
    shares: list[float] = []
    while len(chosen) < max_terms:
        nrm2 = np.sum(Zr**2, axis=0)
        c = Zr.T @ r
        valid = ok & (nrm2 > 1e-8 * np.maximum(norm0, 1e-300))
        err = np.where(valid, c**2 / np.where(valid, nrm2, 1.0) / sst, 0.0)
        # by Frisch–Waugh–Lovell, sign(c) is the sign the new term's OLS coefficient gets
        err[(signs != 0) & (np.sign(c) != signs)] = 0.0
        j = int(np.argmax(err))
        if err[j] < min_share:
            break
        cols = chosen + [j]
        coef = np.linalg.lstsq(Z[:, cols], r0, rcond=None)[0]
        if np.any(signs[cols] * coef < 0):
            ok[j] = False  # it would flip a physical sign: not admissible
            continue
        chosen.append(j)
        shares.append(float(err[j]))
        q = Zr[:, j] / np.sqrt(nrm2[j])
        r = r - q * (q @ r)
        Zr = Zr - np.outer(q, q @ Zr)
        ok[j] = False
    return chosen, shares


def _stlsq_select(Z: np.ndarray, r0: np.ndarray, sst: float, signs: np.ndarray,
                  min_share: float, max_terms: int) -> tuple[list[int], list[float]]:
    """pysindy STLSQ on unit-norm columns, wrong-sign terms removed, then ERR attribution."""
    allowed = np.ones(Z.shape[1], bool)
    # least squares only sees Zᵀ Z and Zᵀ y: the square system (R, Qᵀy) of a thin QR has
    # the same solutions and is ~70x smaller than the pooled samples
    Q, R = np.linalg.qr(Z)
    y = Q.T @ r0 / np.sqrt(sst)
    support = np.zeros(Z.shape[1], bool)
    for _ in range(Z.shape[1]):
        opt = ps.STLSQ(threshold=np.sqrt(min_share), alpha=1e-6, max_iter=50, unbias=True)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # "sparsity parameter too big" is a valid answer
            opt.fit(R[:, allowed], y)
        coef = np.zeros(Z.shape[1])
        coef[allowed] = opt.coef_[0]
        bad = (signs != 0) & (np.sign(coef) == -signs) & (coef != 0)
        support = coef != 0
        if not bad.any():
            break
        allowed &= ~bad
    # attribute by greedy orthogonal order within the STLSQ support
    return _forward_select(Z, r0, sst, np.zeros_like(signs), 0.0,
                           min(max_terms, int(support.sum())), allowed=support)


def _pooled_design(tests: list[TestResidual], channel: str, lib: CandidateLibrary,
                   rate_hz: float) -> tuple[np.ndarray, np.ndarray]:
    Xs, ys = [], []
    for t in tests:
        tau = _filter_tau(t, channel)
        # filter like the residual (compare like with like), then decimate to ~rate_hz
        F = exponential_filter(lib.transform(t), t.dt_s, tau)
        k = max(1, int(round(1.0 / (rate_hz * t.dt_s))))
        Xs.append(F[::k])
        ys.append(np.asarray(t.residual(channel), dtype=np.float64)[::k])
    return np.vstack(Xs), np.concatenate(ys)


@dataclass
class _Design:
    """The pooled, centred regression with the nuisance block projected out."""

    Xc: np.ndarray  # centred candidate columns
    yc: np.ndarray  # centred residual
    nuis: np.ndarray  # which candidates are nuisance
    signs: np.ndarray
    sst: float
    # set by ``project``:
    r0: np.ndarray | None = None  # residual after the nuisance projection
    Z: np.ndarray | None = None  # unit-norm effect columns after the projection
    eff_idx: np.ndarray | None = None  # candidate index of each column of Z
    nuisance_share: float = 0.0

    def project(self) -> None:
        U = _orthonormal_basis(self.Xc[:, self.nuis])
        self.r0 = self.yc - U @ (U.T @ self.yc)
        self.nuisance_share = 1.0 - float(self.r0 @ self.r0) / self.sst
        E = self.Xc[:, ~self.nuis]
        Ep = E - U @ (U.T @ E)
        n0, n1 = np.linalg.norm(E, axis=0), np.linalg.norm(Ep, axis=0)
        # keep candidates with something left after the nuisance projection
        keep = (n0 > 0) & (n1 > 1e-6 * np.maximum(n0, 1e-300))
        self.eff_idx = np.flatnonzero(~self.nuis)[keep]
        self.Z = Ep[:, keep] / n1[keep]

    def coefficients(self, sel: list[int]) -> np.ndarray:
        """Coefficients in the candidates' own units: joint OLS with the nuisance block."""
        if not sel:
            return np.zeros(0)
        A = np.column_stack([self.Xc[:, self.nuis], self.Xc[:, sel]])
        scale = np.linalg.norm(A, axis=0)
        scale[scale == 0] = 1.0  # columns span 1e-3 (m) to 1e3 (N): solve in unit-norm form
        beta = np.linalg.lstsq(A / scale, self.yc, rcond=None)[0] / scale
        return beta[int(self.nuis.sum()):]

    def key_scores(self, keys: list[str], min_share: float) -> dict[str, float]:
        """Order-free view: what each key's own candidates (≤ 3 terms) explain alone."""
        eff_keys = np.array([keys[i] for i in self.eff_idx])
        scores = {}
        for key in sorted(set(eff_keys.tolist())):
            _, s = _forward_select(self.Z, self.r0, self.sst, self.signs[self.eff_idx],
                                   min_share, 3, allowed=eff_keys == key)
            if s:
                scores[key] = float(sum(s))
        return dict(sorted(scores.items(), key=lambda kv: (-kv[1], kv[0])))


def residual_regression(tests: list[TestResidual], library: LibraryFactory,
                        channel: str | None = None, *, min_share: float = 0.01,
                        max_terms: int = 8, rate_hz: float = 100.0,
                        optimizer: str = "frols") -> SparseEvidence:
    """Sparse regression of the base model's residual on the family's candidate library.

    Parameters
    ----------
    tests
        Per-test residual data; only ``role == "identification"`` tests that carry
        ``channel`` are used (control tests never enter the fit).
    library
        The family's library, built from the pooled identification tests
        (``ModelDefinition.candidate_library``).
    channel
        Measured channel whose residual (measured − simulated) is explained;
        default: the channel the library's signs are worked out for.
    min_share
        A term joins only if it explains at least this share of the residual
        variance (1 % by default: far above what noise gets by chance with
        thousands of samples, so a clean campaign selects little or nothing).
    max_terms
        Most catalogue terms selected.
    rate_hz
        Decimation target; tests are pooled at about this rate.
    optimizer
        ``"frols"`` (sign-constrained forward orthogonal least squares, the
        default) or ``"stlsq"`` (pysindy's STLSQ on unit-norm columns with
        threshold √min_share, wrong-sign terms pruned).
    """
    channel = channel or getattr(library, "signed_channel", None)
    ident = _identification_tests(tests, channel, optimizer)
    lib = library(ident)
    d = _centred_design(ident, channel, lib, rate_hz)
    ids = [t.id for t in ident]
    rms = float(np.sqrt(d.sst / max(len(d.yc), 1)))
    empty = SparseEvidence(channel, [], 0.0, 0.0, [], {}, rms, len(d.yc), 0, ids, optimizer)
    if d.sst <= 0:
        return empty
    d.project()
    if d.Z.shape[1] == 0:
        empty.nuisance_variance_explained = d.nuisance_share
        return empty
    select = _forward_select if optimizer == "frols" else _stlsq_select
    chosen, shares = select(d.Z, d.r0, d.sst, d.signs[d.eff_idx], min_share, max_terms)
    cands = lib.candidates
    terms = _selected_terms(d, cands, chosen, shares)
    return SparseEvidence(
        channel=channel, terms=terms, variance_explained=float(sum(shares)),
        nuisance_variance_explained=d.nuisance_share, ranking=_key_ranking(terms),
        key_scores=d.key_scores([c.key for c in cands], min_share),
        residual_rms=rms, n_samples=len(d.yc), n_candidates=int(d.Z.shape[1]),
        test_ids=ids, optimizer=optimizer,
    )


def _identification_tests(tests: list[TestResidual], channel: str | None,
                          optimizer: str) -> list[TestResidual]:
    """The tests the regression reads (identification tests carrying ``channel``);
    refuses a campaign without any and an unknown optimizer."""
    ident = [t for t in tests if t.role == "identification" and channel in t.measured]
    if not ident:
        raise ValueError(f"no identification test carries channel '{channel}'")
    if optimizer not in ("frols", "stlsq"):
        raise ValueError(f"unknown optimizer '{optimizer}' (frols, stlsq)")
    return ident


def _centred_design(ident: list[TestResidual], channel: str, lib: CandidateLibrary,
                    rate_hz: float) -> _Design:
    """The pooled regression of ``channel``'s residual on the library, finite rows only,
    centred, with each candidate's nuisance flag and physical sign (not yet projected)."""
    X, y = _pooled_design(ident, channel, lib, rate_hz)
    good = np.all(np.isfinite(X), axis=1) & np.isfinite(y)
    cands = lib.candidates
    # the physical signs are worked out for the library's signed channel only
    signs = np.array([c.sign if channel == lib.signed_channel else 0 for c in cands])
    # centring is the campaign-wide offset: one bias for all tests, never attributed
    yc = y[good] - y[good].mean()
    return _Design(X[good] - X[good].mean(axis=0), yc, np.array([c.nuisance for c in cands]),
                   signs, float(yc @ yc))


def _selected_terms(d: _Design, cands: list[Candidate], chosen: list[int],
                    shares: list[float]) -> list[SparseTerm]:
    """The selected columns of ``d.Z`` as catalogue terms, coefficients in the
    candidates' own units, in the order they joined."""
    sel = [int(d.eff_idx[j]) for j in chosen]
    return [SparseTerm(cands[i].name, cands[i].key, float(b), s)
            for i, b, s in zip(sel, d.coefficients(sel), shares, strict=True)]


def _key_ranking(terms: list[SparseTerm]) -> list[tuple[str, float]]:
    """Catalogue keys by the summed variance share of their selected terms, largest first."""
    by_key: dict[str, float] = {}
    for term in terms:
        by_key[term.key] = by_key.get(term.key, 0.0) + term.variance_share
    return sorted(by_key.items(), key=lambda kv: (-kv[1], kv[0]))


# --------------------------------------------------------------------------------------
# SINDy-only comparison model
# --------------------------------------------------------------------------------------


class _SimulationFailed(RuntimeError):
    pass


@dataclass
class _ScenarioModel:
    dynamic: list[str]  # channels integrated by the SINDy-with-control model
    static: list[str]  # channels given by a static sparse map of the inputs
    x_mean: np.ndarray
    x_scale: np.ndarray
    u_scale: np.ndarray
    omega_eps: float
    sindy: ps.SINDy | None
    out_lib: ps.PolynomialLibrary | None
    out_coef: np.ndarray | None  # (n_static, n_features)
    out_mean: np.ndarray | None
    out_scale: np.ndarray | None


class SindyControlModel:
    """SINDy with control input on the raw measured channels (no physics).

    One model per scenario, trained on that scenario's identification tests
    (control tests are never used). The measured channels of the scenario
    (z-scored) are the state ``x`` of ``ẋ = Θ(x, u)·Ξ``, a ``ps.SINDy`` model
    with control ``u = [angle, ω, tanh(ω/ω_ε)]`` (ω_ε = 2 % of the rms speed: a
    generic smooth direction regressor), a polynomial library and STLSQ.
    Prediction simulates open loop from the test's first measured sample.

    In ``blocked_column`` the only channel, the torque, is an algebraic
    function of the input angle and speed (torsion bar + column friction, no
    state), so it is regressed directly: a static SINDy-style sparse map
    ``y = Θ(u)·ξ`` instead of an ODE that would only integrate drift.

    The default library is degree 1 (linear in x and u, with the tanh input):
    on the demo campaign degree 2 and 3 models blow up open loop on most
    tests (quadratic state terms escape in finite time), degree 1 stays
    stable. A simulation that blows up or fails anyway gives NaN arrays for
    that test and a reason in ``failures``; ``predict`` never raises for that.

    Parameters
    ----------
    degree
        Polynomial library degree.
    threshold, alpha
        STLSQ threshold and ridge weight (in z-scored units).
    rate_hz
        Training data are decimated to about this rate.
    max_rhs_evals
        Budget of right-hand-side evaluations per simulation.
    blowup
        A state beyond this many training standard deviations counts as blown up.
    use_pysindy_simulate
        Simulate with ``SINDy.simulate`` itself. pysindy 2.1 spends ~4 ms per
        ``predict`` call in input validation, so this takes minutes per test;
        the default integrates the same fitted coefficients directly (checked
        against ``SINDy.predict`` in the tests) with LSODA.
    """

    def __init__(self, degree: int = 1, threshold: float = 0.1, alpha: float = 1e-3,
                 rate_hz: float = 100.0, max_rhs_evals: int = 500_000, blowup: float = 50.0,
                 use_pysindy_simulate: bool = False):
        self.degree = degree
        self.threshold = threshold
        self.alpha = alpha
        self.rate_hz = rate_hz
        self.max_rhs_evals = max_rhs_evals
        self.blowup = blowup
        self.use_pysindy_simulate = use_pysindy_simulate
        self.models_: dict[str, _ScenarioModel] = {}
        self.failures: dict[str, str] = {}
        self.fit_time_s: float = float("nan")

    # -- fitting -----------------------------------------------------------------------
    @staticmethod
    def _inputs(t: TestResidual, omega_eps: float) -> np.ndarray:
        w = np.asarray(t.omega_rad_per_s, float)
        return np.column_stack([np.asarray(t.angle_rad, float), w, np.tanh(w / omega_eps)])

    def _stlsq(self) -> ps.STLSQ:
        return ps.STLSQ(threshold=self.threshold, alpha=self.alpha)

    def _fit_scenario(self, tests: list[TestResidual]) -> _ScenarioModel:
        chans = [c for c in tests[0].measured if all(c in t.measured for t in tests)]
        # one channel (the EPS blocked column: the torque): an algebraic map of u
        static = chans if len(chans) == 1 else []
        dynamic = [c for c in chans if c not in static]
        ks = [max(1, int(round(1.0 / (self.rate_hz * t.dt_s)))) for t in tests]
        w_all = np.concatenate([t.omega_rad_per_s for t in tests])
        omega_eps = 0.02 * float(np.sqrt(np.mean(w_all**2))) or 1e-3
        U = [self._inputs(t, omega_eps)[::k] for t, k in zip(tests, ks, strict=True)]
        u_scale = np.std(np.vstack(U), axis=0)
        u_scale[u_scale == 0] = 1.0
        U = [u / u_scale for u in U]
        T = [np.asarray(t.time_s, float)[::k] for t, k in zip(tests, ks, strict=True)]

        x_mean, x_scale = np.zeros(len(dynamic)), np.ones(len(dynamic))
        sindy = None
        if dynamic:
            raw = [np.column_stack([t.measured[c] for c in dynamic])[::k]
                   for t, k in zip(tests, ks, strict=True)]
            pooled = np.vstack(raw)
            x_mean, x_scale = pooled.mean(axis=0), pooled.std(axis=0)
            x_scale[x_scale == 0] = 1.0
            sindy = ps.SINDy(
                feature_library=ps.PolynomialLibrary(degree=self.degree),
                optimizer=self._stlsq(),
                differentiation_method=ps.SmoothedFiniteDifference(),
            )
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", UserWarning)  # "sparsity parameter too big"
                sindy.fit([(x - x_mean) / x_scale for x in raw], t=T, u=U)

        out_lib = out_coef = out_mean = out_scale = None
        if static:
            Y = np.vstack([np.column_stack([t.measured[c] for c in static])[::k]
                           for t, k in zip(tests, ks, strict=True)])
            out_mean, out_scale = Y.mean(axis=0), Y.std(axis=0)
            out_scale[out_scale == 0] = 1.0
            out_lib = ps.PolynomialLibrary(degree=self.degree)
            theta = np.asarray(out_lib.fit_transform(np.vstack(U)))
            opt = self._stlsq()
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", UserWarning)
                opt.fit(theta, (Y - out_mean) / out_scale)
            out_coef = np.asarray(opt.coef_)
        return _ScenarioModel(dynamic, static, x_mean, x_scale, u_scale, omega_eps, sindy,
                              out_lib, out_coef, out_mean, out_scale)

    def fit(self, tests: list[TestResidual]) -> SindyControlModel:
        """Fit one model per scenario on its identification tests (control tests unused).

        Parameters
        ----------
        tests
            Residual data of a campaign; only ``role == "identification"`` is used.

        Returns
        -------
        SindyControlModel
            ``self``, with ``models_`` per scenario and ``fit_time_s``.
        """
        t0 = time.perf_counter()
        self.models_ = {}
        self.failures = {}
        by_scen: dict[str, list[TestResidual]] = {}
        for t in tests:
            if t.role == "identification":
                by_scen.setdefault(t.scenario, []).append(t)
        for scen in sorted(by_scen):
            self.models_[scen] = self._fit_scenario(by_scen[scen])
        self.fit_time_s = time.perf_counter() - t0
        return self

    # -- prediction --------------------------------------------------------------------
    @staticmethod
    def _poly(powers: np.ndarray) -> Callable[[np.ndarray], np.ndarray]:
        """Θ(z) of a fitted ``PolynomialLibrary`` from its ``powers_`` (rows = terms)."""
        P = np.asarray(powers, dtype=float)
        return lambda z: np.prod(np.asarray(z)[..., None, :] ** P, axis=-1)

    def _simulate_states(self, m: _ScenarioModel, t: TestResidual, U: np.ndarray) -> np.ndarray:
        x0 = (np.array([t.measured[c][0] for c in m.dynamic]) - m.x_mean) / m.x_scale
        ts = np.asarray(t.time_s, float)
        t0, dt, last = float(ts[0]), float(t.dt_s), len(ts) - 2

        def u_at(tt: float) -> np.ndarray:
            # linear interpolation of the input on the uniform test grid
            k = min(max((tt - t0) / dt, 0.0), last + 1.0)
            i = min(int(k), last)
            return U[i] + (k - i) * (U[i + 1] - U[i])

        if self.use_pysindy_simulate:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                X = m.sindy.simulate(x0, ts, u=u_at, integrator_kws={
                    "method": "LSODA", "rtol": 1e-6, "atol": 1e-8})
            if X.shape[0] != len(ts):
                raise _SimulationFailed(f"integrator stopped at sample {X.shape[0]}")
            return X

        coef = np.asarray(m.sindy.coefficients())
        theta = self._poly(m.sindy.feature_library.powers_)
        calls = [0]
        status = {"blown": None}

        def rhs(tt: float, x: np.ndarray) -> np.ndarray:
            calls[0] += 1
            if calls[0] > self.max_rhs_evals:
                raise _SimulationFailed(f"over {self.max_rhs_evals} rhs evaluations (stiff)")
            if not np.all(np.abs(x) < self.blowup):
                # freeze an escaping state: the verdict is NaN anyway, and the solver stops
                # chasing a finite-time blow-up
                status["blown"] = status["blown"] or tt
                return np.zeros_like(x)
            return coef @ theta(np.concatenate([x, u_at(tt)]))

        # odeint is the same LSODA as solve_ivp(method="LSODA") without its per-step Python
        # overhead (3-4x faster here)
        X, info = odeint(rhs, x0, ts, tfirst=True, rtol=1e-6, atol=1e-8, mxstep=20_000,
                         full_output=True)
        if status["blown"] is not None:
            raise _SimulationFailed(f"state left ±{self.blowup} sd at t={status['blown']:.3g} s")
        if info.get("message") != "Integration successful.":
            raise _SimulationFailed(f"integrator: {info.get('message')}")
        return X

    def predict(self, test: TestResidual) -> dict[str, np.ndarray]:
        """Open-loop simulated channels of ``test``.

        Parameters
        ----------
        test
            Any test of a scenario the model was fitted on (typically a control test).

        Returns
        -------
        dict[str, numpy.ndarray]
            One array per key of ``test.measured``, same length as the test; all NaN
            when the scenario has no model or the simulation failed (see ``failures``).
        """
        n = len(test.time_s)
        nan = {c: np.full(n, np.nan) for c in test.measured}
        m = self.models_.get(test.scenario)
        if m is None:
            self.failures[test.id] = f"no model for scenario '{test.scenario}'"
            return nan
        try:
            U = self._inputs(test, m.omega_eps) / m.u_scale
            out: dict[str, np.ndarray] = {}
            if m.dynamic:
                with np.errstate(all="ignore"):
                    X = self._simulate_states(m, test, U)
                out = {c: X[:, i] * m.x_scale[i] + m.x_mean[i] for i, c in enumerate(m.dynamic)}
            if m.static:
                Y = self._poly(m.out_lib.powers_)(U) @ m.out_coef.T * m.out_scale + m.out_mean
                out.update({c: Y[:, i] for i, c in enumerate(m.static)})
            if not all(np.all(np.isfinite(v)) for v in out.values()):
                raise _SimulationFailed("non-finite output")
        except Exception as exc:  # a black-box model may fail in any way: record, never raise
            self.failures[test.id] = f"{type(exc).__name__}: {exc}"
            return nan
        self.failures.pop(test.id, None)
        return {c: out.get(c, nan[c]) for c in test.measured}
