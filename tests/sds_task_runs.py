"""Helpers of the sds_mesh / sds_nerf task tests: run a task with the shipped built-in prior."""

from __future__ import annotations

import json
import math

import pytest
import torch

from l3d_app.app import run_task


def needs_shipped_prior(space: str = "pixel") -> None:
    """Skip unless the shipped built-in prior exists and holds ``space``."""
    from l3d_app.diffusion.builtin_prior import DEFAULT_CHECKPOINT

    if not DEFAULT_CHECKPOINT.exists():
        pytest.skip(f"built-in prior not shipped: {DEFAULT_CHECKPOINT}")
    if space not in torch.load(DEFAULT_CHECKPOINT, map_location="cpu", weights_only=True)["spaces"]:
        pytest.skip(f"the shipped built-in prior has no {space} space")


def run_metrics(compose, tmp_path, *overrides: str) -> dict:
    """Run the composed task into ``tmp_path``; its metrics.json as a dict."""
    needs_shipped_prior("latent" if "space=latent" in overrides else "pixel")
    run_task(compose(*overrides), out_dir=tmp_path)
    return json.loads((tmp_path / "metrics.json").read_text())


def numbers_finite(metrics: dict) -> bool:
    """Every int/float value (bools and None aside) is finite."""
    return all(math.isfinite(v) for v in metrics.values()
               if isinstance(v, (int, float)) and not isinstance(v, bool))
