"""Each family's own report pages, chosen by family name (a model never imports a report).

``family_report(name)(identify_result, figure_dir) -> markdown lines``: figures and
tables a family adds to ``identify.md`` (the EPS power assist); families without
one add nothing.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

from mbst.report import eps_assist

FamilyReport = Callable[[Any, Path], list[str]]

_REPORTS: dict[str, FamilyReport] = {
    "eps-column-assist": eps_assist.write,
}


def family_report(family: str) -> FamilyReport:
    """The identify-page extension of ``family`` (one that adds nothing if it has none)."""
    return _REPORTS.get(family, lambda result, figdir: [])
