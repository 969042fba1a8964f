"""3D Gaussian splatting rasteriser in pure PyTorch: tile-binned, vectorised, differentiable.

One public function, :func:`rasterize_gaussians`. The pipeline (standard 3DGS, Kerbl et al.
2023) in the library's OpenCV camera convention (``X_cam = R X_world + t``, pixel centres
at +0.5, see :mod:`l3d_app.geometry.cameras`):

1. **Projection.** ``Sigma = R_q S S^T R_q^T`` (quaternion ``(w, x, y, z)`` normalised; a
   zero quaternion is the identity rotation), mean to camera space, perspective Jacobian
   ``J = [[fx/z, 0, -fx x/z^2], [0, fy/z, -fy y/z^2]]`` (``x/z``, ``y/z`` clamped to 1.3x
   the view frustum as in 3DGS), ``Sigma_2D = J W Sigma W^T J^T + 0.3 I`` (the low-pass
   keeps sub-pixel splats invertible), conic ``Sigma_2D^-1`` computed on a normalised
   matrix so that huge covariances do not overflow.
2. **Culling.** Splats with ``z <= near`` or whose bounding box lies off screen are
   dropped (no contribution, zero gradient). The box bounds the ellipse where
   ``opacity * exp(-d^T conic d / 2)`` reaches 1/255 (half-widths ``r sqrt(Sigma_xx)``,
   ``r sqrt(Sigma_yy)`` with ``r = sqrt(2 ln(255 opacity))``, about 3 sigma): beyond it every
   contribution is skipped anyway, so the tiling is exact (a dense every-Gaussian-at-every-
   pixel render gives the same image) while faint splats touch fewer tiles. ``radii`` is
   the matching circle radius ``r sqrt(lambda_max)`` (for screen-size pruning).
3. **Tile binning** (:mod:`l3d_app.render.gaussians.composite`). Every (splat, tile)
   overlap of the splat's bounding box is enumerated and sorted by one int64 key
   ``tile * 2^32 + depth key``; each tile's pixels are tested against its splats in padded
   batches and only the (pixel, splat) pairs with ``alpha >= 1/255`` are kept, as one flat
   list grouped by pixel and sorted by depth. Work and memory follow the number of
   contributing overlaps, never ``N * H * W``; at most ``max_elements`` candidates are live.
4. **Compositing** (a custom autograd function with a hand-written backward):
   ``alpha = min(0.99, o * exp(-d^T conic d / 2))``, transmittance as an exclusive
   segmented cumsum of ``log(1 - alpha)`` in float64 (log space, no products of many small
   numbers), per-pixel early termination: a splat whose inclusion would bring
   transmittance below 1e-4 and every later one are skipped (the CUDA rule). The backward
   is the 3DGS one, ``dC/dalpha_k = T_k c_k - (sum_{j>k} w_j c_j) / (1 - alpha_k)``.

Everything is differentiable (means, log-scales, quaternions, opacity logits, SH
coefficients); ``means2d`` in the output retains its gradient so a
densification strategy can read the screen-space gradient after ``backward``.
"""

from __future__ import annotations

from typing import Dict, Optional, Sequence, Union

import torch

from l3d_app.geometry.cameras import Cameras
from l3d_app.render.gaussians.sh import sh_to_color
from l3d_app.render.gaussians.project import ProjectFunction, quat_rotation
from l3d_app.render.gaussians.composite import (ALPHA_MAX, ALPHA_MIN, T_MIN, CompositeFunction, bin_tiles,
                                                composite_pairs, splat_pixel_pairs)

LOW_PASS = 0.3
COVERED_ALPHA = 1e-4   # below this accumulated opacity a pixel has no expected depth (reported as 0)
__all__ = ["rasterize_gaussians", "project_gaussians", "quaternion_to_rotation", "ALPHA_MAX", "ALPHA_MIN", "T_MIN"]


def quaternion_to_rotation(quats: torch.Tensor, eps: float = 1e-12) -> torch.Tensor:
    """(N, 4) quaternions ``(w, x, y, z)``, any norm -> (N, 3, 3) rotation matrices.

    Quaternions are normalised; one with ``|q| <= eps`` (e.g. all zeros) is the identity,
    with finite (zero) gradients.
    """
    return quat_rotation(quats.reshape(-1, 4), eps)[3].reshape(*quats.shape[:-1], 3, 3)


def project_gaussians(means: torch.Tensor, log_scales: torch.Tensor, quats: torch.Tensor,
                      opacity: torch.Tensor, cams: Cameras, near: float = 0.01, custom_backward: bool = True
                      ) -> Dict[str, torch.Tensor]:
    """Project N Gaussians into B cameras.

    Args:
        means: (N, 3) world positions; log_scales: (N, 3) log standard deviations (world
            units); quats: (N, 4) ``(w, x, y, z)``; opacity: (N,) in [0, 1].
        cams: B cameras (internal convention); near: near-plane depth (world units).
        custom_backward: per camera one :class:`~l3d_app.render.gaussians.project.ProjectFunction`
            (hand-written backward); False: the plain-autograd reference below (same values).
    Returns dict of
        means2d (B, N, 2) pixels (u right, v down); conic (B, N, 3) ``(A, B, C)`` of the
        inverse 2D covariance (px^-2); depth (B, N) camera z; radius (B, N) pixels (0 for
        culled splats, no gradient); visible (B, N) bool.
    """
    W, H = cams.width, cams.height
    if custom_backward:
        outs = [ProjectFunction.apply(means, log_scales, quats, cams.R[b].to(means.dtype), cams.t[b].to(means.dtype),
                                      *(float(v[b]) for v in (cams.fx, cams.fy, cams.cx, cams.cy)), W, H, near)
                for b in range(cams.batch_size)]
        means2d, conic, z, diag, lam_max, in_front = (torch.stack(x) for x in zip(*outs))
        a, c = diag.unbind(-1)
    else:
        means2d, conic, z, a, c, lam_max, in_front = _project_autograd(means, log_scales, quats, cams, near)
    u, v = means2d[..., 0], means2d[..., 1]
    with torch.no_grad():
        # exact cover: beyond r = sigma_max * sqrt(2 ln(255 o)) every alpha < 1/255;
        # never more than 3 sigma... except for splats opaque enough to need up to 3.33.
        reach = torch.sqrt(2.0 * torch.log((opacity * 255.0).clamp_min(1.0)))
        radius = torch.sqrt(lam_max) * reach[None, :].expand_as(lam_max)
        # the level-set ellipse's bounding box: half-widths reach * sqrt(Sigma_xx), sqrt(Sigma_yy)
        ext = torch.stack([torch.sqrt(a), torch.sqrt(c)], -1) * reach[None, :, None]
        on_screen = ((u + ext[..., 0] > 0) & (u - ext[..., 0] < W) & (v + ext[..., 1] > 0) & (v - ext[..., 1] < H))
        visible = in_front & on_screen & (radius > 0) & torch.isfinite(radius)
        radius = torch.where(visible, radius, torch.zeros_like(radius))
        ext = torch.where(visible[..., None], ext, torch.zeros_like(ext))
    return {"means2d": means2d, "conic": conic, "depth": z, "radius": radius, "extent": ext, "visible": visible}


def _project_autograd(means, log_scales, quats, cams: Cameras, near: float):
    """Plain-autograd projection (the reference of ProjectFunction): means2d (B, N, 2),
    conic (B, N, 3), z, a, c (diagonal of Sigma_2D), lam_max, in_front (B, N)."""
    dt = means.dtype
    R, t = cams.R.to(dt), cams.t.to(dt)
    fx, fy, cx, cy = (v.to(dt)[:, None] for v in (cams.fx, cams.fy, cams.cx, cams.cy))
    W, H = cams.width, cams.height
    view = torch.einsum("bij,nj->bni", R, means) + t[:, None, :]                     # (B, N, 3)
    z = view[..., 2]
    in_front = z > near
    zs = torch.where(in_front, z, torch.ones_like(z))
    # 3DGS clamps x/z, y/z to 1.3x the frustum so the Jacobian stays sane at the borders.
    lim_lo_x, lim_hi_x = (-0.15 * W - cx) / fx, (1.15 * W - cx) / fx
    lim_lo_y, lim_hi_y = (-0.15 * H - cy) / fy, (1.15 * H - cy) / fy
    xz = torch.minimum(torch.maximum(view[..., 0] / zs, lim_lo_x), lim_hi_x)
    yz = torch.minimum(torch.maximum(view[..., 1] / zs, lim_lo_y), lim_hi_y)
    u = fx * view[..., 0] / zs + cx
    v = fy * view[..., 1] / zs + cy
    means2d = torch.stack([u, v], -1)
    zero = torch.zeros_like(zs)
    J = torch.stack([fx / zs, zero, -fx * xz / zs, zero, fy / zs, -fy * yz / zs], -1).reshape(*zs.shape, 2, 3)
    M = quaternion_to_rotation(quats) * torch.exp(log_scales)[:, None, :]            # (N, 3, 3) R S
    T = J @ R[:, None]                                                               # (B, N, 2, 3)
    TM = T @ M[None]                                                                 # (B, N, 2, 3)
    # Sigma_2D = (TM)(TM)^T + 0.3 I, normalised by k = its largest diagonal entry so that
    # determinant and conic never overflow, even for enormous splats.
    a = (TM[..., 0, :] ** 2).sum(-1) + LOW_PASS
    b = (TM[..., 0, :] * TM[..., 1, :]).sum(-1)
    c = (TM[..., 1, :] ** 2).sum(-1) + LOW_PASS
    k = torch.maximum(a, c)
    an, bn, cn = a / k, b / k, c / k
    det_n = (an * cn - bn * bn).clamp_min(1e-20)
    conic = torch.stack([cn, -bn, an], -1) / (det_n * k)[..., None]
    mid = 0.5 * (an + cn)
    lam_max = k * (mid + torch.sqrt((mid * mid - det_n).clamp_min(0.0)))            # px^2
    return means2d, conic, z, a.detach(), c.detach(), lam_max.detach(), in_front


def rasterize_gaussians(means: torch.Tensor, log_scales: torch.Tensor, quats: torch.Tensor,
                        opacity_logits: torch.Tensor, sh_coeffs: torch.Tensor, sh_degree: int,
                        cams: Cameras, background: Optional[Union[torch.Tensor, Sequence[float]]] = None,
                        near: float = 0.01, tile_size: int = 4, max_elements: int = 1 << 22,
                        custom_backward: bool = True) -> Dict[str, torch.Tensor]:
    """Render N 3D Gaussians into B cameras.

    Args:
        means: (N, 3) centres, world units.
        log_scales: (N, 3) log of the per-axis standard deviations (world units), or
            (N, 1) for isotropic splats (one scale, repeated on the three axes).
        quats: (N, 4) rotations ``(w, x, y, z)``, any norm (zero -> identity).
        opacity_logits: (N,) or (N, 1); opacity = sigmoid(logit).
        sh_coeffs: (N, K, 3) spherical-harmonic colour coefficients, K >= (sh_degree+1)^2.
        sh_degree: 0..3, the SH degree used.
        cams: B cameras (:class:`~l3d_app.geometry.cameras.Cameras`), one image size.
        background: (3,) RGB behind the splats (default black).
        near: near-plane depth (world units); splats closer are culled.
        tile_size: tile side in pixels.
        max_elements: bound on the (pixel, splat) candidates evaluated at once (memory).
        custom_backward: project and composite with the hand-written backwards (False:
            plain autograd through the same forwards, the reference).
    Returns dict:
        color (B, H, W, 3) composited on the background; alpha (B, H, W) = 1 - final
        transmittance (the accumulated opacity, the course's "mask"); depth (B, H, W)
        alpha-weighted camera depth ``sum_i w_i z_i`` (the course's depth map);
        expected_depth (B, H, W) = depth / alpha, the expected depth of the covered part
        (0 where alpha <= ``COVERED_ALPHA``; differentiable); means2d (B, N, 2)
        pixel centres of the splats (``retain_grad`` set when differentiable: the
        screen-space gradient for densification); radii (B, N) pixels (0 = culled);
        visible (B, N) bool; n_pairs (B,) number of (splat, tile) overlaps.
    """
    dt = means.dtype
    N = means.shape[0]
    log_scales = log_scales.expand(N, 3)
    cams = cams.to(device=means.device, dtype=dt)
    bg = torch.zeros(3, dtype=dt, device=means.device) if background is None else \
        torch.as_tensor(background, dtype=dt, device=means.device).reshape(3)
    opacity = torch.sigmoid(opacity_logits.reshape(N))
    proj = project_gaussians(means, log_scales, quats, opacity, cams, near=near, custom_backward=custom_backward)
    means2d = proj["means2d"]
    if means2d.requires_grad:
        means2d.retain_grad()
    centres = cams.centers()                                                         # (B, 3)
    H, W = cams.height, cams.width
    colors, alphas, depths, pairs = [], [], [], []
    for b in range(cams.batch_size):
        if not bool(proj["visible"][b].any()):
            colors.append(bg.expand(H, W, 3) + 0 * means.sum())
            alphas.append(torch.zeros(H, W, dtype=dt, device=means.device))
            depths.append(torch.zeros(H, W, dtype=dt, device=means.device))
            pairs.append(0)
            continue
        # every splat takes part (no gather of the visible ones, no scatter of their gradients
        # back): a culled splat has a zero extent, so it overlaps no tile and gets zero gradient
        d = means - centres[b]
        d = d * torch.rsqrt((d * d).sum(-1, keepdim=True).clamp_min(1e-24))
        rgb = sh_to_color(sh_degree, sh_coeffs, d)
        m2, z, conic = means2d[b], proj["depth"][b], proj["conic"][b]
        with torch.no_grad():
            sid, t_start, t_count = bin_tiles(m2, proj["extent"][b], z, W, H, tile_size)
            pix, spl = splat_pixel_pairs(sid, t_start, t_count, m2, conic, opacity, W, H, tile_size, max_elements)
        feats = torch.cat([rgb, z[:, None]], -1)
        fn = CompositeFunction.apply if custom_backward else composite_pairs
        acc, a = fn(pix, spl, m2, conic, opacity, feats, W, H)
        acc, a = acc.reshape(H, W, -1), a.reshape(H, W)
        n_pairs = int(sid.numel())
        colors.append(acc[..., :3] + (1.0 - a)[..., None] * bg)
        alphas.append(a)
        depths.append(acc[..., 3])
        pairs.append(n_pairs)
    alpha, depth = torch.stack(alphas), torch.stack(depths)
    covered = alpha > COVERED_ALPHA
    safe = torch.where(covered, alpha, torch.ones_like(alpha))
    expected = torch.where(covered, depth / safe, torch.zeros_like(depth))
    return {"color": torch.stack(colors), "alpha": alpha, "depth": depth, "expected_depth": expected,
            "means2d": means2d, "radii": proj["radius"], "visible": proj["visible"],
            "n_pairs": torch.tensor(pairs)}
