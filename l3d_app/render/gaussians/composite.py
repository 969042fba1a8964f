"""Tile binning and front-to-back compositing of projected 2D Gaussians (one view).

The fast path of :func:`l3d_app.render.gaussians.rasterize.rasterize_gaussians`:

1. :func:`bin_tiles` enumerates every (splat, tile) overlap of the splats' bounding boxes
   and sorts them with one argsort of the int64 key ``tile * 2^32 + depth_key`` (the key is
   the float32 depth's bit pattern made monotone, or its rank for other dtypes).
2. :func:`splat_pixel_pairs` (no autograd) tests, per tile, all its pixels against all its
   splats in padded batches (tiles grouped by how many splats they hold, powers of two, so
   padding stays below 2x; at most ``max_elements`` candidates live at once): the quadratic
   form ``d^T conic d`` is one batched matmul of the pixels' monomials ``(1, x, y, x^2, xy,
   y^2)`` with per-splat coefficients, compared with ``2 ln(255 opacity)``. It keeps only
   the (pixel, splat) pairs with ``alpha >= 1/255``: a flat list in which each pixel's pairs
   form one contiguous run sorted by depth. Every later step works on these K pairs, never
   on ``pairs x pixels``.
3. :class:`CompositeFunction` composites them front to back with a hand-written backward:
   transmittance is an exclusive segmented cumsum of ``log(1 - alpha)`` (float64, one
   global cumsum minus each pixel's start), early termination drops a pixel's pairs from
   the one that would bring the transmittance below ``T_MIN``; the backward uses the
   3DGS identity ``dC/dalpha_k = T_k c_k - (sum_{j>k} w_j c_j) / (1 - alpha_k)`` with the
   suffix sums from the same segmented cumsum, and scatters to the splats with
   ``index_add``. :func:`composite_pairs` is the same forward through plain autograd
   (the reference the tests compare the hand-written backward with).
"""

from __future__ import annotations

import math
from typing import Optional, Tuple

import torch

ALPHA_MAX = 0.99
ALPHA_MIN = 1.0 / 255.0
T_MIN = 1e-4
LOG_T_MIN = math.log(T_MIN)


_DEPTH_KEYS = 1 << 32


def _depth_key(depth: torch.Tensor) -> torch.Tensor:
    """(M,) int64 in [0, 2^32) ordered as ``depth``: for float32 its bit pattern made monotone
    (no sort of the depths; equal depths tie), otherwise the rank in an argsort."""
    if depth.dtype == torch.float32:
        bits = depth.contiguous().view(torch.int32).long()
        # IEEE floats order as sign-magnitude integers: negatives (bits < 0) map to [0, 2^31)
        # in reverse, non-negatives to [2^31, 2^32)
        return torch.where(bits < 0, -1 - bits, bits + (1 << 31))
    rank = torch.empty(depth.shape[0], dtype=torch.long, device=depth.device)
    rank[torch.argsort(depth)] = torch.arange(depth.shape[0], device=depth.device)
    return rank


@torch.no_grad()
def bin_tiles(mean2d: torch.Tensor, ext: torch.Tensor, depth: torch.Tensor, width: int, height: int,
              tile: int) -> Tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(splat, tile) overlaps sorted by (tile, depth).

    Args: mean2d (M, 2) px, ext (M, 2) half-extents of the bounding box in x, y (px; a
        splat with a zero half-extent is culled and overlaps no tile), depth (M,) camera z;
        tile: tile side (px).
    Returns: sid (n_pairs,) splat index per overlap, sorted by tile then depth;
        tile_start (n_tiles,) first overlap of each tile; tile_count (n_tiles,).
    """
    dev = mean2d.device
    M = mean2d.shape[0]
    ntx, nty = -(-width // tile), -(-height // tile)
    u, v = mean2d[:, 0], mean2d[:, 1]
    x0 = torch.floor((u - ext[:, 0]) / tile).clamp(0, ntx).long()
    x1 = (torch.floor((u + ext[:, 0]) / tile) + 1).clamp(0, ntx).long()
    y0 = torch.floor((v - ext[:, 1]) / tile).clamp(0, nty).long()
    y1 = (torch.floor((v + ext[:, 1]) / tile) + 1).clamp(0, nty).long()
    wg, hg = (x1 - x0).clamp_min(0), (y1 - y0).clamp_min(0)
    cnt = torch.where((ext > 0).all(1), wg * hg, torch.zeros_like(wg))
    n_pairs = int(cnt.sum())
    gid = torch.repeat_interleave(torch.arange(M, device=dev), cnt)
    # gathers by index_select: on CPU several times faster than advanced indexing x[idx]
    local = torch.arange(n_pairs, device=dev) - (torch.cumsum(cnt, 0) - cnt).index_select(0, gid)
    wgg = wg.index_select(0, gid)
    tid = (y0.index_select(0, gid) + local // wgg) * ntx + x0.index_select(0, gid) + local % wgg
    order = torch.argsort(tid * _DEPTH_KEYS + _depth_key(depth).index_select(0, gid))
    sid = gid.index_select(0, order)
    count = torch.bincount(tid, minlength=ntx * nty)
    return sid, torch.cumsum(count, 0) - count, count


def pixel_centres(width: int, height: int, dtype, device) -> torch.Tensor:
    """(H*W, 2) pixel centres ``(u, v) = (col + 0.5, row + 0.5)``, row-major."""
    v, u = torch.meshgrid(torch.arange(height, dtype=dtype, device=device) + 0.5,
                          torch.arange(width, dtype=dtype, device=device) + 0.5, indexing="ij")
    return torch.stack([u.reshape(-1), v.reshape(-1)], -1)


@torch.no_grad()
def splat_pixel_pairs(sid: torch.Tensor, tile_start: torch.Tensor, tile_count: torch.Tensor,
                      mean2d: torch.Tensor, conic: torch.Tensor, opacity: torch.Tensor,
                      width: int, height: int, tile: int, max_elements: int = 1 << 22,
                      rays: Optional[torch.Tensor] = None, floor: Optional[torch.Tensor] = None
                      ) -> Tuple[torch.Tensor, torch.Tensor]:
    """Flat (pixel, splat) pairs with ``alpha >= 1/255``; each pixel's pairs are one run, by depth.

    Args: the output of :func:`bin_tiles`; mean2d (M, 2), conic (M, 3) ``(A, B, C)`` of
        the inverse 2D covariance, opacity (M,); image and tile size (px).
        rays: surfels only (:mod:`l3d_app.render.gaussians.surfels`): (M, 9) the row-major
            3x3 matrix ``A`` taking a pixel ``(x, y, 1)`` to ``c`` with the ray-splat
            intersection ``(u, v) = (c0, c1) / c2`` (in front of the camera where ``c2 > 0``);
            the quadratic form is then ``min(d^T conic d + floor, u^2 + v^2)`` (``conic`` is the
            low-pass floor, ``floor`` (M,) its offset, default 0).
    Returns: pix (K,) pixel index ``row * width + col``, spl (K,) splat index.
    """
    dev, dt = mean2d.device, mean2d.dtype
    M = mean2d.shape[0]
    ntx = -(-width // tile)
    P = tile * tile
    # one padded column per attribute (entry M: padding, opacity 0), gathered column by column
    # so the arithmetic below runs on contiguous (G, L) arrays; gathers by index_select, on CPU
    # several times faster than advanced indexing
    cols = [torch.cat([x.contiguous(), x.new_zeros(1)]) for x in (*mean2d.unbind(1), *conic.unbind(1), opacity)]
    ray_cols = [] if rays is None else [torch.cat([x.contiguous(), x.new_zeros(1)]) for x in rays.unbind(1)]
    if floor is not None:
        cols.append(torch.cat([floor.contiguous(), floor.new_zeros(1)]))
    sidp = torch.cat([sid, sid.new_full((1,), M)])
    ly, lx = torch.meshgrid(torch.arange(tile, device=dev), torch.arange(tile, device=dev), indexing="ij")
    ly, lx = ly.reshape(-1), lx.reshape(-1)
    # q = d^T conic d as a quadratic in the tile-local pixel centre (lx, ly): the candidates of
    # a group of tiles are ONE batched matmul of per-pixel monomials with per-splat coefficients
    mono = torch.stack([torch.ones(P, device=dev), lx, ly, lx * lx, lx * ly, ly * ly], 1).to(dt)   # (P, 6)
    tiles = torch.nonzero(tile_count).reshape(-1)
    pix_out, spl_out = [sid.new_zeros(0)], [sid.new_zeros(0)]
    if tiles.numel():
        counts, starts = tile_count.index_select(0, tiles), tile_start.index_select(0, tiles)
        level = torch.ceil(torch.log2(counts.to(torch.float64))).long()
        for lv in torch.unique(level).tolist():
            at = torch.nonzero(level == lv).reshape(-1)
            tl, cnt, st = tiles.index_select(0, at), counts.index_select(0, at), starts.index_select(0, at)
            L = int(cnt.max())
            per = max(1, max_elements // (P * L))
            slot = torch.arange(L, device=dev)
            for g0 in range(0, tl.numel(), per):
                t = tl[g0:g0 + per]
                idx = torch.where(slot < cnt[g0:g0 + per, None], st[g0:g0 + per, None] + slot, sid.numel())
                s = sidp.index_select(0, idx.reshape(-1))                               # (G*L,)
                u, v, A, B, C, o, *off = (c.index_select(0, s).reshape(-1, L) for c in cols)  # each (G, L)
                x0, y0 = (t % ntx) * tile, torch.div(t, ntx, rounding_mode="floor") * tile
                ox = u - (x0.to(dt) + 0.5)[:, None]                                    # splat centre, tile-local
                oy = v - (y0.to(dt) + 0.5)[:, None]
                const = A * ox * ox + 2 * B * ox * oy + C * oy * oy
                coef = torch.stack([const + off[0] if off else const, -2 * (A * ox + B * oy),
                                    -2 * (B * ox + C * oy), A, 2 * B, C], 1)            # (G, 6, L)
                # alpha = o exp(-q/2) >= 1/255  <=>  q <= 2 ln(255 o)   (padding: o = 0, never)
                thr = 2.0 * torch.log(o * 255.0)
                if ray_cols:
                    hit = _ray_splat_hits(mono, coef, ray_cols, s, L, x0, y0, thr, dt)
                else:
                    hit = torch.matmul(mono, coef) <= thr[:, None, :]                 # (G, P, L)
                f = torch.nonzero(hit.reshape(-1)).reshape(-1)
                gp = torch.div(f, L, rounding_mode="floor")                            # (tile, pixel)
                col, row = x0[:, None] + lx, y0[:, None] + ly                          # (G, P)
                pix = torch.where((col < width) & (row < height), row * width + col, -1).reshape(-1).index_select(0, gp)
                sp = s.index_select(0, torch.div(gp, P, rounding_mode="floor") * L + (f - gp * L))
                if width % tile or height % tile:                                    # pixels past the border
                    inside = torch.nonzero(pix >= 0).reshape(-1)
                    pix, sp = pix.index_select(0, inside), sp.index_select(0, inside)
                spl_out.append(sp)
                pix_out.append(pix)
    return torch.cat(pix_out), torch.cat(spl_out)


def _ray_splat_hits(mono, coef, ray_cols, s, L, x0, y0, thr, dt) -> torch.Tensor:
    """(G, P, L) bool: the low-pass form (``mono @ coef``) or the ray-splat form ``u^2 + v^2`` is
    within ``thr`` (G, L), for the pixels of G tiles (origins ``x0``, ``y0`` (G,); ``mono`` (P, 6)
    their local monomials ``(1, lx, ly, ...)``) and the splats ``s`` (G*L,) whose rows of ``A`` are
    ``ray_cols`` (9 padded columns). ``c = A (x, y, 1)`` is linear in the local offsets, so its three
    components come from the same matmul as the low-pass form; ``u^2 + v^2 <= thr`` is tested as
    ``c0^2 + c1^2 <= thr c2^2`` with ``c2 > 0`` (the intersection in front of the camera): no division."""
    a = [c.index_select(0, s).reshape(-1, L) for c in ray_cols]                     # each (G, L)
    px0, py0 = (x0.to(dt) + 0.5)[:, None], (y0.to(dt) + 0.5)[:, None]
    zero = torch.zeros_like(a[0])
    comps = [torch.stack([a[3 * k] * px0 + a[3 * k + 1] * py0 + a[3 * k + 2], a[3 * k], a[3 * k + 1],
                          zero, zero, zero], 1) for k in range(3)]                     # each (G, 6, L)
    full = torch.matmul(mono, torch.cat([coef, *comps], 2))                            # (G, P, 4L)
    q, c0, c1, c2 = full.split(L, 2)
    t = thr[:, None, :]
    return (q <= t) | ((c2 > 0) & (c0 * c0 + c1 * c1 <= t * c2 * c2))


def _segments(pix: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
    """For pixel-grouped pairs: (K,) segment id of each pair and (S,) last pair of each segment."""
    new = torch.empty_like(pix, dtype=torch.bool)
    new[:1] = True
    torch.ne(pix[1:], pix[:-1], out=new[1:])
    seg = torch.cumsum(new, 0) - 1
    last = torch.empty_like(new)
    last[-1:] = True
    last[:-1] = new[1:]
    return seg, torch.nonzero(last).reshape(-1)


def _pair_terms(pix, spl, mean2d, conic, opacity, width, height):
    """Per pair: alpha (K,) clamped to ALPHA_MAX, offsets dx, dy (K,) px and the splat's
    ``(A, B, C, opacity)``, four (K,) tensors.

    Column by column: one 1D gather per attribute, and the arithmetic on contiguous (K,)
    rows (on CPU the columns of a gathered (K, 6) array are strided, and elementwise work on
    them was the larger part of this function: 25.8 vs 17.3 ms at 816 627 pairs, 2 cores).
    """
    cx, cy = pixel_centres(width, height, mean2d.dtype, mean2d.device).unbind(1)
    u, v, A, B, C, o = (x.contiguous().index_select(0, spl) for x in (*mean2d.unbind(1), *conic.unbind(1), opacity))
    dx = cx.contiguous().index_select(0, pix) - u
    dy = cy.contiguous().index_select(0, pix) - v
    power = torch.addcmul(dx * dx * A + dy * dy * C, dx * dy, B, value=2.0)
    alpha = (torch.exp(power * -0.5) * o).clamp(max=ALPHA_MAX)
    # the pair test rounds differently: a pair at the 1/255 border contributes nothing, as in the reference
    return torch.where(alpha >= ALPHA_MIN, alpha, torch.zeros_like(alpha)), dx, dy, (A, B, C, o)


def _transmittance(alpha: torch.Tensor, seg: torch.Tensor, last: torch.Tensor):
    """log transmittance before each pair (K,) (float64) and the early-termination mask."""
    log1m = torch.log1p(-alpha).to(torch.float64)
    incl = torch.cumsum(log1m, 0)
    start = torch.cat([incl.new_zeros(1), incl.index_select(0, last[:-1])])    # exclusive total per segment
    log_t_incl = incl - start.index_select(0, seg)
    return log_t_incl - log1m, log_t_incl >= LOG_T_MIN


def composite_pairs(pix, spl, mean2d, conic, opacity, feats, width, height):
    """Reference forward in plain autograd: (H*W, F) ``sum_k w_k f_k`` and (H*W,) ``sum_k w_k``."""
    seg, last = _segments(pix)
    alpha, _, _, _ = _pair_terms(pix, spl, mean2d, conic, opacity, width, height)
    log1m = torch.log1p(-alpha)
    incl = torch.cumsum(log1m, 0)
    log_t_incl = incl - torch.cat([incl.new_zeros(1), incl[last[:-1]]])[seg]
    keep = (log_t_incl >= LOG_T_MIN).detach()
    w = torch.where(keep, alpha * torch.exp(log_t_incl - log1m), torch.zeros_like(alpha))
    HW = width * height
    acc = torch.zeros(HW, feats.shape[1], dtype=feats.dtype, device=feats.device)
    return acc.index_add(0, pix, w[:, None] * feats[spl]), torch.zeros_like(acc[:, 0]).index_add(0, pix, w)


class CompositeFunction(torch.autograd.Function):
    """Front-to-back compositing of flat pixel-grouped pairs with a hand-written backward.

    forward(pix (K,), spl (K,), mean2d (M, 2), conic (M, 3), opacity (M,), feats (M, F),
    width, height) -> acc (H*W, F) = ``sum_k w_k f_k``, alpha (H*W,) = ``sum_k w_k``, with
    ``w_k = alpha_k T_k`` and early-terminated pairs dropped. The per-pair features, the
    forward sum and the backward's scatter to the splats are attribute-major ((columns, pairs),
    each row contiguous): on CPU an ``index_add_`` along dim 1 of that layout is several times
    faster than into the rows of a (splats, columns) array. The outputs and gradients are
    (rows, columns) views of them.
    """

    @staticmethod
    def forward(ctx, pix, spl, mean2d, conic, opacity, feats, width, height):
        seg, last = _segments(pix)
        alpha, dx, dy, a = _pair_terms(pix, spl, mean2d, conic, opacity, width, height)
        log_t, keep = _transmittance(alpha, seg, last)
        if not bool(keep.all()):                 # terminated pairs carry no work (nor gradient)
            # a pixel keeps a prefix of its run, never less than its first pair (alpha <= 0.99 leaves
            # T >= 0.01 > T_MIN): every segment survives, so the segments follow from the kept counts
            k = torch.nonzero(keep).reshape(-1)
            pix, spl, alpha, log_t, dx, dy, *a = (x.index_select(0, k) for x in (pix, spl, alpha, log_t, dx, dy, *a))
            seg = seg.index_select(0, k)
            last = torch.cumsum(keep, 0).index_select(0, last) - 1
        T = torch.exp(log_t).to(alpha.dtype)
        w = alpha * T
        fk = torch.cat([feats.t().contiguous().index_select(1, spl), torch.ones_like(w)[None]], 0)     # (F+1, K)
        acc = torch.zeros(fk.shape[0], width * height, dtype=feats.dtype, device=feats.device)
        acc.index_add_(1, pix, fk * w)
        ctx.save_for_backward(pix, spl, seg, last, alpha, T, dx, dy, *a, fk)
        ctx.n_splats = mean2d.shape[0]
        return acc[:-1].t(), acc[-1]

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, g_acc, g_alpha):
        pix, spl, seg, last, alpha, T, dx, dy, A, B, C, o, fk = ctx.saved_tensors
        w = alpha * T
        F = fk.shape[0] - 1
        G = torch.cat([g_acc.t(), g_alpha[None]], 0).index_select(1, pix)             # (F+1, K)
        g = (G * fk).sum(0)                                                          # dL/d(acc at pair)
        cs = torch.cumsum((w * g).to(torch.float64), 0)
        suffix = (cs.index_select(0, last).index_select(0, seg) - cs).to(alpha.dtype)  # sum_{j > k} w_j g_j
        d_alpha = T * g - suffix / (1.0 - alpha)
        d_pow = torch.where(alpha < ALPHA_MAX, d_alpha * alpha, torch.zeros_like(d_alpha))
        out = torch.empty(6 + F, w.shape[0], dtype=w.dtype, device=w.device)            # (6 + F, K)
        torch.mul(d_pow, A * dx + B * dy, out=out[0])
        torch.mul(d_pow, B * dx + C * dy, out=out[1])
        torch.mul(-0.5 * d_pow, dx * dx, out=out[2])
        torch.mul(-d_pow, dx * dy, out=out[3])
        torch.mul(-0.5 * d_pow, dy * dy, out=out[4])
        torch.div(d_pow, o, out=out[5])
        torch.mul(G[:F], w, out=out[6:])
        g_splat = torch.zeros(6 + F, ctx.n_splats, dtype=out.dtype, device=out.device).index_add_(1, spl, out)
        return None, None, g_splat[:2].t(), g_splat[2:5].t(), g_splat[5], g_splat[6:].t(), None, None
