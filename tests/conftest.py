"""Bench campaigns shared by several test modules, built once per test session.

Each ``*_bench`` fixture returns the folder ``run_bench`` wrote: ``<dir>/campaign/`` and
``<dir>/truth.json``. The folders are shared, so tests must only read them
(``read_campaign(<dir> / "campaign")``, the truth file). A test that edits a
campaign's files builds its own campaign in ``tmp_path``. Each ``*_identified``
fixture is the campaign and its identification with the default settings, shared
alike: read it, never change it.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from mbst.identify.cascade import IdentifyResult, IdentifySettings, identify
from mbst.io.campaign import Campaign, read_campaign
from mbst.systems.eps.bench import BenchRecipe, run_bench

# Test modules that read the same session fixtures run on one xdist worker (a session
# fixture is built once per worker): the demo identifications are the longest to build.
# Every other module is a group of its own (``--dist loadgroup``, pyproject.toml).
SHARED_WORKER = {"test_identify.py": "demo-identified", "test_neural.py": "demo-identified",
                 "test_sindy.py": "demo-identified"}


@pytest.hookimpl(tryfirst=True)  # before xdist reads the groups
def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    for item in items:
        name = item.path.name
        item.add_marker(pytest.mark.xdist_group(SHARED_WORKER.get(name, name)))


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


def _identified(bench: Path) -> tuple[Campaign, IdentifyResult]:
    camp = read_campaign(bench / "campaign")
    return camp, identify(camp, IdentifySettings())


@pytest.fixture(scope="session")
def demo_clean_identified(demo_clean_bench) -> tuple[Campaign, IdentifyResult]:
    """``demo_clean_bench`` identified (test_identify, test_sindy, test_neural)."""
    return _identified(demo_clean_bench)


@pytest.fixture(scope="session")
def demo_backlash_identified(demo_backlash_bench) -> tuple[Campaign, IdentifyResult]:
    """``demo_backlash_bench`` identified (test_identify, test_sindy, test_neural)."""
    return _identified(demo_backlash_bench)
