"""Hard (z-buffered) triangle rasterisation in vectorised pure PyTorch.

Conventions are those of :mod:`l3d_app.geometry.cameras` (OpenCV camera frame, pixel
``(row i, col j)`` centred at ``(u, v) = (j + .5, i + .5)``); a pixel is covered by a
triangle when its CENTRE is inside it or on its boundary.

Algorithm (no Python loop over faces or pixels):

1. project vertices (:func:`project_vertices`);
2. per face: cull it when any vertex has camera depth ``Z < near`` (triangles crossing the
   near plane are DROPPED, never clipped: no NaN, no garbage, but a face that pokes
   through the near plane vanishes whole), when its screen area is (relatively) zero,
   when its pixel bounding box misses the image, and, optionally, when it faces away;
3. bucket the faces by the size of their pixel bounding box into square tiles of ~1.5x
   growing sides (1, 2, 3, 4, 6, 8, 12, ...; small buckets are merged upwards), and for
   each bucket evaluate the three edge functions at the pixel centres of all (tile, face)
   pairs as broadcast (th, tw, n) tensors: ``E = dx (py - ay) - dy (px - ax)`` is
   separable, so only the final subtraction runs over every candidate. A pixel is inside
   when ``E >= 0`` on all edges. Edge functions use a canonical vertex order
   (lexicographic in screen position), so two faces sharing an edge get bitwise opposite
   values: a pixel centre on a shared edge is never lost (no cracks); it may be claimed
   by both, and the z-test picks one;
4. z-buffer with ONE ``scatter_reduce('amax')`` per bucket over int64 keys
   ``float32_bits(+-1/Z) << 32 | (2^32 - 1 - face_id)`` where the sign is negative outside
   the triangle: positive float bits sort like the floats, so this is an exact depth test;
   equal depths go to the LOWER face id;
5. recompute barycentrics and depth for the winning face of each covered pixel. This
   last step is differentiable w.r.t. the vertex positions (the visibility is not).

Tiles are processed in chunks of at most ``max_candidates`` (face, pixel) pairs, so
memory stays bounded whatever the mesh and image size.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import Optional, Tuple

import torch

from l3d_app.errors import UserError
from l3d_app.geometry.cameras import Cameras

_LOW32 = 0xFFFFFFFF


@dataclass
class Fragments:
    """Rasteriser output for a batch of B views of H x W pixels.

    Packed attributes, one row per covered pixel (P = number of covered pixels), for
    shading only what is visible:
        fg_pixels: (P,) long, flat index ``b * H * W + i * W + j`` of each covered pixel.
        fg_faces: (P,) long index of the visible face.
        fg_bary: (P, 3) PERSPECTIVE-CORRECT barycentrics of the pixel centre w.r.t. the
            face's vertices ``faces[f, 0..2]`` (non-negative, sum to 1).
        fg_bary_screen: (P, 3) screen-space (affine) barycentrics.
        fg_zbuf: (P,) camera-frame depth Z (world units) at the pixel centre.
        fg_bary_t: (3, P) ``fg_bary`` channels-first (fast shading on the CPU).

    Dense views, built on first access (background: ``pix_to_face == -1``):
        pix_to_face (B, H, W) long, -1 on background; bary, bary_screen (B, H, W, 3), 0 on
        background; zbuf (B, H, W), **0 on background** (never inf, so masked sums stay
        finite); mask (B, H, W) bool.
    """

    fg_pixels: torch.Tensor
    fg_faces: torch.Tensor
    fg_bary: torch.Tensor
    fg_bary_screen: torch.Tensor
    fg_zbuf: torch.Tensor
    batch: int
    height: int
    width: int
    fg_bary_t: Optional[torch.Tensor] = None

    def __post_init__(self):
        if self.fg_bary_t is None:
            self.fg_bary_t = self.fg_bary.t().contiguous()

    @property
    def shape(self) -> Tuple[int, int, int]:
        """(B, H, W)."""
        return self.batch, self.height, self.width

    def densify(self, packed: torch.Tensor, fill: float = 0.0) -> torch.Tensor:
        """(P, ...) per-covered-pixel values -> (B, H, W, ...) image, ``fill`` elsewhere."""
        n = self.batch * self.height * self.width
        out = packed.new_full((n, *packed.shape[1:]), fill)
        return out.index_copy_(0, self.fg_pixels, packed).view(*self.shape, *packed.shape[1:])

    @cached_property
    def pix_to_face(self) -> torch.Tensor:
        return self.densify(self.fg_faces, -1)

    @cached_property
    def bary(self) -> torch.Tensor:
        return self.densify(self.fg_bary)

    @cached_property
    def bary_screen(self) -> torch.Tensor:
        return self.densify(self.fg_bary_screen)

    @cached_property
    def zbuf(self) -> torch.Tensor:
        return self.densify(self.fg_zbuf)

    @property
    def mask(self) -> torch.Tensor:
        """(B, H, W) bool, True where a face is visible."""
        return self.pix_to_face >= 0


def project_vertices(cams: Cameras, verts: torch.Tensor, near: float = 1e-3
                     ) -> Tuple[torch.Tensor, torch.Tensor]:
    """World vertices (V, 3) or (B, V, 3) -> pixels ``uv`` (B, V, 2) and depth ``z`` (B, V).

    Vertices with ``z < near`` are projected as if at depth ``near`` (finite values); the
    rasteriser culls every face that uses one, so those coordinates are never used.
    """
    view = cams.world_to_view(verts)
    z = view[..., 2]
    zs = z.clamp_min(near)
    u = view[..., 0] / zs * cams.fx[:, None] + cams.cx[:, None]
    v = view[..., 1] / zs * cams.fy[:, None] + cams.cy[:, None]
    return torch.stack([u, v], dim=-1), z


# Square tile sizes (pixels per side) for bucketing faces by bounding-box size: ~1.5x steps
# keep the padding small while the number of buckets (Python iterations) stays ~10.
_TILES = (1, 2, 3, 4, 6, 8, 12, 16, 24, 32, 48, 64, 96, 128, 192, 256, 384, 512, 768, 1024,
          1536, 2048, 3072, 4096, 6144, 8192, 12288, 16384)

_MERGE_PIXELS = 1 << 16


def _face_table(uv: torch.Tensor, z: torch.Tensor, faces: torch.Tensor):
    """Per-face quantities in structure-of-arrays layout (one contiguous row per quantity).

    Returns:
        table: (15, B*F); rows ``4k .. 4k+3`` = ``(ax, ay, dx, dy)`` of edge k (the edge
            opposite vertex k) and rows ``12 + k`` = ``1 / z_k``. The edge function
            ``E_k(p) = dx * (py - ay) - dy * (px - ax)`` is >= 0 inside the triangle; its
            start ``a`` is the lexicographically smaller end (u, then v) and ``d`` the
            direction times +-1, so faces sharing an edge get bitwise opposite values.
        corners: (3 comps u/v/z, 3 verts, B*F) projected face corners.
        area2: (B*F,) signed doubled screen area (> 0: the face points away from the camera).
    """
    B, V = z.shape
    F = faces.shape[0]
    table_v = torch.cat([uv.permute(2, 0, 1), z[None]], 0).reshape(3, B * V)
    gidx = faces.t()[:, None, :] + (torch.arange(B, device=uv.device) * V)[None, :, None]
    corners = table_v.index_select(1, gidx.reshape(-1)).view(3, 3, B * F)
    u, v = corners[0], corners[1]
    area2 = (u[1] - u[0]) * (v[2] - v[0]) - (v[1] - v[0]) * (u[2] - u[0])
    a, b = corners[:2].roll(-1, dims=1), corners[:2].roll(-2, dims=1)  # edge k: v[k+1] -> v[k+2]
    swap = (a[0] > b[0]) | ((a[0] == b[0]) & (a[1] > b[1]))           # (3, BF)
    start = torch.where(swap, b, a)
    flip = swap ^ (area2 < 0)
    d = (torch.where(swap, a, b) - start) * (1.0 - 2.0 * flip.to(uv.dtype))
    edges = torch.stack([start[0], start[1], d[0], d[1]], dim=1).reshape(12, B * F)
    table = torch.cat([edges, 1.0 / corners[2].clamp_min(1e-30)], 0)
    return table, corners, area2


def _merge_buckets(counts, height: int, width: int):
    """Merge each face bucket into the next non-empty (larger-tile) one when that adds fewer
    than ``_MERGE_PIXELS`` padded candidates: a bucket costs ~40 tensor ops of fixed
    overhead, worth about that many candidates. Returns (class remap list, new counts)."""
    area = [min(t, height) * min(t, width) for t in _TILES]
    remap, counts = list(range(len(counts))), list(counts)
    nonempty = [c for c, n in enumerate(counts) if n]
    for c, nxt in zip(nonempty[:-1], nonempty[1:]):
        if counts[c] * (area[nxt] - area[c]) < _MERGE_PIXELS:
            counts[nxt] += counts[c]
            counts[c] = 0
            remap = [nxt if r == c else r for r in remap]
    return remap, counts


def _tile_keys(t: torch.Tensor, x0: torch.Tensor, y0: torch.Tensor, fid: torch.Tensor,
               th: int, tw: int, width: int, pixbase: torch.Tensor):
    """Z-buffer keys and flat pixel indices, both (th, tw, n), of n faces' pixel tiles.

    t: (15, n) face table columns; x0, y0: (n,) float tile origins + 0.5 (pixel centres);
    fid: (n,) int64 low key bits (encoded face ids); pixbase: (n,) flat index of each
    tile's first pixel. Key = float32 bits of ``+-1/Z`` (negative outside) << 32 | fid.
    """
    dev, dt = t.device, t.dtype
    py = torch.arange(th, device=dev, dtype=dt)[:, None, None] + y0   # (th, 1, n), exact
    px = torch.arange(tw, device=dev, dtype=dt)[:, None] + x0         # (tw, n), exact
    E = [(py - t[4 * k + 1]).mul_(t[4 * k + 2]) - (px - t[4 * k]).mul_(t[4 * k + 3])
         for k in range(3)]                                            # separable: (th, tw, n)
    s = E[0] + E[1]
    s += E[2]
    w = E[0] * t[12]
    w.addcmul_(E[1], t[13]).addcmul_(E[2], t[14]).div_(s)             # 1 / Z (perspective)
    m = torch.minimum(E[0], E[1])
    torch.minimum(m, E[2], out=m)
    w.copysign_(m.add_(0.0)).nan_to_num_(nan=-1.0)                    # -0.0 counts as inside
    key = w.to(torch.float32).view(torch.int32).to(torch.int64)
    key.bitwise_left_shift_(32).bitwise_or_(fid)
    rows = torch.arange(0, th * width, width, device=dev)[:, None, None] + pixbase
    pix = rows + torch.arange(tw, device=dev)[:, None]
    return key, pix


def _zbuffer(table, corners, area2, B, F, height, width, near, cull_backfaces, max_candidates):
    """(B*H*W,) int64 z-buffer keys: < 0 on background, else ``bits(1/Z) << 32 |
    (2^32 - 1 - face id)`` of the nearest face (see :func:`_tile_keys`)."""
    dev, dt = table.device, table.dtype
    keys = torch.full((B * height * width,), -1, dtype=torch.int64, device=dev)
    uvc = corners[:2]
    lo = torch.minimum(torch.minimum(uvc[:, 0], uvc[:, 1]), uvc[:, 2])   # (2, BF)
    hi = torch.maximum(torch.maximum(uvc[:, 0], uvc[:, 1]), uvc[:, 2])
    ext = (hi - lo).amax(0)
    zc = corners[2]
    # in front of the near plane; non-degenerate (also False for NaN/inf corners)
    ok = (torch.minimum(torch.minimum(zc[0], zc[1]), zc[2]) >= near) \
        & (area2.abs() > 1e-6 * ext * ext)
    if cull_backfaces:
        ok &= area2 < 0
    big = float(max(width, height) + 1)
    jmin = torch.ceil(lo - 0.5).clamp_(-1.0, big)       # first / last pixel centre inside
    jmax = torch.floor(hi - 0.5).clamp_(-1.0, big)
    dims = torch.tensor([[width], [height]], device=dev, dtype=dt)
    jmin.clamp_min_(0.0)
    jmax = torch.minimum(jmax, dims - 1)
    size = jmax - jmin + 1                               # (2, BF) bbox size in pixels
    ok &= (size > 0).all(0)
    idx = ok.nonzero().squeeze(1)
    if idx.numel() == 0:
        return keys
    tiles = torch.tensor(_TILES, device=dev, dtype=dt)
    cls = torch.searchsorted(tiles, size[:, idx].amax(0))  # square tile class per face
    remap, counts = _merge_buckets(torch.bincount(cls, minlength=len(_TILES)).tolist(),
                                   height, width)
    cls, order = torch.sort(torch.tensor(remap, device=dev).index_select(0, cls))
    idx = idx.index_select(0, order)
    t = table.index_select(1, idx)
    side = tiles[cls]
    tsize = torch.minimum(side, dims)                    # (2, M) tile size within the image
    origin = torch.minimum(jmin[:, idx], dims - tsize)   # tile inside the image, covers bbox
    o_int = origin.to(torch.int64)
    b_idx = torch.div(idx, F, rounding_mode="floor")
    fid = _LOW32 - (idx - b_idx * F)                     # amax: ties to the lower face id
    pixbase = b_idx * (height * width) + o_int[1] * width + o_int[0]
    origin += 0.5
    start = 0
    for c, n in enumerate(counts):
        if n == 0:
            continue
        th, tw = min(_TILES[c], height), min(_TILES[c], width)
        step = max(1, max_candidates // (th * tw))
        for s in range(start, start + n, step):
            e = min(s + step, start + n)
            key, pix = _tile_keys(t[:, s:e], origin[0, s:e], origin[1, s:e], fid[s:e],
                                  th, tw, width, pixbase[s:e])
            keys.scatter_reduce_(0, pix.reshape(-1), key.reshape(-1), reduce="amax")
        start += n
    return keys


def rasterize_projected(uv: torch.Tensor, z: torch.Tensor, faces: torch.Tensor, height: int,
                        width: int, near: float = 1e-3, cull_backfaces: bool = False,
                        max_candidates: int = 1 << 21) -> Fragments:
    """Rasterise projected vertices: ``uv`` (B, V, 2) pixels, ``z`` (B, V) camera depth.

    ``faces`` (F, 3) long. See :func:`rasterize` for the meaning of the options.
    """
    B, F, HW = uv.shape[0], faces.shape[0], height * width
    dt = uv.dtype
    if max(height, width) > _TILES[-1]:
        raise UserError(f"image side {max(height, width)} exceeds {_TILES[-1]} pixels")
    faces = faces.to(device=uv.device, dtype=torch.long)
    table, corners, area2 = _face_table(uv, z, faces)
    with torch.no_grad():
        keys = _zbuffer(table.detach(), corners.detach(), area2.detach(), B, F, height, width,
                        near, cull_backfaces, max_candidates)
    # ---- pass 2: differentiable barycentrics for the winning face of each covered pixel
    fg = (keys >= 0).nonzero().squeeze(1)
    fg_faces = _LOW32 - (keys.index_select(0, fg) & _LOW32)
    b_idx = torch.div(fg, HW, rounding_mode="floor")
    rem = fg - b_idx * HW
    row = torch.div(rem, width, rounding_mode="floor")
    px = (rem - row * width).to(dt) + 0.5
    py = row.to(dt) + 0.5
    t = table.index_select(1, b_idx * F + fg_faces)                  # (15, P)
    E = [(py - t[4 * k + 1]) * t[4 * k + 2] - (px - t[4 * k]) * t[4 * k + 3] for k in range(3)]
    wE = [E[k] * t[12 + k] for k in range(3)]
    sum_e, w = E[0] + E[1] + E[2], wE[0] + wE[1] + wE[2]
    bary_t = torch.stack([x / w for x in wE])
    return Fragments(fg, fg_faces, bary_t.t(), torch.stack([x / sum_e for x in E], 1),
                     sum_e / w, B, height, width, bary_t)


def rasterize(cams: Cameras, verts: torch.Tensor, faces: torch.Tensor, near: float = 1e-3,
              cull_backfaces: bool = False, max_candidates: int = 1 << 21) -> Fragments:
    """Hard-rasterise a triangle mesh seen by B cameras.

    Args:
        cams: B cameras (they give the image size H x W).
        verts: (V, 3) or (B, V, 3) world-space vertex positions.
        faces: (F, 3) long vertex indices.
        near: faces with ANY vertex at camera depth ``Z < near`` (world units) are culled
            whole (no clipping). This also removes everything behind the camera.
        cull_backfaces: drop faces whose front side (counter-clockwise vertices seen from
            outside) points away from the camera. Off by default.
        max_candidates: upper bound on (face, pixel) candidate pairs processed at once
            (memory ~ 60 bytes per pair).

    Returns:
        :class:`Fragments` (pix_to_face, perspective-correct bary, bary_screen, zbuf with 0
        on background, plus packed per-covered-pixel copies). Gradients flow from ``bary``,
        ``bary_screen`` and ``zbuf`` to ``verts``; which face is visible is piecewise constant.
    """
    uv, z = project_vertices(cams, verts, near)
    return rasterize_projected(uv, z, faces, cams.height, cams.width, near=near,
                               cull_backfaces=cull_backfaces, max_candidates=max_candidates)
