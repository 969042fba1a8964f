"""Which points a set of cameras sees, given depth maps of the surface that occludes them.

A point counts as seen by a camera when it projects inside the image, lies in front of the
camera, and is no farther than the depth map at its pixel plus a tolerance; when the point's
surface normal is given, that surface must also face the camera. The depth maps may be finer
than the cameras (a scale factor on both axes). Used by the observed-surface metrics
(:mod:`l3d_app.metrics.observed`, depth of the TRUE surface) and by the visibility culling of
extracted meshes (:mod:`l3d_app.render.mesh.visibility`, depth of the mesh itself).
"""

from __future__ import annotations

from typing import Optional

import torch

from l3d_app.errors import UserError
from l3d_app.geometry.cameras import Cameras


@torch.no_grad()
def observed_mask(points: torch.Tensor, cameras: Cameras, depth_maps: torch.Tensor,
                  tolerance: float = 0.01, normals: Optional[torch.Tensor] = None,
                  chunk: int = 8) -> torch.Tensor:
    """(N,) bool: True where at least one of the B cameras observes the point.

    Args:
        points: (N, 3) world points.
        cameras: B cameras (at their own resolution; ``depth_maps`` may be finer).
        depth_maps: (B, h, w) camera Z of the occluding surface (the true one for the metrics,
            the mesh itself for culling), +inf where empty
            (:func:`l3d_app.render.mesh.rgbd.true_depth_maps`; h / H = w / W = the scale).
        tolerance: world units a point may lie behind that depth and still count.
        normals: optional (N, 3) outward normals of the points' surface: a camera then
            counts only if the surface faces it (``n . (C - p) > 0``).
    """
    if points.dim() != 2 or points.shape[-1] != 3:
        raise UserError(f"observed_mask: points must be (N, 3), got {tuple(points.shape)}")
    B, h, w = depth_maps.shape
    if B != len(cameras):
        raise UserError(f"observed_mask: {len(cameras)} cameras but {B} depth maps")
    sx, sy = w / cameras.width, h / cameras.height
    seen = torch.zeros(points.shape[0], dtype=torch.bool, device=points.device)
    pts = points.to(cameras.R.dtype)
    for s in range(0, B, int(chunk)):
        cams = cameras[s:s + int(chunk)]
        uv, z = cams.project(pts)                                     # (b, N, 2), (b, N)
        u = torch.floor(uv[..., 0] * sx).long()
        v = torch.floor(uv[..., 1] * sy).long()
        inside = (z > 0) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
        flat = (v.clamp(0, h - 1) * w + u.clamp(0, w - 1))
        d = torch.gather(depth_maps[s:s + int(chunk)].reshape(len(cams), -1), 1, flat)
        ok = inside & (z <= d + float(tolerance))
        if normals is not None:
            to_cam = cams.centers()[:, None, :] - pts[None]                  # (b, N, 3)
            ok &= (to_cam * normals.to(pts.dtype)[None]).sum(-1) > 0
        seen |= ok.any(dim=0)
    return seen
