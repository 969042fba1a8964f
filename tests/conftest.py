"""Shared test fixtures: paths to the repo, its configs and the optional course data; the
random-order setup.

Random order: pytest-randomly (the test extra; ``addopts = -p randomly``) shuffles the tests
on every run and reseeds ``random`` and numpy before each test; the seed is printed at the
end of the run (repeat an order with ``--randomly-seed=N``, or ``-p no:randomly`` for file
order). It does not touch torch, so this conftest seeds torch's global generator before
each test (``pytest_runtest_setup``, ahead of its fixtures) from the test's id alone: a
test's torch draws are the same in any order and under any --randomly-seed, and the shuffle
can only expose real leaks between tests (registries, global flags, working directory,
environment).
"""

from __future__ import annotations

import os
import zlib
from pathlib import Path

import pytest
import torch

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"

os.environ.setdefault("L3D_NO_PROGRESS", "1")


def course_data(*parts: str) -> Path:
    """Path inside ../shared/data; skips the test cleanly when it is absent."""
    path = SHARED_DATA.joinpath(*parts)
    if not path.exists():
        pytest.skip(f"course data not present: {path}")
    return path


@pytest.fixture
def compose():
    """Compose the app's Hydra config with overrides (no run directory, no chdir)."""
    from hydra import compose as hydra_compose, initialize_config_dir

    def _compose(*overrides: str):
        with initialize_config_dir(version_base="1.3", config_dir=str(REPO / "conf")):
            return hydra_compose(config_name="config", overrides=list(overrides))

    return _compose


@pytest.fixture(scope="session")
def data_cache(tmp_path_factory):
    """One cache folder for the session's built-in datasets (each file keyed by the dataset's
    parameters): a scene is rendered once for every test that asks for the same one."""
    return tmp_path_factory.mktemp("data_cache")


@pytest.hookimpl(tryfirst=True)
def pytest_runtest_setup(item):
    """Seed torch's global generator from the test's node id (order-independent), before any
    fixture of the test is set up (module-scoped ones included)."""
    torch.manual_seed(zlib.crc32(item.nodeid.encode()))


def pytest_terminal_summary(terminalreporter, config):
    """Print the random-order seed even under -q (pytest-randomly prints it only in the header)."""
    if config.pluginmanager.hasplugin("randomly"):
        seed = config.getoption("randomly_seed", None)
        terminalreporter.write_line(f"random order: --randomly-seed={seed} (pytest-randomly; "
                                    f"-p no:randomly for file order)")
