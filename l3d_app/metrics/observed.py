"""Which points a set of cameras actually observes, given the true surface.

Multi-view reconstruction cannot recover surface that no input camera sees (the underside
of an object on its stand, the inside of a joint). Benchmarks therefore score against the
*observed* part (the DTU evaluation does it with its observation masks). Here a point
counts as observed when at least one camera sees it: it projects inside that camera's image,
in front of the camera, and no farther than the true surface's depth at that pixel plus a
tolerance; and, when the point's surface normal is given (points sampled on the true
surface), the surface faces that camera. The true depth maps are an input, rendered by the caller
(:func:`l3d_app.render.rgbd.true_depth_maps`, our own rasteriser at ``scale`` times the
cameras' resolution: finer pixels, so a smaller tolerance suffices on thin parts and
silhouettes); metrics never render.
The facing test matters at grazing views: from a camera a little above the underside's
plane, the whole underside projects onto a one-pixel sliver along the bottom edge, where a
depth lookup alone is ambiguous.

The same test applies to points of a *reconstruction*: a reconstructed point in free space
in front of the true surface is observed (it is a visible floater and counts as an error);
one hidden behind the true surface in every view (e.g. a guess under the stand) is not.
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
        depth_maps: (B, h, w) camera Z of the true surface, +inf where empty
            (:func:`l3d_app.render.rgbd.true_depth_maps`; h / H = w / W = the scale).
        tolerance: world units a point may lie behind the true depth and still count.
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
