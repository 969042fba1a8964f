"""Turntables that orbit about the data's up axis, and the gif writer every field task uses.

The up axis is the dataset's ``up`` attribute when it has one (NeRF-synthetic: +Z), else
the mean of its cameras' up vectors (OpenCV frame: up = minus the second row of ``R``),
snapped to the nearest world axis when within ``snap_deg`` of it. :func:`orbit_cameras`
builds the usual +Y turntable and rotates the world so that +Y becomes ``up``.
"""

from __future__ import annotations

import math
from typing import Callable, Dict, Optional, Sequence

import torch

from l3d_app.errors import UserError
from l3d_app.geometry.camera_paths import turntable
from l3d_app.geometry.cameras import Cameras
from l3d_app.render.evaluation import render_views
from l3d_app.runtime.media import save_gif


def cameras_up(cameras: Cameras, snap_deg: float = 15.0) -> torch.Tensor:
    """(3,) unit mean up vector of ``cameras`` (snapped to a world axis within ``snap_deg``)."""
    up = -cameras.R[:, 1, :].double().mean(dim=0)
    if float(up.norm()) < 1e-6:
        return torch.tensor([0.0, 1.0, 0.0])
    up = up / up.norm()
    axis = int(up.abs().argmax())
    if float(up[axis].abs()) >= math.cos(math.radians(snap_deg)):
        snapped = torch.zeros(3, dtype=torch.float64)
        snapped[axis] = float(torch.sign(up[axis]))
        up = snapped
    return up.float()


def data_up(data) -> torch.Tensor:
    """(3,) the dataset's up axis: ``data.up`` if present, else :func:`cameras_up` of its cameras."""
    up = getattr(data, "up", None)
    if up is not None:
        up = torch.as_tensor(up, dtype=torch.float32).reshape(3).cpu()
        return up / up.norm()
    return cameras_up(data.cameras.to("cpu"))


def _rotation_from_y(up: torch.Tensor) -> torch.Tensor:
    """(3, 3) proper rotation Q with Q e_y = up (Rodrigues; a half turn about X for -Y)."""
    y = torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)
    u = up.double() / up.double().norm()
    v, c = torch.linalg.cross(y, u), float((y * u).sum())
    if c < -1.0 + 1e-9:
        return torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=torch.float64))
    vx = torch.tensor([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]], dtype=torch.float64)
    return torch.eye(3, dtype=torch.float64) + vx + vx @ vx / (1.0 + c)


def orbit_cameras(num_frames: int, distance: float, elevation: float, fov: float, image_size: int,
                  up: Optional[Sequence[float]] = None, at: Sequence[float] = (0.0, 0.0, 0.0),
                  device=None) -> Cameras:
    """:func:`~l3d_app.geometry.camera_paths.turntable` about ``up`` (default +Y) through ``at``:
    elevation is measured from the plane perpendicular to ``up``."""
    cams = turntable(int(num_frames), float(distance), float(elevation), float(fov), int(image_size))
    if up is None:
        return cams.to(device)
    q = _rotation_from_y(torch.as_tensor(up, dtype=torch.float64)).to(cams.R.dtype)
    at_t = torch.as_tensor(at, dtype=cams.R.dtype).reshape(3)
    r = cams.R @ q.T                                                     # X_cam = R Q^T (X' - at) + t
    t = cams.t - (r @ at_t[:, None])[..., 0]
    return Cameras.from_fov(r, t, float(fov), int(image_size), int(image_size)).to(device)


def data_orbit(data, frames: int, elevation: float, width: int, device=None) -> Cameras:
    """``frames`` cameras orbiting the data's up axis (:func:`data_up`) at its cameras' mean distance
    from the origin, ``elevation`` degrees, the data's field of view, ``width`` pixels square."""
    return orbit_cameras(int(frames), float(data.cameras.centers().norm(dim=-1).mean()), float(elevation),
                         float(data.cameras.fov()[0]), int(width), up=data_up(data), device=device)


@torch.no_grad()
def write_turntable(path, frames_fn: Callable[[Cameras], torch.Tensor], cameras: Cameras, fps: float = 12.0
                    ) -> torch.Tensor:
    """Render ``frames_fn(cameras) -> (N, H, W, 3)`` in [0, 1], check it is finite, save a gif."""
    frames = frames_fn(cameras)
    if not bool(torch.isfinite(frames).all()):
        raise UserError(f"{path}: the render produced non-finite values")
    save_gif(path, frames.clamp(0, 1), fps=float(fps))
    return frames


def color_depth_frames(render_fn, chunk: int = 8192) -> Callable[[Cameras], torch.Tensor]:
    """``frames_fn`` for :func:`write_turntable`: colour | depth side by side."""
    from l3d_app.render.evaluation import depth_picture

    def fn(cams: Cameras) -> torch.Tensor:
        out: Dict[str, torch.Tensor] = render_views(render_fn, cams, chunk)
        return torch.cat([out["color"].clamp(0, 1), depth_picture(out["depth"], out["opacity"])], dim=2)

    return fn
