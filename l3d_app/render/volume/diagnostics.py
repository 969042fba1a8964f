"""Pictures of the ray machinery before anything is trained (the course's first volume-rendering part).

- :func:`pixel_grid_image`: each pixel coloured by its normalised image coordinates, the
  course's ``vis_grid``: ``rgb = ((x + 1) / 2.001, (y + 1) / 2.001, 0)`` with ``x, y`` in
  [-1, 1] the pixel centre's position across the image (x right, y down, our convention);
- :func:`ray_direction_image`: each pixel coloured by ``|d|`` of its unit world-space ray
  direction, the course's ``vis_rays``;
- :func:`ray_sample_points`: the 3D points ``o + t d`` of evenly spaced samples in
  ``[near, far]`` along every ``stride``-th pixel's ray, with their ``t``;
- :func:`depth_colormap`: depth coloured by a matplotlib colormap over ``[0, max]`` (the
  course's depth pictures: depth normalised by its maximum, viridis).
"""

from __future__ import annotations

import math

from typing import Optional, Tuple

import torch

from l3d_app.errors import UserError
from l3d_app.geometry.cameras import Cameras
from l3d_app.geometry.rays import camera_rays, pixel_centers
from l3d_app.render.volume.samplers import stratified_samples


def pixel_grid_image(height: int, width: int) -> torch.Tensor:
    """(H, W, 3) float32 in [0, 1): red grows to the right, green downwards, blue 0."""
    uv = pixel_centers(int(height), int(width))                     # (H, W, 2), pixels
    size = torch.tensor([float(width), float(height)])
    xy = uv / size * 2.0 - 1.0                                      # (H, W, 2) in (-1, 1)
    return torch.cat([(xy + 1.0) / 2.001, torch.zeros_like(xy[..., :1])], dim=-1)


def ray_direction_image(cams: Cameras) -> torch.Tensor:
    """(B, H, W, 3): ``|d|`` per component of each pixel's unit world-space ray direction."""
    _, dirs = camera_rays(cams, normalize=True)
    return dirs.abs()


def ray_sample_points(cams: Cameras, near: float, far: float, n_samples: int,
                      stride: int = 1) -> Tuple[torch.Tensor, torch.Tensor]:
    """Sample points along the rays of the FIRST camera.

    ``n_samples`` evenly spaced ``t`` in ``[near, far]`` (world units along unit rays, the
    deterministic :func:`~l3d_app.render.volume.samplers.stratified_samples`) on every
    ``stride``-th pixel in each direction. Returns points (R * S, 3) and their t (R * S,).
    """
    if not 0 <= near < far:
        raise UserError(f"need 0 <= near < far, got near={near}, far={far}")
    if int(stride) < 1:
        raise UserError(f"stride must be >= 1, got {stride}")
    origins, dirs = camera_rays(cams[0], normalize=True)            # (1, H, W, 3)
    s = int(stride)
    o = origins[0, ::s, ::s].reshape(-1, 3)
    d = dirs[0, ::s, ::s].reshape(-1, 3)
    t = stratified_samples(near, far, int(n_samples), n_rays=o.shape[0], dtype=o.dtype, device=o.device)
    points = o[:, None, :] + t[..., None] * d[:, None, :]           # (R, S, 3)
    return points.reshape(-1, 3), t.reshape(-1)


def depth_colormap(depth: torch.Tensor, mask: Optional[torch.Tensor] = None, vmax: Optional[float] = None,
                   cmap: str = "viridis", background: float = 1.0) -> torch.Tensor:
    """(..., H, W) depth -> (..., H, W, 3) colours: ``depth / vmax`` (default: the maximum finite
    depth under ``mask``) through ``cmap``; ``background`` grey where ``mask`` is False. A depth
    of +inf or NaN (no stereo match, a zero disparity) gets the top colour, -inf the bottom."""
    import matplotlib

    mask = torch.ones_like(depth, dtype=torch.bool) if mask is None else mask.bool()
    if vmax is None:
        finite = mask & torch.isfinite(depth)
        vmax = float(depth[finite].max()) if bool(finite.any()) else 1.0
    if not math.isfinite(float(vmax)):
        vmax = 1.0
    norm = torch.nan_to_num(depth / max(float(vmax), 1e-12), nan=1.0, posinf=1.0, neginf=0.0).clamp(0.0, 1.0)
    lut = torch.as_tensor(matplotlib.colormaps[cmap](torch.linspace(0, 1, 256).numpy())[:, :3],
                          dtype=torch.float32)
    rgb = lut[(norm.detach().cpu() * 255).round().long()]
    rgb[~mask.cpu()] = float(background)
    return rgb.to(depth.device)
