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
2. **Culling.** Splats with ``z <= near`` or whose bounding square lies off screen are
   dropped (no contribution, zero gradient). The radius is ``3 sigma_max`` of the
   standard formulation tightened to where ``opacity * exp(-r^2 / 2 sigma_max^2)``
   reaches 1/255: beyond it every contribution is skipped anyway, so the tiling is exact
   (a dense every-Gaussian-at-every-pixel render gives the same image) while faint splats
   touch fewer tiles.
3. **Tile binning.** Every (splat, tile) overlap of the splat's square is enumerated,
   sorted by one int64 key ``tile * M + depth_rank`` and cut into chunks of ``chunk``
   splats per tile. Work and memory follow the number of overlaps, not ``N * H * W``.
4. **Compositing.** Per chunk, all ``tile_size^2`` pixels against all chunk splats at once:
   ``alpha = min(0.99, o * exp(-d^T conic d / 2))``, alphas below 1/255 skipped,
   transmittance as an exclusive cumsum of ``log(1 - alpha)`` inside the chunk plus the
   exclusive cumsum of the chunk totals of earlier chunks of the same tile (log space, no
   products of many small numbers). Per-pixel early termination: a splat whose inclusion
   would bring transmittance below 1e-4 and every later one are skipped (the CUDA rule).
   Groups of whole tiles are processed in turn so that at most about ``max_elements``
   (pixel, splat) pairs are live at once: bounded memory at any image size.

Everything is differentiable through autograd (means, log-scales, quaternions, opacity
logits, SH coefficients); ``means2d`` in the output retains its gradient so a
densification strategy can read the screen-space gradient after ``backward``.
"""

from __future__ import annotations

import math
from typing import Dict, Optional, Sequence, Union

import torch

from l3d_app.geometry.cameras import Cameras
from l3d_app.models.sh import sh_to_color

ALPHA_MAX = 0.99
ALPHA_MIN = 1.0 / 255.0
T_MIN = 1e-4
LOW_PASS = 0.3


def quaternion_to_rotation(quats: torch.Tensor, eps: float = 1e-12) -> torch.Tensor:
    """(N, 4) quaternions ``(w, x, y, z)``, any norm -> (N, 3, 3) rotation matrices.

    Quaternions are normalised; one with ``|q| <= eps`` (e.g. all zeros) is the identity,
    with finite (zero) gradients.
    """
    sq = (quats * quats).sum(-1, keepdim=True)
    ok = sq > eps * eps
    q = quats * torch.rsqrt(sq.clamp_min(eps * eps))
    ident = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=quats.dtype, device=quats.device)
    w, x, y, z = torch.where(ok, q, ident).unbind(-1)
    return torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ], dim=-1).reshape(*quats.shape[:-1], 3, 3)


def project_gaussians(means: torch.Tensor, log_scales: torch.Tensor, quats: torch.Tensor,
                      opacity: torch.Tensor, cams: Cameras, near: float = 0.01
                      ) -> Dict[str, torch.Tensor]:
    """Project N Gaussians into B cameras.

    Args:
        means: (N, 3) world positions; log_scales: (N, 3) log standard deviations (world
            units); quats: (N, 4) ``(w, x, y, z)``; opacity: (N,) in [0, 1].
        cams: B cameras (internal convention); near: near-plane depth (world units).
    Returns dict of
        means2d (B, N, 2) pixels (u right, v down); conic (B, N, 3) ``(A, B, C)`` of the
        inverse 2D covariance (px^-2); depth (B, N) camera z; radius (B, N) pixels (0 for
        culled splats, no gradient); visible (B, N) bool.
    """
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
    with torch.no_grad():
        # exact cover: beyond r = sigma_max * sqrt(2 ln(255 o)) every alpha < 1/255;
        # never more than 3 sigma... except for splats opaque enough to need up to 3.33.
        reach = torch.sqrt(2.0 * torch.log((opacity * 255.0).clamp_min(1.0)))
        radius = torch.sqrt(lam_max) * reach[None, :].expand_as(lam_max)
        on_screen = ((u + radius > 0) & (u - radius < W) & (v + radius > 0) & (v - radius < H))
        visible = in_front & on_screen & (radius > 0) & torch.isfinite(radius)
        radius = torch.where(visible, radius, torch.zeros_like(radius))
    return {"means2d": means2d, "conic": conic, "depth": z, "radius": radius, "visible": visible}


def _bin_tiles(mean2d: torch.Tensor, radius: torch.Tensor, depth: torch.Tensor, width: int, height: int,
               tile: int, chunk: int):
    """(splat, tile) overlaps sorted by (tile, depth), cut into per-tile chunks (no grad).

    Inputs for M visible splats: mean2d (M, 2), radius (M,), depth (M,).
    Returns table (n_chunks, chunk) splat indices (M = padding), chunk_tile (n_chunks,),
    chunk_rank (n_chunks,) position of the chunk within its tile, n_pairs.
    """
    dev = mean2d.device
    M = mean2d.shape[0]
    ntx, nty = -(-width // tile), -(-height // tile)
    u, v = mean2d[:, 0], mean2d[:, 1]
    x0 = torch.floor((u - radius) / tile).clamp(0, ntx).long()
    x1 = (torch.floor((u + radius) / tile) + 1).clamp(0, ntx).long()
    y0 = torch.floor((v - radius) / tile).clamp(0, nty).long()
    y1 = (torch.floor((v + radius) / tile) + 1).clamp(0, nty).long()
    wg, hg = (x1 - x0).clamp_min(0), (y1 - y0).clamp_min(0)
    cnt = wg * hg
    n_pairs = int(cnt.sum())
    rank = torch.empty(M, dtype=torch.long, device=dev)
    rank[torch.argsort(depth)] = torch.arange(M, device=dev)
    gid = torch.repeat_interleave(torch.arange(M, device=dev), cnt)
    local = torch.arange(n_pairs, device=dev) - (torch.cumsum(cnt, 0) - cnt)[gid]
    tid = (y0[gid] + local // wg[gid]) * ntx + x0[gid] + local % wg[gid]
    key, perm = torch.sort(tid * M + rank[gid])
    gid, tid = gid[perm], key // M
    n_t = torch.bincount(tid, minlength=ntx * nty)
    k_t = (n_t + chunk - 1) // chunk
    r = torch.arange(n_pairs, device=dev) - (torch.cumsum(n_t, 0) - n_t)[tid]
    chunk_start = torch.cumsum(k_t, 0) - k_t
    n_chunks = int(k_t.sum())
    table = torch.full((n_chunks, chunk), M, dtype=torch.long, device=dev)
    table[chunk_start[tid] + r // chunk, r % chunk] = gid
    chunk_tile = torch.repeat_interleave(torch.arange(ntx * nty, device=dev), k_t)
    chunk_rank = torch.arange(n_chunks, device=dev) - chunk_start[chunk_tile]
    return table, chunk_tile, chunk_rank, n_pairs


def _composite_tiles(table, chunk_tile, chunk_rank, mean2d, conic, opacity, feats, width, height,
                     tile: int, max_elements: int):
    """Front-to-back compositing of the binned splats of one view.

    mean2d (M, 2), conic (M, 3), opacity (M,), feats (M, F) (colour + depth). Returns
    (H, W, F) accumulated ``sum_i w_i f_i`` and (H, W) ``sum_i w_i`` (= 1 - transmittance).
    """
    dev, dt = mean2d.device, mean2d.dtype
    ntx, nty = -(-width // tile), -(-height // tile)
    P, F = tile * tile, feats.shape[1]
    pad = lambda x: torch.cat([x, x.new_zeros(1, *x.shape[1:])])  # noqa: E731  index M -> alpha 0
    m2, cn, op, ft = pad(mean2d), pad(conic), pad(opacity), pad(feats)
    ly, lx = torch.meshgrid(torch.arange(tile, device=dev, dtype=dt), torch.arange(tile, device=dev, dtype=dt),
                            indexing="ij")
    lx, ly = lx.reshape(-1) + 0.5, ly.reshape(-1) + 0.5
    out = torch.zeros(ntx * nty, P, F + 1, dtype=dt, device=dev)
    n_chunks, C = table.shape
    per_group = max(1, max_elements // (P * C))
    log_tmin = math.log(T_MIN)
    # groups of whole tiles: a tile belongs to the group in which its first chunk starts
    tile_first = chunk_rank == 0
    starts = torch.nonzero(tile_first).reshape(-1)
    group_of_tile = torch.div(starts, per_group, rounding_mode="floor")
    bounds = torch.nonzero(torch.diff(group_of_tile, prepend=group_of_tile.new_tensor([-1]))).reshape(-1)
    chunk_bounds = torch.cat([starts[bounds], starts.new_tensor([n_chunks])]).tolist()
    for c0, c1 in zip(chunk_bounds[:-1], chunk_bounds[1:]):
        tbl, ct, cr = table[c0:c1], chunk_tile[c0:c1], chunk_rank[c0:c1]
        px = ((ct % ntx) * tile).to(dt)[:, None] + lx                                # (G, P)
        py = ((ct // ntx) * tile).to(dt)[:, None] + ly
        m = m2[tbl]                                                                  # (G, C, 2)
        q = cn[tbl]                                                                  # (G, C, 3)
        dx = px[:, :, None] - m[:, None, :, 0]                                       # (G, P, C)
        dy = py[:, :, None] - m[:, None, :, 1]
        power = (-0.5 * q[:, None, :, 0]) * dx * dx - q[:, None, :, 1] * dx * dy - (0.5 * q[:, None, :, 2]) * dy * dy
        alpha = (op[tbl][:, None, :] * torch.exp(power)).clamp(max=ALPHA_MAX)
        alpha = torch.where(alpha >= ALPHA_MIN, alpha, torch.zeros_like(alpha))
        log1m = torch.log1p(-alpha)
        incl = torch.cumsum(log1m, dim=2)                                            # within chunk
        # exclusive prefix of the chunk totals of earlier chunks of the same tile
        tl = ct - ct[0]
        buf = torch.zeros(int(tl[-1]) + 1, int(cr.max()) + 1, P, dtype=dt, device=dev)
        tot = incl[:, :, -1]
        buf = buf.index_put((tl, cr), tot)
        pre = (torch.cumsum(buf, 1) - buf)[tl, cr]                                   # (G, P)
        log_t_incl = incl + pre[:, :, None]
        with torch.no_grad():
            keep = log_t_incl >= log_tmin                                            # early termination
        weight = torch.where(keep, alpha * torch.exp(log_t_incl - log1m), torch.zeros_like(alpha))
        res = torch.cat([torch.bmm(weight, ft[tbl]), weight.sum(-1, keepdim=True)], -1)  # (G, P, F+1)
        out = out.index_add(0, ct, res)
    img = out.reshape(nty, ntx, tile, tile, F + 1).permute(0, 2, 1, 3, 4).reshape(nty * tile, ntx * tile, F + 1)
    img = img[:height, :width]
    return img[..., :F], img[..., F]


def rasterize_gaussians(means: torch.Tensor, log_scales: torch.Tensor, quats: torch.Tensor,
                        opacity_logits: torch.Tensor, sh_coeffs: torch.Tensor, sh_degree: int,
                        cams: Cameras, background: Optional[Union[torch.Tensor, Sequence[float]]] = None,
                        near: float = 0.01, tile_size: int = 8, chunk: int = 32,
                        max_elements: int = 1 << 23) -> Dict[str, torch.Tensor]:
    """Render N 3D Gaussians into B cameras.

    Args:
        means: (N, 3) centres, world units.
        log_scales: (N, 3) log of the per-axis standard deviations (world units).
        quats: (N, 4) rotations ``(w, x, y, z)``, any norm (zero -> identity).
        opacity_logits: (N,) or (N, 1); opacity = sigmoid(logit).
        sh_coeffs: (N, K, 3) spherical-harmonic colour coefficients, K >= (sh_degree+1)^2.
        sh_degree: 0..3, the SH degree used.
        cams: B cameras (:class:`~l3d_app.geometry.cameras.Cameras`), one image size.
        background: (3,) RGB behind the splats (default black).
        near: near-plane depth (world units); splats closer are culled.
        tile_size: tile side in pixels; chunk: splats per tile processed together;
        max_elements: bound on live (pixel, splat) pairs per group of tiles (memory).
    Returns dict:
        color (B, H, W, 3) composited on the background; alpha (B, H, W) = 1 - final
        transmittance; depth (B, H, W) alpha-weighted camera depth ``sum_i w_i z_i``
        (divide by alpha for the expected depth of the covered part); means2d (B, N, 2)
        pixel centres of the splats (``retain_grad`` set when differentiable: the
        screen-space gradient for densification); radii (B, N) pixels (0 = culled);
        visible (B, N) bool; n_pairs (B,) number of (splat, tile) overlaps.
    """
    dt = means.dtype
    N = means.shape[0]
    cams = cams.to(device=means.device, dtype=dt)
    bg = torch.zeros(3, dtype=dt, device=means.device) if background is None else \
        torch.as_tensor(background, dtype=dt, device=means.device).reshape(3)
    opacity = torch.sigmoid(opacity_logits.reshape(N))
    proj = project_gaussians(means, log_scales, quats, opacity, cams, near=near)
    means2d = proj["means2d"]
    if means2d.requires_grad:
        means2d.retain_grad()
    centres = cams.centers()                                                         # (B, 3)
    H, W = cams.height, cams.width
    colors, alphas, depths, pairs = [], [], [], []
    for b in range(cams.batch_size):
        vis = torch.nonzero(proj["visible"][b]).reshape(-1)
        if vis.numel() == 0:
            colors.append(bg.expand(H, W, 3) + 0 * means.sum())
            alphas.append(torch.zeros(H, W, dtype=dt, device=means.device))
            depths.append(torch.zeros(H, W, dtype=dt, device=means.device))
            pairs.append(0)
            continue
        mv = means[vis]
        d = mv - centres[b]
        d = d * torch.rsqrt((d * d).sum(-1, keepdim=True).clamp_min(1e-24))
        rgb = sh_to_color(sh_degree, sh_coeffs[vis], d)
        m2, z = means2d[b, vis], proj["depth"][b, vis]
        with torch.no_grad():
            table, ct, cr, n_pairs = _bin_tiles(m2.detach(), proj["radius"][b, vis], z.detach(), W, H,
                                                tile_size, chunk)
        feats = torch.cat([rgb, z[:, None]], -1)
        acc, a = _composite_tiles(table, ct, cr, m2, proj["conic"][b, vis], opacity[vis], feats, W, H,
                                  tile_size, max_elements)
        colors.append(acc[..., :3] + (1.0 - a)[..., None] * bg)
        alphas.append(a)
        depths.append(acc[..., 3])
        pairs.append(n_pairs)
    return {"color": torch.stack(colors), "alpha": torch.stack(alphas), "depth": torch.stack(depths),
            "means2d": means2d, "radii": proj["radius"], "visible": proj["visible"],
            "n_pairs": torch.tensor(pairs)}
