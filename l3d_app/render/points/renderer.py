"""Differentiable point-cloud renderer: z-buffered disc splats, alpha-composited (pure PyTorch).

Conventions are those of :mod:`l3d_app.geometry.cameras` (OpenCV camera frame, pixel
``(row i, col j)`` centred at ``(u, v) = (j + .5, i + .5)``).

Each point projects to ``(u, v)`` with camera depth ``Z`` and becomes a disc of radius
``r`` pixels: ``r = radius`` (``radius_units='pixels'``) or ``r = f * radius / Z`` with
``f = (fx + fy) / 2`` (``radius_units='world'``; a circle, also when fx != fy). A pixel
is covered by a splat when its CENTRE is strictly inside the disc, ``d^2 < r^2``.
Per covered pixel, the ``K = max_per_pixel`` nearest splats in depth are composited
front to back (PyTorch3D's alpha compositor) with

    w_k = opacity * (1 - d_k^2 / r_k^2),   T_k = prod_{j<k} (1 - w_j)
    image = sum_k T_k w_k c_k + T_K * background,   alpha = 1 - T_K,

so colours AND positions (through ``d^2``, and ``r`` in world units) get gradients; the
choice and order of the K splats is not differentiable. Depth order is decided on the
float32 depth, ties going to the lower point index. Points with ``Z <= near`` (behind
or at the camera) or non-finite projections are culled.

Algorithm (no Python loop over points or pixels): splats are bucketed by the side of
their pixel bounding square (1, 2, 3, 4, 6, 8, 12, ... pixels); per bucket, chunks of
(splat, pixel) candidate pairs are evaluated as broadcast (n, S, S) tensors and those
inside the disc kept. The kept pairs are reduced to the K nearest per pixel by a
stable sort on an int64 ``pixel << 32 | float32 depth bits`` key (plus a sort by point
index when keys tie) whenever they exceed a bound, so memory stays bounded by ``max_candidates + K * B * H * W`` pairs. Finally the
weights of the K survivors of each pixel are recomputed with autograd and composited.
"""

from __future__ import annotations

from typing import Dict, Sequence

import torch

from l3d_app.errors import UserError
from l3d_app.geometry.cameras import Cameras
from l3d_app.geometry.pointcloud import PointCloud
from l3d_app.registry import RENDERERS

DEFAULT_COLOR = (0.5, 0.5, 0.5)  # grey for clouds without colours
RADIUS_UNITS = ("pixels", "world")


def _tile_sides(limit: int) -> list:
    """Bucket sides 1, 2, 3, 4, 6, 8, 12, 16, ... up to (and including) ``limit``."""
    sides, s = [1, 2, 3], 4
    while s < limit:
        sides += [s, s * 3 // 2]
        s *= 2
    sides = sorted({x for x in sides if x < limit} | {limit})
    return sides


def splat_geometry(cloud_points: torch.Tensor, cams: Cameras, radius: float, radius_units: str,
                   near: float):
    """Project points to splats. Returns u, v, z, r (each (B, N), pixels / world Z) and
    ``valid`` (B, N) bool (in front of the near plane, finite). Differentiable."""
    view = cams.world_to_view(cloud_points)
    z = view[..., 2]
    uv = cams.view_to_pixels(view)
    valid = (z > near) & torch.isfinite(uv).all(-1) & torch.isfinite(z)
    if radius_units == "world":
        f = 0.5 * (cams.fx + cams.fy)
        r = f[:, None] * radius / torch.where(valid, z, torch.ones_like(z))
    else:
        r = torch.full_like(z, float(radius))
    return uv[..., 0], uv[..., 1], z, r, valid


def _keep_nearest(key: torch.Tensor, sid: torch.Tensor, k: int):
    """Keep the ``k`` nearest pairs per pixel. ``key`` (M,) int64 ``pixel << 32 | depth
    bits``, ``sid`` (M,) splat ids; equal keys go to the lower splat id. Returns the kept
    (key, sid) sorted by key, and their rank within the pixel."""
    key, order = torch.sort(key, stable=True)
    sid = sid[order]
    if key.numel() > 1 and bool((key[1:] == key[:-1]).any()):  # ties (e.g. coincident points)
        order = torch.argsort(sid, stable=True)
        key, sid = key[order], sid[order]
        key, order = torch.sort(key, stable=True)
        sid = sid[order]
    pix = key >> 32
    idx = torch.arange(pix.shape[0], device=pix.device)
    first = torch.ones_like(pix, dtype=torch.bool)
    first[1:] = pix[1:] != pix[:-1]
    start = torch.cummax(torch.where(first, idx, torch.zeros_like(idx)), 0).values
    rank = idx - start
    keep = rank < k
    return key[keep], sid[keep], rank[keep]


@torch.no_grad()
def select_splats(u, v, z, r, valid, height: int, width: int, k: int,
                  max_candidates: int = 1 << 22) -> torch.Tensor:
    """(B*H*W, k) long ids ``b * N + n`` of the k nearest splats covering each pixel,
    front to back, -1 where fewer. Inputs (B, N) as from :func:`splat_geometry`."""
    B, N = u.shape
    dev = u.device
    u, v, r = u.reshape(-1), v.reshape(-1), r.reshape(-1)
    # Pixel bounding square of each disc (pixel centres j + .5 with |j + .5 - u| < r).
    x0, x1 = torch.ceil(u - r - 0.5), torch.floor(u + r - 0.5)
    y0, y1 = torch.ceil(v - r - 0.5), torch.floor(v + r - 0.5)
    x0c, x1c = x0.clamp(0, width - 1), x1.clamp(0, width - 1)
    y0c, y1c = y0.clamp(0, height - 1), y1.clamp(0, height - 1)
    ok = valid.reshape(-1) & (r > 0) & (x1 >= 0) & (x0 <= width - 1) & (y1 >= 0) & (y0 <= height - 1)
    ok &= (x1c >= x0c) & (y1c >= y0c)
    side = torch.maximum(x1c - x0c, y1c - y0c) + 1
    zbits = z.reshape(-1).float().clamp_min(0).view(torch.int32).to(torch.int64)
    sides = torch.tensor(_tile_sides(max(height, width)), device=dev)
    bucket = torch.bucketize(torch.where(ok, side, torch.zeros_like(side)).to(sides.dtype), sides)
    kept = [torch.empty(0, dtype=torch.int64, device=dev)] * 2
    pending, pending_n = [], 0

    def flush(parts):
        key = torch.cat([kept[0]] + [p[0] for p in parts])
        sd = torch.cat([kept[1]] + [p[1] for p in parts])
        return _keep_nearest(key, sd, k)

    for bi in torch.unique(bucket[ok]).tolist():
        S = int(sides[bi])
        members = torch.nonzero(ok & (bucket == bi)).squeeze(1)
        step = max(1, max_candidates // (S * S))
        off = torch.arange(S, device=dev, dtype=u.dtype)
        for c in range(0, members.shape[0], step):
            m = members[c:c + step]
            px = x0c[m, None] + off  # (n, S) pixel columns
            py = y0c[m, None] + off  # (n, S) pixel rows
            dx2 = (px + 0.5 - u[m, None]).square().masked_fill(px > x1c[m, None], float("inf"))
            dy2 = (py + 0.5 - v[m, None]).square().masked_fill(py > y1c[m, None], float("inf"))
            inside = dy2[:, :, None] + dx2[:, None, :] < r[m, None, None].square()
            row = torch.div(m, N, rounding_mode="floor")[:, None] * height + py.long()
            pix = row[:, :, None] * width + px.long()[:, None, :]  # (n, S, S) flat pixel ids
            key = (pix << 32) | zbits[m][:, None, None]
            pending.append((key[inside], m[:, None, None].expand_as(inside)[inside]))
            pending_n += pending[-1][0].shape[0]
            if pending_n > max_candidates:
                kept, pending, pending_n = list(flush(pending)[:2]), [], 0
    key, sid, rank = flush(pending)
    pix = key >> 32
    ids = torch.full((B * height * width, k), -1, dtype=torch.int64, device=dev)
    ids[pix, rank] = sid
    return ids


def composite_splats(ids, u, v, z, r, colors, background, opacity: float, height: int, width: int):
    """Alpha-composite the selected splats (see module docstring). ``ids`` (B*H*W, K) from
    :func:`select_splats`; u, v, z, r (B, N); colors (N, 3). Returns image (B, H, W, 3),
    alpha (B, H, W), depth (B, H, W) (camera Z of the nearest splat, 0 on background)."""
    B, N = u.shape
    P, K = ids.shape
    hit = ids >= 0
    safe = ids.clamp_min(0)
    pix = torch.arange(P, device=ids.device)
    pu = (pix % width).to(u.dtype)[:, None] + 0.5
    pv = (torch.div(pix, width, rounding_mode="floor") % height).to(u.dtype)[:, None] + 0.5
    d2 = (pu - u.reshape(-1)[safe]).square() + (pv - v.reshape(-1)[safe]).square()
    rk = r.reshape(-1)[safe]
    w = (opacity * (1.0 - d2 / rk.square())).clamp(0.0, 1.0)
    w = torch.where(hit, w, torch.zeros_like(w))
    one_minus = 1.0 - w
    trans = torch.cumprod(torch.cat([torch.ones_like(w[:, :1]), one_minus], dim=1), dim=1)
    col = colors[safe % N]  # (P, K, 3)
    bg = torch.as_tensor(background, dtype=u.dtype, device=u.device)
    image = ((trans[:, :K] * w)[..., None] * col).sum(1) + trans[:, K:] * bg
    depth = torch.where(hit[:, 0], z.reshape(-1)[safe[:, 0]], torch.zeros_like(d2[:, 0]))
    return {"image": image.view(B, height, width, 3),
            "alpha": (1.0 - trans[:, K]).view(B, height, width),
            "depth": depth.view(B, height, width)}


@RENDERERS.register("points")
class PointRenderer:
    """Render a :class:`PointCloud` from B cameras as alpha-composited disc splats.

    Args:
        radius: splat radius, in pixels or world units (see ``radius_units``).
        radius_units: 'pixels' (same size everywhere) or 'world' (``f * radius / Z`` px).
        background: RGB behind the splats (blended by the remaining transmittance).
        opacity: peak splat opacity in (0, 1] (at the disc centre).
        max_per_pixel: K, the number of nearest splats composited per pixel.
        near: camera-depth near plane; points with ``Z <= near`` are culled.
        max_candidates: bound on (splat, pixel) pairs held at once (memory knob).
    """

    def __init__(self, radius: float = 2.0, radius_units: str = "pixels",
                 background: Sequence[float] = (1.0, 1.0, 1.0), opacity: float = 1.0,
                 max_per_pixel: int = 8, near: float = 1e-3, max_candidates: int = 1 << 22):
        if radius_units not in RADIUS_UNITS:
            raise UserError(f"unknown radius_units '{radius_units}'; known: {', '.join(RADIUS_UNITS)}")
        if not float(radius) > 0:
            raise UserError(f"point radius must be positive, got {radius}")
        if not 0.0 < float(opacity) <= 1.0:
            raise UserError(f"opacity must be in (0, 1], got {opacity}")
        if int(max_per_pixel) < 1:
            raise UserError(f"max_per_pixel must be >= 1, got {max_per_pixel}")
        if len(background) != 3:
            raise UserError(f"background must be 3 numbers (RGB), got {background}")
        self.radius, self.radius_units = float(radius), radius_units
        self.background = tuple(float(c) for c in background)
        self.opacity, self.max_per_pixel = float(opacity), int(max_per_pixel)
        self.near, self.max_candidates = float(near), int(max_candidates)

    def __call__(self, cloud: PointCloud, cams: Cameras) -> Dict[str, torch.Tensor]:
        """Returns image (B, H, W, 3), alpha (B, H, W) in [0, 1] and depth (B, H, W)
        (camera Z of the nearest covering splat, 0 on background), in the cloud's dtype."""
        pts = cloud.points
        if cams.R.dtype != pts.dtype or cams.device != pts.device:
            cams = cams.to(device=pts.device, dtype=pts.dtype)
        colors = cloud.colors
        if colors is None:
            colors = pts.new_tensor(DEFAULT_COLOR).expand(pts.shape[0], 3)
        H, W = cams.height, cams.width
        if pts.shape[0] == 0:  # empty cloud: background only
            B = cams.batch_size
            bg = pts.new_tensor(self.background).expand(B, H, W, 3).contiguous()
            return {"image": bg, "alpha": pts.new_zeros(B, H, W), "depth": pts.new_zeros(B, H, W)}
        u, v, z, r, valid = splat_geometry(pts, cams, self.radius, self.radius_units, self.near)
        ids = select_splats(u.detach(), v.detach(), z.detach(), r.detach(), valid, H, W,
                            self.max_per_pixel, self.max_candidates)
        return composite_splats(ids, u, v, z, r, colors.to(pts.dtype), self.background,
                                self.opacity, H, W)
