"""Pieces shared by tasks: config checks and the training loop's spec from a config."""

from __future__ import annotations

from typing import Dict, Sequence

import torch

from l3d_app.errors import UserError
from l3d_app.geometry.cameras import Cameras
from l3d_app.geometry.marching_cubes import require_grid_memory
from l3d_app.registry import CAMERA_PATHS, RENDERERS
from l3d_app.render.field_mesh import FIELD_MESH_FORMATS
from l3d_app.runtime.config_values import (config_words, require_fraction,  # noqa: F401  (the tasks' checks)
                                            require_nonnegative, require_positive)
from l3d_app.runtime.device import available_host_memory
from l3d_app.runtime.progress import progress
from l3d_app.runtime.training import LoopSpec


def require_mesh_resolution(cfg) -> None:
    """UserError unless ``cfg.mesh_resolution`` is an integer >= 2 (marching-cubes cells per
    axis) whose grid fits the host memory available now: checked before training, since the mesh is
    extracted after it."""
    value = cfg.get("mesh_resolution")
    if isinstance(value, bool) or not isinstance(value, int) or value < 2:
        raise UserError(f"mesh_resolution must be an integer >= 2 (marching-cubes cells per axis), got {value!r}")
    require_grid_memory(value, available_host_memory())


def require_mesh_formats(cfg, key: str = "mesh_formats", allowed: Sequence[str] = FIELD_MESH_FORMATS) -> None:
    """UserError unless ``cfg[key]`` is a non-empty list of formats in ``allowed`` (a single
    string for ``mesh_format``): checked before training, since the mesh is written after it."""
    value = cfg.get(key)
    formats = config_words([] if value is None else value, key)
    bad = [f for f in formats if str(f).lower().lstrip(".") not in allowed]
    if not formats or bad:
        raise UserError(f"{key} must be {'one' if isinstance(value, str) else 'a non-empty list'} of "
                        f"{', '.join(allowed)}, got {value!r}")


def check_output_knobs(cfg) -> None:
    """Build the renderers (``renderer``, ``point_renderer``) and the camera path (``camera``)
    that ``cfg`` names, once, and drop them: a bad shading, radius unit, background or path
    name fails now, not at the turntable after training (or, for the renderer the run's data
    does not use, never)."""
    for key in ("renderer", "point_renderer"):
        if cfg.get(key) is not None:
            RENDERERS.build(cfg[key])
    if cfg.get("camera") is not None:
        CAMERA_PATHS.build(cfg.camera)


def loop_spec(cfg, desc: str, iters: int = 0, **kwargs) -> LoopSpec:
    """The training loop's spec from a task's config: ``iters`` (0: ``cfg.iters``), ``eval_every``,
    ``checkpoint_every`` and ``resume`` where the config has them, the bar's ``desc``; ``kwargs`` add
    or override :class:`~l3d_app.runtime.training.LoopSpec` fields."""
    known = {k: cfg[k] for k in ("eval_every", "checkpoint_every", "resume") if cfg.get(k) is not None}
    spec = {"eval_every": int(known.get("eval_every", 0)), "checkpoint_every": int(known.get("checkpoint_every", 0)),
            "resume": bool(known.get("resume", False)), **kwargs}
    return LoopSpec(int(iters or cfg.iters), desc=desc, **spec)
