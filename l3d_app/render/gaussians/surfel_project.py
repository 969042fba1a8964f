"""Projection of 2D Gaussian surfels (oriented planar disks) into cameras: the ray-splat homography.

A surfel (2D Gaussian splatting, Huang et al. 2024) is a centre ``m``, a rotation ``R_q``
(quaternion ``(w, x, y, z)``) whose first two columns span the disk's plane and whose third
column is its normal, and two tangent standard deviations ``s_u``, ``s_v`` (world units). Its
points are ``m + u s_u t_u + v s_v t_v`` with ``(u, v)`` the splat's local coordinates, where the
Gaussian is ``exp(-(u^2 + v^2) / 2)``. In a camera (``X_cam = R X + t``, intrinsics ``K``) the
homogeneous pixel of the local point ``(u, v, 1)`` is ``T (u, v, 1)^T`` with the 3x3 matrix

    T = K [R s_u t_u | R s_v t_v | R m + t]   (columns),

so ``T``'s third row gives the camera depth ``z(u, v) = T_2 . (u, v, 1)`` and its third column is
``z_c (u_c, v_c, 1)``: the projected centre ``(u_c, v_c)`` (``means2d``) times the centre's depth.
The pixel ``p = (x, y, 1)`` sees the local point ``(u, v, 1) ~ T^{-1} p``: ``c = A p`` with ``A``
the adjugate of ``T`` (finite also where ``T`` is singular: a splat seen edge-on), normalised by
its largest entry and by the sign of ``det T`` so that ``c2 > 0`` exactly when the intersection
lies in front of the camera; ``(u, v) = (c0, c1) / c2``. This is the perspective-correct
intersection (no affine approximation), computed per pixel in
:mod:`l3d_app.render.gaussians.surfel_composite`.

Screen bounds: the disk's level set ``u^2 + v^2 = r^2`` with ``r^2 = 2 ln(255 o)`` (where
``o exp(-(u^2 + v^2) / 2)`` falls to 1/255) is the conic whose dual is
``D = T diag(r^2, r^2, -1) T^T``; its bounding box has centre ``(D02, D12) / D22`` and half-widths
``sqrt(D02^2 - D00 D22) / |D22|`` (``sqrt(D12^2 - D11 D22) / |D22|``), an ellipse when ``D22 < 0``
(the disk lies wholly in front of the camera's plane); a splat whose disk crosses that plane is
culled, as is one with its centre at ``z <= near``. The box is joined with the low-pass disk
around ``(u_c, v_c)``: the floor ``rho exp(-LOW_PASS_INV (dx^2 + dy^2) / 2)`` (px) keeps a splat seen
edge-on (a line on screen) or smaller than a pixel visible as a blob of the pixel's size (variance
1/12 px^2, a pixel box's), with the weight ``rho = min(1, LOW_PASS_INV |det T| / z_c^3)``: the disk's
projected area (``|det T| / z_c^3`` is the homography's Jacobian determinant at the centre, px^2 per
unit of local area) over the floor's, so that the blob carries the disk's coverage and no more.
2DGS's floor has variance 1/2 px^2 and ``rho = 1``: at this project's image sizes (128 px) its blobs
fatten every silhouette by most of a pixel, and the fitted surface shrinks by as much (on the
development scene ``dev``, surfels placed on the true surface drew 11% more silhouette than the
truth's; with this floor 5%, the rest from the Gaussian tails of the disks).
"""

from __future__ import annotations

from typing import Dict

import torch

from l3d_app.geometry.cameras import Cameras
from l3d_app.render.gaussians.project import quat_rotation

LOW_PASS_INV = 12.0    # px^-2: the floor's quadratic form is LOW_PASS_INV (dx^2 + dy^2): the variance of a pixel's box, 1/12 px^2
FLOOR_MIN = 1e-12      # the floor's weight never falls below this (an exactly edge-on splat: a finite offset)


def surfel_frames(log_scales: torch.Tensor, quats: torch.Tensor):
    """World tangent axes scaled by the surfel's two standard deviations, (N, 3) each, and
    the unit normals (N, 3) (the rotation's third column; a zero quaternion is the identity)."""
    R = quat_rotation(quats.reshape(-1, 4))[3]                                       # (N, 3, 3)
    s = torch.exp(log_scales[:, :2])
    return R[:, :, 0] * s[:, :1], R[:, :, 1] * s[:, 1:2], R[:, :, 2]


def project_surfels(means: torch.Tensor, log_scales: torch.Tensor, quats: torch.Tensor, opacity: torch.Tensor,
                    cams: Cameras, near: float = 0.01) -> Dict[str, torch.Tensor]:
    """Project N surfels into B cameras (plain autograd, vectorised over B x N).

    Args:
        means: (N, 3) world centres; log_scales: (N, 2) or (N, 3) log tangent standard
            deviations (a third column, the thickness, is ignored); quats: (N, 4); opacity:
            (N,) in [0, 1]; cams: B cameras; near: near-plane depth (world units).
    Returns dict of
        means2d (B, N, 2) projected centres (px); rays (B, N, 9) the normalised adjugate ``A``
        (row-major); depth_row (B, N, 3) ``T``'s third row (``z(u, v) = depth_row . (u, v, 1)``);
        depth (B, N) centre depth; normals (B, N, 3) world unit normals turned to face each camera;
        floor (B, N) the floor's offset ``-2 ln rho`` >= 0 (its weight ``rho``, see the module docstring);
        box_centre (B, N, 2) and extent (B, N, 2) of the screen box (px, no gradient; 0 when
        culled); radius (B, N) its larger half-width (0 when culled); visible (B, N) bool.
    """
    dt = means.dtype
    R, t = cams.R.to(dt), cams.t.to(dt)
    fx, fy, cx, cy = (v.to(dt)[:, None] for v in (cams.fx, cams.fy, cams.cx, cams.cy))
    tu, tv, normal = surfel_frames(log_scales, quats)
    p = torch.einsum("bij,nj->bni", R, means) + t[:, None, :]                       # (B, N, 3)
    au = torch.einsum("bij,nj->bni", R, tu)
    av = torch.einsum("bij,nj->bni", R, tv)
    z = p[..., 2]
    in_front = z > near
    zs = torch.where(in_front, z, torch.ones_like(z))
    means2d = torch.stack([fx * p[..., 0] / zs + cx, fy * p[..., 1] / zs + cy], -1)
    # T's rows; the third column through means2d, so that its gradient is the screen-space one
    row0 = torch.stack([fx * au[..., 0] + cx * au[..., 2], fx * av[..., 0] + cx * av[..., 2], means2d[..., 0] * zs], -1)
    row1 = torch.stack([fy * au[..., 1] + cy * au[..., 2], fy * av[..., 1] + cy * av[..., 2], means2d[..., 1] * zs], -1)
    row2 = torch.stack([au[..., 2], av[..., 2], zs], -1)
    # T^-1 = [row1 x row2 | row2 x row0 | row0 x row1] / det (columns): A[k, j] = (cross_j)[k]
    cols = [torch.cross(row1, row2, dim=-1), torch.cross(row2, row0, dim=-1), torch.cross(row0, row1, dim=-1)]
    adj = torch.stack(cols, -1)                                                      # (B, N, 3, 3)
    det = (row0 * cols[0]).sum(-1)
    # the floor's weight: the disk's projected area (|det T| / z^3, px^2 per unit local area) over the floor's,
    # at most 1; carried as the offset -2 ln(weight) of the floor's quadratic form
    floor = -2.0 * torch.log((LOW_PASS_INV * det.abs() / zs ** 3).clamp(FLOOR_MIN, 1.0))
    with torch.no_grad():            # u, v are invariant to A's scale: a detached normaliser changes no gradient
        norm = adj.abs().amax((-2, -1)).clamp_min(torch.finfo(dt).tiny) * torch.where(det < 0, -1.0, 1.0).to(dt)
    rays = (adj / norm[..., None, None]).reshape(*adj.shape[:2], 9)
    centres = cams.centers().to(dt)
    facing = ((means[None] - centres[:, None]) * normal[None]).sum(-1) > 0               # normal points away
    normals = torch.where(facing[..., None], -normal[None], normal[None])
    with torch.no_grad():
        box, ext, visible = _screen_box(torch.stack([row0, row1, row2], -2), means2d, opacity, floor, in_front,
                                        cams.width, cams.height)
    return {"means2d": means2d, "rays": rays, "depth_row": row2, "depth": z, "normals": normals, "floor": floor,
            "box_centre": box, "extent": ext, "radius": ext.amax(-1), "visible": visible}


def _screen_box(T: torch.Tensor, means2d: torch.Tensor, opacity: torch.Tensor, floor: torch.Tensor,
                in_front: torch.Tensor, width: int, height: int):
    """Box centre and half-extents (B, N, 2) px of the surfels' ``alpha >= 1/255`` region (the
    disk's dual conic joined with the low-pass disk), and visible (B, N); culled: zero extent."""
    r2 = 2.0 * torch.log((opacity * 255.0).clamp_min(1.0))[None, :].expand(T.shape[:2])   # (B, N)
    tu, tv, tc = T[..., 0], T[..., 1], T[..., 2]                                      # columns (B, N, 3)
    D = r2[..., None, None] * (tu[..., :, None] * tu[..., None, :] + tv[..., :, None] * tv[..., None, :]) \
        - tc[..., :, None] * tc[..., None, :]
    d22 = D[..., 2, 2]
    ellipse = d22 < 0
    safe = torch.where(ellipse, d22, -torch.ones_like(d22))
    centre = torch.stack([D[..., 0, 2], D[..., 1, 2]], -1) / safe[..., None]
    half = torch.sqrt((torch.stack([D[..., 0, 2] ** 2 - D[..., 0, 0] * d22, D[..., 1, 2] ** 2 - D[..., 1, 1] * d22], -1)
                       ).clamp_min(0.0)) / safe.abs()[..., None]
    low = torch.sqrt((r2 - floor).clamp_min(0.0) / LOW_PASS_INV)[..., None]          # the floor's reach (px)
    lo = torch.minimum(centre - half, means2d - low)
    hi = torch.maximum(centre + half, means2d + low)
    box, ext = 0.5 * (lo + hi), 0.5 * (hi - lo)
    on_screen = (hi[..., 0] > 0) & (lo[..., 0] < width) & (hi[..., 1] > 0) & (lo[..., 1] < height)
    visible = in_front & ellipse & (r2 > 0) & on_screen & torch.isfinite(ext).all(-1)
    ext = torch.where(visible[..., None], ext, torch.zeros_like(ext))
    box = torch.where(visible[..., None], box, torch.zeros_like(box))
    return box, ext, visible
