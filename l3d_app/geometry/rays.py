"""Rays through pixel centres, in the internal camera convention (see ``cameras.py``)."""

from __future__ import annotations

from typing import Tuple

import torch

from l3d_app.errors import UserError
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


def pixel_axes(cams: Cameras) -> Tuple[torch.Tensor, torch.Tensor]:
    """(B, 3), (B, 3): how an UNNORMALISED ray direction (camera-frame Z = 1, as from
    :func:`pixels_to_directions` with ``normalize=False``) changes per pixel step in u and in v.

    A pinhole direction is linear in the pixel coordinates, so the ray through (u + a, v + b)
    is exactly ``d(u, v) + a * du + b * dv``: random sub-pixel rays (anti-aliased training)
    cost one multiply-add.
    """
    return cams.R[:, 0, :] / cams.fx[:, None], cams.R[:, 1, :] / cams.fy[:, None]


def supersampled_rays(cams: Cameras, factor: int, normalize: bool = True) -> Tuple[torch.Tensor, torch.Tensor]:
    """Rays through a ``factor`` x ``factor`` grid of sub-pixel centres of every pixel: origins and
    directions (B, H, W, factor^2, 3); their mean colour is the box-filtered (SSAA) pixel, the way
    the mesh renderer's ``antialias`` makes images."""
    s = int(factor)
    if s < 1:
        raise UserError(f"supersampling factor must be >= 1, got {factor}")
    uv = pixel_centers(cams.height, cams.width, device=cams.device, dtype=cams.R.dtype)         # (H, W, 2)
    off = (torch.arange(s, device=cams.device, dtype=cams.R.dtype) + 0.5) / s - 0.5
    grid = torch.stack(torch.meshgrid(off, off, indexing="xy"), dim=-1).reshape(-1, 2)        # (s*s, 2)
    uv = (uv[:, :, None, :] + grid)[None].expand(cams.batch_size, -1, -1, -1, -1)
    dirs = pixels_to_directions(cams, uv, normalize=normalize)
    origins = cams.centers()[:, None, None, None, :].expand_as(dirs)
    return origins, dirs
