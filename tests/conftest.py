"""Shared test fixtures: paths to the repo, its configs and the optional course data."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

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
