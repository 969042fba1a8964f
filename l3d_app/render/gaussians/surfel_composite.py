"""Front-to-back compositing of surfel (pixel, splat) pairs, with a hand-written backward.

The pairs come from :func:`~l3d_app.render.gaussians.composite.splat_pixel_pairs` (each pixel's
run sorted by the splats' centre depth); transmittance, early termination and the weights'
backward are those of :mod:`~l3d_app.render.gaussians.composite` (the same helpers). Per pair
``k`` of pixel ``p = (x, y)`` and splat ``i`` (see :mod:`~l3d_app.render.gaussians.surfel_project`):

* ``c = A_i (x, y, 1)``, ``(u, v) = (c0, c1) / c2``: the ray-splat intersection, ``q3 = u^2 + v^2``
  (+inf when ``c2 <= 0``: behind the camera); the low-pass floor ``q2 = LOW_PASS_INV |p - m_i|^2 + f_i``
  (``f_i = -2 ln rho_i``: the floor's weight, :mod:`~l3d_app.render.gaussians.surfel_project`);
  ``q = min(q3, q2)``, ``alpha = min(0.99, o_i exp(-q / 2))`` (0 below 1/255);
* depth ``z = depth_row_i . (u, v, 1)`` (camera z of the intersection) where ``q3 <= q2``, the
  centre's depth where the floor decides (as 2DGS);
* ``w_k = alpha_k T_k``. Outputs per pixel: ``sum w f_i`` (per-splat features: colour, normal),
  ``sum w``, ``sum w z``, the distortion ``sum_{k} sum_{j<k} w_k w_j (z_k - z_j)^2`` (the 2DGS
  depth-distortion on camera depth, world units squared) and the median depth: ``z`` of the last
  pair whose transmittance before it is above 0.5 (the first pair if none is).

Backward, with ``g_k = dL/dw_k`` summed over the outputs (the distortion's
``dD/dw_k = W z_k^2 - 2 z_k Z1 + Z2`` with the pixel's totals ``W = sum w``, ``Z1 = sum w z``,
``Z2 = sum w z^2``, all with ``z`` taken about the pixel's median depth, which the distortion does
not see and which keeps the expansion from cancelling): ``dL/dalpha_k = T_k g_k - (sum_{j>k} w_j g_j) / (1 - alpha_k)``; ``dL/dz_k``
collects ``w_k`` (depth sum), ``2 w_k (z_k W - Z1)`` (distortion) and the median's pick; then the
chain through ``(u, v)``, ``c`` and ``A``, scattered to the splats with ``index_add``.
:func:`surfel_composite_pairs` is the same forward in plain autograd (the reference the tests
compare the hand-written backward with).
"""

from __future__ import annotations

import math
from typing import Tuple

import torch

from l3d_app.render.gaussians.composite import (ALPHA_MAX, ALPHA_MIN, LOG_T_MIN, _segments, _transmittance,
                                                pixel_centres)
from l3d_app.render.gaussians.surfel_project import LOW_PASS_INV

LOG_HALF = math.log(0.5)


def _pair_geometry(pix, spl, mean2d, rays, depth_row, opacity, floor, width, height):
    """Per pair: alpha (K,), depth z (K,) and what the backward needs: (u, v, c2, use3, px, py,
    dx, dy, the splat's opacity and depth row (2 columns)). Column by column (contiguous rows)."""
    cx, cy = pixel_centres(width, height, mean2d.dtype, mean2d.device).unbind(1)
    px, py = cx.contiguous().index_select(0, pix), cy.contiguous().index_select(0, pix)
    a = [x.contiguous().index_select(0, spl) for x in rays.unbind(1)]
    c0, c1, c2 = (a[3 * k] * px + a[3 * k + 1] * py + a[3 * k + 2] for k in range(3))
    front = c2 > 0
    c2s = torch.where(front, c2, torch.ones_like(c2))
    u, v = c0 / c2s, c1 / c2s
    q3 = torch.where(front, u * u + v * v, torch.full_like(u, float("inf")))
    mu, mv, o, f = (x.contiguous().index_select(0, spl) for x in (*mean2d.unbind(1), opacity, floor))
    dx, dy = px - mu, py - mv
    q2 = LOW_PASS_INV * (dx * dx + dy * dy) + f
    use3 = q3 <= q2
    q = torch.where(use3, q3, q2)
    alpha = (torch.exp(q * -0.5) * o).clamp(max=ALPHA_MAX)
    alpha = torch.where(alpha >= ALPHA_MIN, alpha, torch.zeros_like(alpha))
    r0, r1, r2 = (x.contiguous().index_select(0, spl) for x in depth_row.unbind(1))
    u, v = torch.where(use3, u, torch.zeros_like(u)), torch.where(use3, v, torch.zeros_like(v))
    z = r0 * u + r1 * v + r2
    return alpha, z, (u, v, c2s, use3, px, py, dx, dy, o, r0, r1)


def _exclusive(x: torch.Tensor, seg: torch.Tensor, last: torch.Tensor) -> torch.Tensor:
    """Per pair the sum of ``x`` over the earlier pairs of its pixel (float64 segmented cumsum, float64)."""
    x = x.to(torch.float64)
    incl = torch.cumsum(x, 0)
    start = torch.cat([incl.new_zeros(1), incl.index_select(0, last[:-1])])
    return incl - start.index_select(0, seg) - x


def _distortion(w: torch.Tensor, z: torch.Tensor, seg: torch.Tensor, last: torch.Tensor) -> torch.Tensor:
    """Per pair ``w_k sum_{j<k} w_j (z_k - z_j)^2`` expanded in the pixel's running sums, in float64
    (the expansion cancels: float32 leaves 1e-7 of noise on a plane at depth 3)."""
    w64, z64 = w.to(torch.float64), z.to(torch.float64)
    b0, b1, b2 = (_exclusive(x, seg, last) for x in (w64, w64 * z64, w64 * z64 * z64))
    return (w64 * (z64 * z64 * b0 - 2 * z64 * b1 + b2)).to(w.dtype)


def _median_pairs(log_t: torch.Tensor, seg: torch.Tensor, last: torch.Tensor) -> torch.Tensor:
    """(S,) index of each pixel's median pair: the last whose transmittance before it exceeds 0.5
    (transmittance only falls along a run, so these pairs are a prefix; the first always is)."""
    count = torch.zeros(last.shape[0], dtype=torch.long, device=seg.device).index_add_(0, seg, (log_t > LOG_HALF).long())
    first = torch.cat([last.new_zeros(1), last[:-1] + 1])
    return first + count.clamp_min(1) - 1


def surfel_composite_pairs(pix, spl, mean2d, rays, depth_row, opacity, floor, feats, width, height):
    """Reference forward in plain autograd: (H*W, F) ``sum w f``, (H*W,) ``sum w``, ``sum w z``,
    distortion and median depth (0 where a pixel has no pair)."""
    HW = width * height
    seg, last = _segments(pix)
    alpha, z, _ = _pair_geometry(pix, spl, mean2d, rays, depth_row, opacity, floor, width, height)
    log1m = torch.log1p(-alpha)
    incl = torch.cumsum(log1m, 0)
    log_t_incl = incl - torch.cat([incl.new_zeros(1), incl[last[:-1]]])[seg]
    keep = (log_t_incl >= LOG_T_MIN).detach()
    log_t = log_t_incl - log1m
    w = torch.where(keep, alpha * torch.exp(log_t), torch.zeros_like(alpha))
    dist = _distortion(w, z, seg, last)
    zeros = torch.zeros(HW, dtype=feats.dtype, device=feats.device)
    acc = torch.zeros(HW, feats.shape[1], dtype=feats.dtype, device=feats.device).index_add(0, pix, w[:, None] * feats[spl])
    med = _median_pairs(log_t.detach(), seg, last)
    median = zeros.index_put((pix[last],), z[med])
    return (acc, zeros.index_add(0, pix, w), zeros.index_add(0, pix, w * z), zeros.index_add(0, pix, dist), median)


class SurfelCompositeFunction(torch.autograd.Function):
    """forward(pix (K,), spl (K,), mean2d (M, 2), rays (M, 9), depth_row (M, 3), opacity (M,),
    floor (M,), feats (M, F), width, height) -> acc (H*W, F), alpha (H*W,), depth sum (H*W,), distortion
    (H*W,), median depth (H*W,); see the module docstring. Attribute-major per-pair work, as
    :class:`~l3d_app.render.gaussians.composite.CompositeFunction`."""

    @staticmethod
    def forward(ctx, pix, spl, mean2d, rays, depth_row, opacity, floor, feats, width, height):
        HW = width * height
        seg, last = _segments(pix)
        alpha, z, geo = _pair_geometry(pix, spl, mean2d, rays, depth_row, opacity, floor, width, height)
        log_t, keep = _transmittance(alpha, seg, last)
        if not bool(keep.all()):                 # terminated pairs carry no work (nor gradient)
            k = torch.nonzero(keep).reshape(-1)
            pix, spl, alpha, z, log_t, seg = (x.index_select(0, k) for x in (pix, spl, alpha, z, log_t, seg))
            geo = tuple(x.index_select(0, k) for x in geo)
            last = torch.cumsum(keep, 0).index_select(0, last) - 1
        T = torch.exp(log_t).to(alpha.dtype)
        w = alpha * T
        med = _median_pairs(log_t, seg, last)
        median = torch.zeros(HW, dtype=feats.dtype, device=feats.device)
        median[pix.index_select(0, last)] = z.index_select(0, med)
        is_med = torch.zeros_like(alpha, dtype=torch.bool)
        is_med[med] = True
        zc = z - z.index_select(0, med).index_select(0, seg)       # the distortion is shift-invariant: about the median
        fk = torch.cat([feats.t().contiguous().index_select(1, spl), w[None].new_ones(1, w.shape[0]), z[None],
                        zc[None], (zc * zc)[None]], 0)                                 # (F + 4, K)
        sums = torch.zeros(fk.shape[0], HW, dtype=feats.dtype, device=feats.device).index_add_(1, pix, fk * w)
        dist = _distortion(w, zc, seg, last)
        distortion = torch.zeros(HW, dtype=feats.dtype, device=feats.device).index_add_(0, pix, dist)
        F = feats.shape[1]
        ctx.save_for_backward(pix, spl, seg, last, alpha, T, z, zc, is_med, sums[[F, F + 2, F + 3]], *geo, fk[:F])
        ctx.n_splats = mean2d.shape[0]
        return sums[:F].t(), sums[F], sums[F + 1], distortion, median

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, g_acc, g_alpha, g_depth, g_dist, g_median):
        (pix, spl, seg, last, alpha, T, z, zc, is_med, totals, u, v, c2, use3, px, py, dx, dy, o, r0, r1,
         fk) = ctx.saved_tensors
        w = alpha * T
        F = fk.shape[0]
        G = torch.cat([g_acc.t(), g_alpha[None], g_depth[None], g_dist[None], g_median[None]], 0).index_select(1, pix)
        W, Z1, Z2 = totals.index_select(1, pix)              # the pixel's sums of w, w zc, w zc^2, per pair
        gd = G[F + 2]
        # dL/dw_k over every output, then the 3DGS identity for dL/dalpha_k
        g = (G[:F] * fk).sum(0) + G[F] + G[F + 1] * z + gd * (W * zc * zc - 2 * zc * Z1 + Z2)
        cs = torch.cumsum((w * g).to(torch.float64), 0)
        suffix = (cs.index_select(0, last).index_select(0, seg) - cs).to(alpha.dtype)
        d_alpha = T * g - suffix / (1.0 - alpha)
        d_q = torch.where(alpha < ALPHA_MAX, -0.5 * d_alpha * alpha, torch.zeros_like(d_alpha))
        g_z = G[F + 1] * w + gd * 2 * w * (zc * W - Z1) + torch.where(is_med, G[F + 3], torch.zeros_like(z))
        # the ray-splat branch: q3 = u^2 + v^2, z = r0 u + r1 v + r2, (u, v) = (c0, c1) / c2
        g_u = torch.where(use3, 2 * u * d_q + r0 * g_z, torch.zeros_like(u))
        g_v = torch.where(use3, 2 * v * d_q + r1 * g_z, torch.zeros_like(v))
        gc0, gc1 = g_u / c2, g_v / c2
        gc2 = -(g_u * u + g_v * v) / c2
        low = torch.where(use3, torch.zeros_like(d_q), d_q) * (-2.0 * LOW_PASS_INV)
        out = torch.empty(16 + F, w.shape[0], dtype=w.dtype, device=w.device)
        torch.mul(low, dx, out=out[0])
        torch.mul(low, dy, out=out[1])
        for k, gk in enumerate((gc0, gc1, gc2)):
            torch.mul(gk, px, out=out[2 + 3 * k])
            torch.mul(gk, py, out=out[3 + 3 * k])
            out[4 + 3 * k] = gk
        torch.mul(g_z, u, out=out[11])
        torch.mul(g_z, v, out=out[12])
        out[13] = g_z
        torch.div(-2.0 * d_q, o, out=out[14])                                             # d alpha / d o = alpha / o
        torch.where(use3, torch.zeros_like(d_q), d_q, out=out[15])                        # d q / d floor = 1
        torch.mul(G[:F], w, out=out[16:])
        g_splat = torch.zeros(16 + F, ctx.n_splats, dtype=out.dtype, device=out.device).index_add_(1, spl, out)
        return (None, None, g_splat[:2].t(), g_splat[2:11].t(), g_splat[11:14].t(), g_splat[14], g_splat[15],
                g_splat[16:].t(), None, None)


def composite_surfels(pix: torch.Tensor, spl: torch.Tensor, mean2d, rays, depth_row, opacity, floor, feats,
                      width: int, height: int, custom_backward: bool = True) -> Tuple[torch.Tensor, ...]:
    """:class:`SurfelCompositeFunction` (``custom_backward``) or its autograd reference."""
    if custom_backward:
        return SurfelCompositeFunction.apply(pix, spl, mean2d, rays, depth_row, opacity, floor, feats, width, height)
    return surfel_composite_pairs(pix, spl, mean2d, rays, depth_row, opacity, floor, feats, width, height)
