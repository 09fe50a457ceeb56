"""Run the evidence methods beside the structure test (identification tests only).

A failure of one method is recorded in its place and never sinks the discovery.
"""

from __future__ import annotations

import logging

from mbst.core.candidates import LibraryFactory
from mbst.discovery.data import TestResidual
from mbst.discovery.state import DiscoverSettings

log = logging.getLogger(__name__)


def sparse_evidence(id_res: list[TestResidual], library: LibraryFactory) -> dict | None:
    from mbst.discovery.evidence.sindy import residual_regression

    try:
        ev = residual_regression(id_res, library)
    except Exception as exc:  # evidence only: a failure must not sink the discovery
        log.warning("sparse-regression evidence failed: %s: %s", type(exc).__name__, exc)
        return {"error": f"{type(exc).__name__}: {exc}", "ranking": []}
    d = ev.to_dict()
    d["ranking"] = [list(x) for x in ev.ranking]
    return d


def neural_evidence(id_res: list[TestResidual], settings: DiscoverSettings,
                    library: LibraryFactory):
    from mbst.discovery.evidence import neural

    kw = {"seed": settings.identify.seed}
    if settings.neural_iterations is not None:
        kw["iterations"] = settings.neural_iterations
    try:
        model = neural.NeuralResidual(**kw).fit(id_res)
        ev = neural.explain(model, id_res, library)
    except Exception as exc:  # evidence only: a failure must not sink the discovery
        log.warning("neural-residual evidence failed: %s: %s", type(exc).__name__, exc)
        return None, {"error": f"{type(exc).__name__}: {exc}", "ranking": []}
    ev["train_seconds"] = getattr(model, "train_seconds", None)
    return model, ev
