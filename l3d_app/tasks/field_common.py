"""Config glue shared by the field tasks (train_nerf, volsdf): their turntables' size and orbit."""

from __future__ import annotations

from typing import Callable, Dict

import torch

from l3d_app.geometry.cameras import Cameras
from l3d_app.render.previews import write_turntables
from l3d_app.render.turntable import data_orbit
from l3d_app.runtime.budget import TimeBudget


def turntable_width(cfg, data_width: int) -> int:
    """Turntable frame width in pixels: ``cfg.turntable_size`` when set, else the data's
    ``data_width`` capped at ``cfg.turntable_max`` (a task's optional key; 0 or absent: no cap)."""
    size = int(cfg.turntable_size)
    if size:
        return size
    cap = int(cfg.get("turntable_max", 0) or 0)
    return min(int(data_width), cap) if cap > 0 else int(data_width)


def write_field_turntables(cfg, ctx, data, gifs: Dict[str, Callable[[Cameras], torch.Tensor]],
                           budget: TimeBudget) -> int:
    """Write each ``gifs`` entry (file name -> ``frames_fn(cameras) -> (N, H, W, 3)``) as a turntable of
    ``cfg.gif_frames`` frames about the data (``cfg.gif_elevation``, :func:`turntable_width`), the
    frames that fit ``budget`` (:func:`~l3d_app.render.previews.write_turntables`); the frames written."""
    width = turntable_width(cfg, data.cameras.width)
    return write_turntables({ctx.path(name): fn for name, fn in gifs.items()},
                            lambda n: data_orbit(data, n, float(cfg.gif_elevation), width, ctx.device),
                            int(cfg.gif_frames), float(cfg.fps), budget)
