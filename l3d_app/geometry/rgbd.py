"""RGB-D images <-> point clouds (rendering RGB-D views of a mesh: :mod:`l3d_app.render.mesh.rgbd`).

Depth maps hold camera-frame Z (world units; the convention of
:mod:`l3d_app.geometry.cameras` and of ``MeshRenderer``'s ``depth``), with 0 (or any
value <= 0, or non-finite) meaning "no measurement". A pixel ``(i, j)`` with depth ``Z``
unprojects to ``C + Z * d`` where ``d`` is the ray through its centre ``(j + .5, i + .5)``
scaled to camera Z = 1 (:func:`l3d_app.geometry.rays.pixels_to_directions`).
"""

from __future__ import annotations

from typing import Optional, Sequence, Union

import torch

from l3d_app.errors import UserError
from l3d_app.geometry.cameras import Cameras
from l3d_app.geometry.point_mesh_distance import point_mesh_distance  # noqa: F401  (older import path)
from l3d_app.geometry.pointcloud import PointCloud
from l3d_app.geometry.rays import pixel_centers, pixels_to_directions


def unproject_depth(depth: torch.Tensor, cams: Cameras, rgb: Optional[torch.Tensor] = None,
                    mask: Optional[torch.Tensor] = None) -> PointCloud:
    """World points of all valid pixels of B depth maps, as one cloud (views in order,
    pixels row-major).

    Args:
        depth: (B, H, W) camera Z in world units; <= 0 or non-finite = invalid.
        cams: B cameras of size H x W.
        rgb: optional (B, H, W, 3) colours in [0, 1] -> the cloud's colours.
        mask: optional (B, H, W) bool (or 0/1); False pixels are dropped.
    Returns:
        PointCloud with (P, 3) points (and (P, 3) colours when ``rgb`` is given).
    """
    if depth.dim() == 2:
        depth = depth[None]
    B, H, W = depth.shape
    if (cams.batch_size, cams.height, cams.width) != (B, H, W):
        raise UserError(f"depth {tuple(depth.shape)} does not match {cams.batch_size} cameras "
                        f"of {cams.height}x{cams.width}")
    if rgb is not None and rgb.shape[:3] != depth.shape:
        raise UserError(f"rgb {tuple(rgb.shape)} does not match depth {tuple(depth.shape)}")
    if mask is not None and mask.shape != depth.shape:
        raise UserError(f"mask {tuple(mask.shape)} does not match depth {tuple(depth.shape)}")
    cams = cams.to(device=depth.device, dtype=depth.dtype)
    valid = torch.isfinite(depth) & (depth > 0)
    if mask is not None:
        valid &= mask.to(device=depth.device).bool()
    uv = pixel_centers(H, W, device=depth.device, dtype=depth.dtype)[None].expand(B, H, W, 2)
    dirs = pixels_to_directions(cams, uv, normalize=False)  # (B, H, W, 3), camera Z = 1
    centres = cams.centers()[:, None, None, :]
    points = (centres + depth.nan_to_num(0.0)[..., None] * dirs)[valid]
    colors = None if rgb is None else rgb.to(points.dtype)[valid]
    return PointCloud(points, colors)


def concat_clouds(clouds: Sequence[PointCloud]) -> PointCloud:
    """Union of clouds in one frame; colours/normals kept only if every cloud has them."""
    if not clouds:
        raise UserError("cannot concatenate an empty list of point clouds")
    cat = lambda name: (None if any(getattr(c, name) is None for c in clouds)  # noqa: E731
                        else torch.cat([getattr(c, name) for c in clouds]))
    return PointCloud(torch.cat([c.points for c in clouds]), cat("colors"), cat("normals"))


def unproject_views(depth: Union[torch.Tensor, Sequence[torch.Tensor]],
                    cams: Union[Cameras, Sequence[Cameras]],
                    rgb=None, mask=None) -> PointCloud:
    """Union, in the world frame, of the clouds of several RGB-D views.

    ``depth`` (B, H, W) with B cameras, or lists (one entry per batch, image sizes may
    differ) of depth / Cameras / rgb / mask as in :func:`unproject_depth`.
    """
    if torch.is_tensor(depth):
        return unproject_depth(depth, cams, rgb, mask)
    n = len(depth)
    if isinstance(cams, Cameras) or len(cams) != n:
        raise UserError("unproject_views with a list of depth maps needs a list of cameras of the same length")
    rgb = [None] * n if rgb is None else rgb
    mask = [None] * n if mask is None else mask
    return concat_clouds([unproject_depth(d, c, r, m) for d, c, r, m in zip(depth, cams, rgb, mask)])
