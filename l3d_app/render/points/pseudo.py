"""Pseudo-renderer of point clouds (Lin, Kong & Lucey, AAAI 2018): depth and carried values.

A differentiable stand-in for rendering a dense point cloud into a depth image, used to
train a point generator from 2D depth/silhouettes only. Each point is projected into the
camera (conventions of :mod:`l3d_app.geometry.cameras`: OpenCV frame, pixel ``(row i,
col j)`` centred at ``(u, v) = (j + .5, i + .5)``) and dropped onto an UPSAMPLED grid of
``(U H) x (U W)`` pixels, sub-pixel ``(floor(U v), floor(U u))``. Per sub-pixel the point
of largest INVERSE depth ``1 / Z`` (the nearest) wins (a z-buffer, ties to the lower point
index); the image is then max-pooled by ``U x U`` back to ``H x W``, again keeping the
largest inverse depth (the first one in row-major order on ties). Upsampling first makes
collisions between points rare, the max-pool closes the holes between them.

Gradients: the rendered inverse depth is the winner's ``1 / Z``, gathered with autograd,
so the depth (and everything it depends on: the point) gets the gradient of the winning
point; values carried per point (e.g. mask logits) are gathered the same way. The choice of
the winner and the pixel a point falls into are not differentiable (as in the paper).
Pixels no point reaches render inverse depth 0 (depth 0, ``covered`` False).

Vectorised: one projection, one ``scatter_reduce`` for the z-buffer, one for the tie-break,
one ``max_pool2d``; no Python loop over points or pixels.
"""

from __future__ import annotations

from typing import Dict, Optional

import torch
import torch.nn.functional as F

from l3d_app.errors import UserError
from l3d_app.geometry.cameras import Cameras


def pseudo_render(points: torch.Tensor, cams: Cameras, upsample: int = 4,
                  values: Optional[torch.Tensor] = None, active: Optional[torch.Tensor] = None,
                  near: float = 1e-3) -> Dict[str, torch.Tensor]:
    """Render B point clouds, one per camera.

    Args:
        points: (B, N, 3) world points (or (N, 3), shared by all B cameras).
        cams: B cameras (image ``H x W`` pixels).
        upsample: U >= 1, the sub-pixel factor of the z-buffer grid.
        values: optional (B, N, C) (or (N, C)) per-point values carried to the pixels.
        active: optional (B, N) (or (N,)) bool; only active points are rendered (the
            paper renders the points its mask calls foreground, see ``svr_pseudo``).
        near: points with camera depth ``Z <= near`` are dropped.
    Returns:
        inv_depth (B, H, W): ``1 / Z`` of the winning point, 0 where no point lands;
        depth (B, H, W): ``Z`` of the winning point, 0 where no point lands;
        covered (B, H, W) bool; index (B, H, W) long: winning point (-1 where none);
        values (B, H, W, C) when ``values`` is given (0 where no point lands).
    """
    B, H, W, U = cams.batch_size, cams.height, cams.width, int(upsample)
    if U < 1:
        raise UserError(f"pseudo-render upsample factor must be >= 1, got {upsample}")
    if points.dim() == 2:
        points = points[None].expand(B, -1, -1)
    if points.dim() != 3 or points.shape[0] != B or points.shape[-1] != 3:
        raise UserError(f"pseudo_render points must be (B, N, 3) with B = {B} cameras, got {tuple(points.shape)}")
    N = points.shape[1]
    cams = cams.to(device=points.device, dtype=points.dtype)
    uv, z = cams.project(points)                                   # (B, N, 2), (B, N)
    col = torch.floor(uv[..., 0].detach() * U)
    row = torch.floor(uv[..., 1].detach() * U)
    zd = z.detach()
    valid = (zd > near) & torch.isfinite(uv.detach()).all(-1) & (col >= 0) & (col < U * W) & (row >= 0) & (row < U * H)
    if active is not None:
        valid = valid & active.to(device=points.device, dtype=torch.bool).expand(B, N)
    Hu, Wu = U * H, U * W
    b = torch.arange(B, device=points.device)[:, None].expand(B, N)
    key = (b * (Hu * Wu) + row.clamp(0, Hu - 1).long() * Wu + col.clamp(0, Wu - 1).long())[valid]
    inv_all = 1.0 / torch.where(z > near, z, torch.ones_like(z))    # (B, N), finite everywhere
    inv_valid = inv_all.detach()[valid]
    # z-buffer: the largest inverse depth per sub-pixel, then the lowest point index among ties
    best = torch.zeros(B * Hu * Wu, dtype=points.dtype, device=points.device)
    best = best.scatter_reduce(0, key, inv_valid, "amax", include_self=True)
    flat_id = (b * N + torch.arange(N, device=points.device))[valid]  # index into (B * N)
    is_best = inv_valid == best[key]
    sentinel = B * N
    winner = torch.full((B * Hu * Wu,), sentinel, dtype=torch.long, device=points.device)
    winner = winner.scatter_reduce(0, key[is_best], flat_id[is_best], "amin", include_self=True)
    hit = winner < sentinel
    inv_up = torch.zeros(B * Hu * Wu, dtype=points.dtype, device=points.device)
    inv_up = inv_up.masked_scatter(hit, inv_all.reshape(-1)[winner[hit]])  # gathered with autograd
    # back to H x W: max-pool of the inverse depth, remembering which sub-pixel won
    pooled, arg = F.max_pool2d(inv_up.view(B, 1, Hu, Wu), U, return_indices=True)
    inv_depth = pooled[:, 0]
    sub = arg[:, 0].reshape(B, -1) + (torch.arange(B, device=points.device) * Hu * Wu)[:, None]
    index_flat = torch.where(hit, winner, torch.full_like(winner, -1))[sub.reshape(-1)].view(B, H, W)
    covered = index_flat >= 0
    depth = torch.where(covered, 1.0 / torch.where(covered, inv_depth, torch.ones_like(inv_depth)),
                        torch.zeros_like(inv_depth))
    out = {"inv_depth": inv_depth, "depth": depth, "covered": covered,
           "index": torch.where(covered, index_flat % N, torch.full_like(index_flat, -1))}
    if values is not None:
        if values.dim() == 2:
            values = values[None].expand(B, -1, -1)
        flat_vals = values.reshape(B * N, -1)
        picked = flat_vals[index_flat.clamp_min(0).reshape(-1)].view(B, H, W, -1)
        out["values"] = picked * covered[..., None].to(picked.dtype)
    return out
