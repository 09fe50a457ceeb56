"""Known values a campaign states: priors fitted with their σ, fixed values checked by the data.

A ``known:`` entry ``{value, sigma}`` (campaign-format.md) is freed in the
cascade stage that isolates its component and fitted with a Gaussian prior
term; its standard error includes the prior, and a fitted value more than
``CONTRADICTED_SIGMA`` σ from the prior is reported. A plain number is held
fixed, but a datasheet value is never exact: a short refit of its stage with the
value freed beside the stage's own parameters, with the residual-memory (HAC)
standard error, says when the data would move it by more than
``CONTRADICTED_SIGMA`` of its standard errors. It is reported, never silently
changed.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mbst.core.model import ModelDefinition
from mbst.identify.fitting import FitProblem, PreparedTest, channel_scales, solve

# a stated value the data put further than this many standard deviations away is contradicted
CONTRADICTED_SIGMA = 3.0
# a prior whose posterior σ keeps this share of its own was not informed by the tests
UNINFORMED_SHARE = 0.9
# iterations of the refit that frees a fixed known value beside its stage's parameters
FREED_NFEV = 15


@dataclass(frozen=True)
class KnownCheck:
    """One stated value against what the data say of it."""

    name: str
    unit: str
    value: float  # as the campaign states it
    sigma: float | None  # its prior's σ; None for a value held fixed
    fitted: float  # the fit's value (prior) or where the freed refit takes it (fixed)
    std_error: float  # of ``fitted``
    stage: str

    @property
    def z(self) -> float:
        """Distance from the stated value in σ of the prior (or of the estimate, if fixed)."""
        scale = self.sigma if self.sigma is not None else self.std_error
        return (self.fitted - self.value) / scale if scale > 0 else 0.0

    @property
    def contradicted(self) -> bool:
        return bool(np.isfinite(self.z)) and abs(self.z) > CONTRADICTED_SIGMA

    @property
    def informed(self) -> bool:
        """Whether the tests say anything of it: a posterior narrower than the prior (prior),
        a standard error below half the value (fixed). Else "consistent" would mean nothing."""
        if self.sigma is not None:
            return self.std_error < UNINFORMED_SHARE * self.sigma
        return self.std_error < 0.5 * abs(self.value)

    @property
    def verdict(self) -> str:
        if self.contradicted:
            return "contradicted"
        return "consistent" if self.informed else "not informed by these tests"

    def record(self) -> dict:
        return {"value": self.value, "sigma": self.sigma, "fitted": self.fitted,
                "std_error": self.std_error, "stage": self.stage, "z": self.z,
                "held_fixed": self.sigma is None, "contradicted": self.contradicted,
                "verdict": self.verdict}

    def sentence(self) -> str:
        stated = (f"{self.value:.4g} ± {self.sigma:.3g} {self.unit} (prior)"
                  if self.sigma is not None else f"{self.value:.4g} {self.unit} (held fixed)")
        verb = "are fitted at" if self.sigma is not None else "would move it to"
        change = 100.0 * (self.fitted / self.value - 1.0)
        return (f"known '{self.name}' = {stated}: the {self.stage} tests {verb} "
                f"{self.fitted:.4g} ± {self.std_error:.3g} {self.unit} ({change:+.2g} %), "
                f"{abs(self.z):.1f} σ away")


def campaign_priors(campaign, model: ModelDefinition) -> dict[str, tuple[float, float]]:
    """The campaign's priors on model parameters as (value, std of ln θ) for ``FitProblem``."""
    return {k: (campaign.known[k], sigma / abs(campaign.known[k]))
            for k, sigma in campaign.priors.items() if k in model.param_index}


def stage_of(model: ModelDefinition, name: str, tests: list[PreparedTest]) -> str | None:
    """The first cascade stage with tests where the parameter's component acts."""
    acts = model.component_scenarios.get(model.spec(name).component)
    for scenario, _ in model.cascade:
        if model.stage_tests(scenario, tests) and (acts is None or scenario in acts):
            return scenario
    return None


def prior_stages(model: ModelDefinition, names, tests: list[PreparedTest]
                 ) -> dict[str, tuple[str, ...]]:
    """Stage → the prior parameters it frees (``run_cascade``'s ``extra_free``)."""
    out: dict[str, list[str]] = {}
    for n in names:
        stage = stage_of(model, n, tests)
        if stage is not None:
            out.setdefault(stage, []).append(n)
    return {k: tuple(v) for k, v in out.items()}


def check_priors(campaign, model: ModelDefinition, params: np.ndarray, stages) -> list[KnownCheck]:
    """Each prior's fitted value and standard error (the last stage that fitted it)."""
    checks = {}
    for st in stages:
        for n in st.free:
            if n in campaign.priors and n in model.param_index:
                checks[n] = KnownCheck(n, model.spec(n).unit, campaign.known[n],
                                       campaign.priors[n], float(params[model.param_index[n]]),
                                       float(st.std_error[n]), st.scenario)
    return list(checks.values())


def check_fixed_known(campaign, model: ModelDefinition, params: np.ndarray, stages,
                      prepared: dict[str, PreparedTest], decimate: int) -> list[KnownCheck]:
    """Every fixed known value freed in the stage that isolates its component."""
    id_tests = [prepared[s.id] for s in campaign.identification_tests()]
    fixed = [k for k in campaign.known
             if k in model.param_index and k not in campaign.priors]
    by_stage: dict[str, list[str]] = {}
    for k in fixed:
        stage = stage_of(model, k, id_tests)
        if stage is not None:
            by_stage.setdefault(stage, []).append(k)
    scales = channel_scales(id_tests)
    out = []
    for st in stages:
        names = by_stage.pop(st.scenario, [])
        if names:
            tests = [prepared[t] for t in st.tests]
            out += _freed_refit(model, tests, list(st.free), names, params, scales, decimate,
                               st.scenario)
    return out


def _freed_refit(model, tests, free, names, params, scales, decimate, stage
                 ) -> list[KnownCheck]:
    """Refit the stage with the known values freed beside its parameters (a short fit).

    One Gauss–Newton step from the fit overshot through the friction terms (the cost
    rose a hundredfold); a few trust-region iterations do not.
    """
    prob = FitProblem(tests, {pt.id: list(pt.measured) for pt in tests}, free + names, params,
                      scales, decimate=decimate)
    fr = solve(prob, [params], max_nfev=FREED_NFEV)
    # a value the stage's tests do not move at all (zero sensitivity) is not checked
    return [KnownCheck(k, model.spec(k).unit, float(params[model.param_index[k]]), None,
                       float(fr.p[model.param_index[k]]), fr.std_error[k], stage)
            for k in names if fr.std_error[k] > 0.0]


def known_notes(checks: list[KnownCheck]) -> list[str]:
    """The warnings: every stated value the data contradict."""
    return [f"LOUD: the data contradict {c.sentence()}; check the value "
            + ("(a datasheet value is never exact; give it as a prior {value, sigma} to fit it)"
               if c.sigma is None else "and its sigma")
            for c in checks if c.contradicted]
