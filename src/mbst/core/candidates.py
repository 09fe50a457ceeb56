"""A family's candidate library: named terms the evidence methods regress a residual on.

One library per family, read by both the sparse regression
(``discovery.evidence.sindy``) and the reading of the neural residual
(``discovery.evidence.neural.explain``), so the two methods speak of the same
catalogue keys with the same grids. The family builds it from its own internal
signals (``TestResidual.states``); the evidence methods only see columns.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

__all__ = ["Candidate", "CandidateLibrary", "LibraryFactory"]


@dataclass(frozen=True)
class Candidate:
    """One candidate term.

    ``key`` is the catalogue key ``"effect:component"`` the term stands for, or
    ``"base:<component>"`` for a nuisance term: re-tuning the base model could do
    it (a Coulomb level, a viscous term, a stiffness), so it is no missing effect.
    ``sign`` is the coefficient's physically required sign on the library's
    ``signed_channel`` (+1/−1), 0 where either sign is physical.
    """

    name: str
    key: str
    sign: int
    fn: Callable[[Mapping[str, Any]], np.ndarray]

    @property
    def nuisance(self) -> bool:
        return self.key.startswith("base:")


class CandidateLibrary(Protocol):
    """Candidate terms with grids fixed from the pooled identification tests."""

    #: the channel whose residual the library's signs are worked out for
    signed_channel: str
    candidates: list[Candidate]

    def transform(self, test: Any) -> np.ndarray:
        """Raw (unfiltered, full-rate) candidate matrix of one test, (samples, candidates)."""
        ...


#: builds a family's library from the pooled identification tests (``TestResidual``)
LibraryFactory = Callable[[list], CandidateLibrary]
