"""Pieces shared by tasks: input checks and batched rendering with a progress bar."""

from __future__ import annotations

from typing import Dict, Sequence

import torch

from l3d_app.errors import UserError
from l3d_app.geometry.cameras import Cameras
from l3d_app.geometry.marching_cubes import require_grid_memory
from l3d_app.registry import CAMERA_PATHS, RENDERERS
from l3d_app.render.field_mesh import FIELD_MESH_FORMATS
from l3d_app.runtime.config_values import config_words
from l3d_app.runtime.device import available_host_memory
from l3d_app.runtime.progress import progress


def require_positive(cfg, *keys: str) -> None:
    """UserError naming the first of ``keys`` whose config value is not > 0."""
    for key in keys:
        value = cfg.get(key)
        if value is None or isinstance(value, bool) or not isinstance(value, (int, float)) or value <= 0:
            raise UserError(f"{key} must be a positive number, got {value!r}")


def require_fraction(cfg, *keys: str) -> None:
    """UserError naming the first of ``keys`` whose config value is not a number in [0, 1]
    (a probability, a decay)."""
    for key in keys:
        value = cfg.get(key)
        if value is None or isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 <= value <= 1:
            raise UserError(f"{key} must be a number in [0, 1], got {value!r}")


def require_nonnegative(cfg, *keys: str) -> None:
    """UserError naming the first of ``keys`` whose config value is not a number >= 0."""
    for key in keys:
        value = cfg.get(key)
        if value is None or isinstance(value, bool) or not isinstance(value, (int, float)) or value < 0:
            raise UserError(f"{key} must be a number >= 0, got {value!r}")


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


RUN_KEYS_NONNEGATIVE = ("time_budget", "reserve", "mesh_reserve", "gif_frames", "turntable_size", "eval_views", "checkpoint_every")
"""Run and output knobs that many tasks share, where 0 means none / off / the default and a
negative value means nothing."""
RUN_KEYS_POSITIVE = ("fps",)


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


def require_run_keys(cfg) -> None:
    """Check the shared run / output knobs a task's config has (``RUN_KEYS_*``) before the task
    starts, so a bad turntable size or frame rate fails now, not after training."""
    require_nonnegative(cfg, *(k for k in RUN_KEYS_NONNEGATIVE if k in cfg))
    require_positive(cfg, *(k for k in RUN_KEYS_POSITIVE if k in cfg))


@torch.no_grad()
def render_frames(renderer, mesh, cams: Cameras, batch: int, desc: str,
                  keys=("image", "alpha", "depth")) -> Dict[str, torch.Tensor]:
    """Render ``cams`` in batches of ``batch`` views; returns the ``keys`` outputs
    stacked over all views, on the CPU: image (N, H, W, 3), alpha (N, H, W), depth (N, H, W).
    """
    chunks: Dict[str, list] = {k: [] for k in keys}
    for start in progress(range(0, len(cams), batch), desc=desc):
        out = renderer(mesh, cams[start:start + batch])
        for k in keys:
            chunks[k].append(out[k].detach().cpu())
    return {k: torch.cat(v) for k, v in chunks.items()}


def background_parameter(mode, data) -> torch.nn.ParameterDict:
    """What lies behind the scene box: one RGB composited behind every ray or splat.

    Args:
        mode: ``learn_background`` knob: ``auto`` (learn when ``data.background_known`` is
            False, i.e. a real capture), ``true`` or ``false``.
        data: a multi-view dataset with ``background`` (3,) in [0, 1] (the loader's estimate
            when not known).
    Returns:
        ``ParameterDict`` with ``"rgb"`` (3,), starting at ``data.background``; it requires
        grad only when learnt (callers clamp it to [0, 1] when rendering and pass it to the
        optimiser only when ``requires_grad``).
    """
    key = str(mode).lower()
    choices = {"auto": not getattr(data, "background_known", True), "true": True, "false": False}
    if key not in choices:
        raise UserError(f"learn_background must be auto, true or false, got {mode!r}")
    rgb = torch.nn.Parameter(data.background.clone().float(), requires_grad=choices[key])
    return torch.nn.ParameterDict({"rgb": rgb})
