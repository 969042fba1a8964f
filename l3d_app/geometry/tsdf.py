"""Truncated signed distance fusion of depth maps into a sparse voxel band, and its mesh.

:func:`fuse_depth_maps` follows KinectFusion / Open3D's ``ScalableTSDFVolume``: voxels of side
``voxel`` (world units) on a grid over the depth maps' points (clipped to a box), of which only
the BAND near an observed surface is kept (the voxels within the truncation distance, per axis,
of a voxel holding a depth point). Each view updates every band voxel it sees in front of the
camera with the signed distance along the optical axis ``sdf = depth(p) - z(voxel)`` (``p`` the
voxel centre's projection; the depth there interpolated bilinearly in inverse depth, which is exact
on a plane, where the four pixels around ``p`` hold one surface, else the pixel's), truncated: ``min(1, sdf / trunc)``, skipped where
``sdf < -trunc`` (hidden behind the surface); a running average with weight 1 per view. Colour
is averaged where ``|sdf| < COLOR_BAND`` voxels. Pixels marked empty (``valid`` False, e.g. transparent in a
render) vote ``+1`` (free space) with ``carve=True`` for the voxels that fall among four empty
pixels (not on a silhouette's edge pixel): a surface that only some views show is thinned by
the views that look through it.

:func:`tsdf_mesh` runs marching cubes (:func:`~l3d_app.geometry.marching_cubes.grid_to_mesh`) at
level 0 on the cubes whose eight corners were all measured (the surface ends where the
measurements do, never at the band's edge) and colours the vertices trilinearly from the fused
colours. Everything is vectorised over voxels; the loop is over views.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional, Sequence, Tuple

import torch

from l3d_app.errors import UserError
from l3d_app.geometry.cameras import Cameras
from l3d_app.geometry.depth_normals import depth_to_points
from l3d_app.geometry.marching_cubes import grid_to_mesh
from l3d_app.geometry.mesh import Mesh


COLOR_BAND = 1.5    # voxels: colour is fused where |sdf| is below this (farther, a pixel shows surface beside the voxel)


@dataclass
class TSDFVolume:
    """A fused band of voxels. ``lo`` (3,) world position of voxel ``(0, 0, 0)``'s centre,
    ``voxel`` side (world units), ``dims`` (3,) grid size, ``trunc`` truncation distance (world
    units); per band voxel (M,): ``index`` flat grid index ``(i * Y + j) * Z + k`` (sorted),
    ``tsdf`` in [-1, 1], ``weight`` (number of views that measured it), ``color`` (M, 3) and
    ``color_weight`` (M,)."""

    lo: torch.Tensor
    voxel: float
    dims: Tuple[int, int, int]
    trunc: float
    index: torch.Tensor
    tsdf: torch.Tensor
    weight: torch.Tensor
    color: torch.Tensor
    color_weight: torch.Tensor

    def centres(self) -> torch.Tensor:
        """(M, 3) world centres of the band voxels."""
        return self.lo + _unflatten(self.index, self.dims).to(self.lo.dtype) * self.voxel


def _unflatten(index: torch.Tensor, dims) -> torch.Tensor:
    X, Y, Z = dims
    return torch.stack([index // (Y * Z), (index // Z) % Y, index % Z], -1)


def _band(points: torch.Tensor, lo: torch.Tensor, voxel: float, dims, trunc: float) -> torch.Tensor:
    """Sorted flat indices (M,) of the voxels within ``trunc`` (per axis) of a point's voxel: the
    points' voxels dilated by a box, separably (a running count along each axis)."""
    ijk = ((points - lo) / voxel).round().long()
    for a in range(3):
        ijk[:, a].clamp_(0, dims[a] - 1)
    occ = torch.zeros(dims, dtype=torch.int32, device=points.device)
    occ[ijk[:, 0], ijk[:, 1], ijk[:, 2]] = 1
    r = int(math.ceil(trunc / voxel))
    for a in range(3):
        c = torch.cumsum(occ, a, dtype=torch.int32)
        n = dims[a]
        hi = c.narrow(a, min(r, n - 1), n - min(r, n - 1))            # count up to i + r (clamped at the end)
        hi = torch.cat([hi, c.narrow(a, n - 1, 1).expand_as(c.narrow(a, 0, min(r, n - 1)))], a)
        lo_ = torch.cat([torch.zeros_like(c.narrow(a, 0, min(r + 1, n))), c.narrow(a, 0, n - min(r + 1, n))], a)
        occ = (hi - lo_ > 0).to(torch.int32)
    return torch.nonzero(occ.reshape(-1)).reshape(-1)


@torch.no_grad()
def fuse_depth_maps(depth: torch.Tensor, cams: Cameras, voxel: float, trunc: float,
                    colors: Optional[torch.Tensor] = None, valid: Optional[torch.Tensor] = None,
                    box: Optional[Sequence[Sequence[float]]] = None, carve: bool = True,
                    max_voxels: int = 40_000_000) -> TSDFVolume:
    """Fuse V depth maps into a :class:`TSDFVolume` (see the module docstring).

    Args:
        depth: (V, H, W) camera z (world units); cams: V cameras of that size.
        voxel: voxel side; trunc: truncation distance (world units, > voxel).
        colors: (V, H, W, 3) in [0, 1] to fuse (default grey).
        valid: (V, H, W) bool, pixels with a surface (default: finite depth > 0); the others
            are empty (free space with ``carve``, ignored without).
        box: ((3,), (3,)) world box the grid may not leave (default: the points' bounds).
        max_voxels: bound on the grid (a UserError beyond it).
    """
    if not (voxel > 0 and trunc > voxel):
        raise UserError(f"TSDF fusion needs voxel > 0 and trunc > voxel, got voxel={voxel}, trunc={trunc}")
    V, H, W = depth.shape
    dev, dt = depth.device, depth.dtype
    cams = cams.to(device=dev, dtype=dt)
    ok = torch.isfinite(depth) & (depth > 0)
    valid = ok if valid is None else (valid.to(dev).bool() & ok)
    points = depth_to_points(torch.where(valid, depth, torch.zeros_like(depth)), cams)[valid]
    if points.shape[0] == 0:
        raise UserError("TSDF fusion: no depth map holds a valid pixel")
    pad = trunc + voxel
    lo, hi = points.min(0).values - pad, points.max(0).values + pad
    if box is not None:
        b = torch.as_tensor(box, dtype=dt, device=dev)
        lo, hi = torch.maximum(lo, b[0]), torch.minimum(hi, b[1])
        keep = ((points >= lo) & (points <= hi)).all(-1)
        points = points[keep]
        if points.shape[0] == 0 or not bool((hi > lo).all()):
            raise UserError("TSDF fusion: no depth point lies inside the box")
    dims = tuple(int(x) for x in (torch.ceil((hi - lo) / voxel) + 1).tolist())
    if math.prod(dims) > max_voxels:
        raise UserError(f"TSDF grid of {dims} voxels (voxel {voxel:g}) exceeds {max_voxels}: use a larger voxel")
    index = _band(points, lo, voxel, dims, trunc)
    vol = TSDFVolume(lo, float(voxel), dims, float(trunc), index, torch.zeros(index.shape[0], dtype=dt, device=dev),
                     torch.zeros(index.shape[0], dtype=dt, device=dev),
                     torch.zeros(index.shape[0], 3, dtype=dt, device=dev),
                     torch.zeros(index.shape[0], dtype=dt, device=dev))
    centres = vol.centres().t().contiguous()
    rgb = None if colors is None else colors.to(device=dev, dtype=dt)
    for v in range(V):
        _integrate(vol, centres, cams[v], depth[v], valid[v], None if rgb is None else rgb[v], carve)
    return vol


def _neighbourhoods(depth: torch.Tensor, valid: torch.Tensor, jump: float) -> Tuple[torch.Tensor, torch.Tensor]:
    """Per 2x2 block of pixel centres of one view (the image padded by one empty pixel on each
    side, so a block is indexed by its top-left pixel ``(row + 1) * (W + 1) + col + 1``...): its four
    depths and inverse depths (0 where empty) as a ((H+1)(W+1), 8) table, and its kind (uint8): 1 the
    four hold one surface (within ``jump``: interpolate), 2 all empty, 0 otherwise."""
    H, W = depth.shape
    d = torch.nn.functional.pad(torch.where(valid, depth, torch.zeros_like(depth)), (1, 1, 1, 1))
    corners = [d[:-1, :-1], d[:-1, 1:], d[1:, :-1], d[1:, 1:]]
    ds = torch.stack(corners, -1).reshape(-1, 4)                                   # ((H+1)(W+1), 4)
    has = ds > 0
    inv = torch.where(has, 1.0 / torch.where(has, ds, torch.ones_like(ds)), torch.zeros_like(ds))
    one = has.all(-1) & (ds.amax(-1) - ds.amin(-1) < jump)
    kind = torch.where(one, 1, torch.where(~has.any(-1), 2, 0)).to(torch.uint8)
    return torch.cat([ds, inv], -1).contiguous(), kind


def _integrate(vol: TSDFVolume, centres: torch.Tensor, cam: Cameras, depth: torch.Tensor, valid: torch.Tensor,
               rgb: Optional[torch.Tensor], carve: bool) -> None:
    """One view's update of every band voxel (in place): depth (H, W), valid (H, W), rgb (H, W, 3).

    The depth at a voxel's projection ``(u, v)``: bilinear in inverse depth among the four pixel
    centres around it when they hold one surface (within the truncation of each other), else the
    depth of the pixel it falls in (the nearest centre); free space where all four are empty."""
    H, W = depth.shape
    table, kind = _neighbourhoods(depth, valid, vol.trunc)
    KR = (cam.K()[0] @ cam.R[0]).tolist()
    Kt = (cam.K()[0] @ cam.t[0]).tolist()
    X, Y, Z = centres                                          # (3, M) rows: one contiguous pass per term
    hx, hy, z = (X.mul(KR[i][0]).add_(Y, alpha=KR[i][1]).add_(Z, alpha=KR[i][2]).add_(Kt[i]) for i in range(3))
    front = z > 0
    inv_z = torch.where(front, z, torch.ones_like(z)).reciprocal_()
    gx = hx.mul_(inv_z).add_(0.5)                  # padded pixel-centre coordinates: centre (c+1) at c + 1.5
    gy = hy.mul_(inv_z).add_(0.5)
    seen = front & (gx >= 0.5) & (gx < W + 0.5) & (gy >= 0.5) & (gy < H + 0.5)
    c0, r0 = gx.floor(), gy.floor()
    fx, fy = gx - c0, gy - r0
    at = r0.mul_(W + 1).add_(c0).mul_(seen).long()
    row = table.index_select(0, at)                                                  # (M, 8)
    k = kind.index_select(0, at)
    bil = torch.lerp(torch.lerp(row[:, 4], row[:, 5], fx), torch.lerp(row[:, 6], row[:, 7], fx), fy)
    near = row.gather(1, ((fy >= 0.5).long() * 2 + (fx >= 0.5).long())[:, None])[:, 0]
    d = torch.where(k == 1, 1.0 / torch.where(k == 1, bil, torch.ones_like(bil)), near)
    surface = seen & (d > 0)
    sdf = d - z
    obs = (sdf / vol.trunc).clamp(max=1.0)
    update = torch.where(surface, sdf > -vol.trunc, seen & (k == 2) & carve)
    obs = torch.where(surface, obs, torch.ones_like(obs))
    w = update.to(vol.weight.dtype)
    vol.tsdf = torch.where(update, (vol.tsdf * vol.weight + obs) / (vol.weight + w).clamp_min(1), vol.tsdf)
    vol.weight += w
    idx = torch.nonzero(surface & (sdf.abs() < COLOR_BAND * vol.voxel)).reshape(-1)
    if idx.numel() == 0:
        return
    if rgb is None:
        c = torch.full((idx.numel(), 3), 0.5, dtype=vol.color.dtype, device=idx.device)
    else:                                                     # the pixel the voxel falls in
        pix = (gy.index_select(0, idx) - 0.5).long().clamp(0, H - 1) * W + \
            (gx.index_select(0, idx) - 0.5).long().clamp(0, W - 1)
        c = rgb.reshape(-1, 3).index_select(0, pix)
    cw = vol.color_weight.index_select(0, idx)
    vol.color.index_copy_(0, idx, (vol.color.index_select(0, idx) * cw[:, None] + c) / (cw + 1)[:, None])
    vol.color_weight.index_add_(0, idx, torch.ones_like(cw))


@torch.no_grad()
def tsdf_mesh(vol: TSDFVolume, min_weight: float = 1.0) -> Mesh:
    """Marching cubes of ``vol``'s zero level on the cubes whose 8 corners have weight >=
    ``min_weight``, vertices coloured by trilinear interpolation of the fused colours (over the
    corners that hold a colour). UserError when the fused band holds no surface."""
    X, Y, Z = vol.dims
    dev = vol.tsdf.device
    grid = torch.ones(X * Y * Z, dtype=torch.float32, device=dev)
    seen = torch.zeros(X * Y * Z, dtype=torch.bool, device=dev)
    measured = vol.weight >= min_weight
    grid[vol.index] = torch.where(measured, vol.tsdf, torch.ones_like(vol.tsdf)).float()
    seen[vol.index] = measured
    seen = seen.reshape(X, Y, Z)
    # a cube is meshed where all eight of its corners were measured
    mask = -torch.nn.functional.max_pool3d(-seen.float()[None, None], 2, stride=1)[0, 0] > 0.5
    mesh = grid_to_mesh(grid.reshape(X, Y, Z), vol.lo.tolist(), [vol.voxel] * 3, 0.0, mask=mask, device=dev,
                        what="in the fused TSDF")
    return Mesh(verts=mesh.verts, faces=mesh.faces, vert_colors=_vertex_colors(vol, mesh.verts))


def _vertex_colors(vol: TSDFVolume, verts: torch.Tensor) -> torch.Tensor:
    """(V, 3) trilinear interpolation of the fused colours at ``verts`` over the corners holding one."""
    g = (verts.to(vol.lo.dtype) - vol.lo) / vol.voxel
    base = g.floor().long()
    frac = g - base
    dims = torch.tensor(vol.dims, device=verts.device)
    out = torch.zeros(verts.shape[0], 3, dtype=vol.color.dtype, device=verts.device)
    total = torch.zeros(verts.shape[0], dtype=vol.color.dtype, device=verts.device)
    for corner in range(8):
        off = torch.tensor([(corner >> 2) & 1, (corner >> 1) & 1, corner & 1], device=verts.device)
        ijk = (base + off).clamp(torch.zeros_like(dims), dims - 1)
        flat = (ijk[:, 0] * vol.dims[1] + ijk[:, 1]) * vol.dims[2] + ijk[:, 2]
        pos = torch.searchsorted(vol.index, flat).clamp_max(vol.index.shape[0] - 1)
        has = (vol.index[pos] == flat) & (vol.color_weight[pos] > 0)
        wt = torch.where(off.bool(), frac, 1 - frac).prod(-1) * has
        out += wt[:, None] * vol.color[pos]
        total += wt
    return torch.where(total[:, None] > 0, out / total.clamp_min(1e-12)[:, None],
                       torch.full_like(out, 0.5)).clamp(0, 1).float()
