"""Bench campaigns shared by several test modules, built once per test session.

Each fixture returns the folder ``run_bench`` wrote: ``<dir>/campaign/`` and
``<dir>/truth.json``. The folders are shared, so tests must only read them
(``read_campaign(<dir> / "campaign")``, the truth file). A test that edits a
campaign's files builds its own campaign in ``tmp_path``.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from mbst.systems.eps.bench import BenchRecipe, run_bench


def _bench(tmp_path_factory: pytest.TempPathFactory, name: str, recipe: BenchRecipe) -> Path:
    out = tmp_path_factory.mktemp(name)
    run_bench(out, recipe)
    return out


@pytest.fixture(scope="session")
def demo_clean_bench(tmp_path_factory) -> Path:
    """The demo plan, no hidden effect, seed 1 (test_identify, test_sindy, test_neural)."""
    return _bench(tmp_path_factory, "demo-clean", BenchRecipe(effects=[], seed=1))


@pytest.fixture(scope="session")
def demo_backlash_bench(tmp_path_factory) -> Path:
    """The demo plan with the worm-gear backlash, seed 1 (test_identify, test_sindy,
    test_neural)."""
    return _bench(tmp_path_factory, "demo-backlash",
                  BenchRecipe(effects=["backlash:worm_gear"], seed=1))
