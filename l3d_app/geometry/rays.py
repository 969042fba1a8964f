"""Rays through pixel centres, in the internal camera convention (see ``cameras.py``)."""

from __future__ import annotations

from typing import Tuple

import torch

from l3d_app.geometry.cameras import Cameras


def pixel_centers(height: int, width: int, device=None, dtype=torch.float32) -> torch.Tensor:
    """(H, W, 2) pixel-centre coordinates (u, v) = (column + 0.5, row + 0.5)."""
    v, u = torch.meshgrid(torch.arange(height, device=device, dtype=dtype) + 0.5,
                          torch.arange(width, device=device, dtype=dtype) + 0.5, indexing="ij")
    return torch.stack([u, v], dim=-1)


def pixels_to_directions(cams: Cameras, uv: torch.Tensor, normalize: bool = True) -> torch.Tensor:
    """World-space ray directions (B, ..., 3) through pixel coordinates ``uv`` (B, ..., 2).

    With ``normalize=False`` the directions have camera-frame Z = 1, so a point at
    distance ``s`` along the ray has depth ``s``.
    """
    b = cams.batch_size
    shape = uv.shape[1:-1]
    flat = uv.reshape(b, -1, 2)
    x = (flat[..., 0] - cams.cx[:, None]) / cams.fx[:, None]
    y = (flat[..., 1] - cams.cy[:, None]) / cams.fy[:, None]
    d_cam = torch.stack([x, y, torch.ones_like(x)], dim=-1)
    d_world = d_cam @ cams.R  # (R^T d)^T = d^T R
    if normalize:
        d_world = torch.nn.functional.normalize(d_world, dim=-1)
    return d_world.reshape(b, *shape, 3)


def camera_rays(cams: Cameras, normalize: bool = True) -> Tuple[torch.Tensor, torch.Tensor]:
    """Rays through every pixel centre: origins and directions, each (B, H, W, 3)."""
    uv = pixel_centers(cams.height, cams.width, device=cams.device, dtype=cams.R.dtype)
    uv = uv[None].expand(cams.batch_size, -1, -1, -1)
    dirs = pixels_to_directions(cams, uv, normalize=normalize)
    origins = cams.centers()[:, None, None, :].expand_as(dirs)
    return origins, dirs
