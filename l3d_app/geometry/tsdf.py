"""Truncated signed distance fusion of depth maps into a sparse voxel band, and its mesh.

:func:`fuse_depth_maps` follows KinectFusion / Open3D's ``ScalableTSDFVolume``: voxels of side
``voxel`` (world units) on a grid over the depth maps' points (clipped to a box), of which only
the BAND near an observed surface is kept (blocks of ``block``^3 voxels holding a depth point,
grown by the truncation distance). Each view updates every band voxel it sees in front of the
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


def _band(points: torch.Tensor, lo: torch.Tensor, voxel: float, dims, trunc: float, block: int) -> torch.Tensor:
    """Sorted flat indices of the voxels of every block within ``trunc`` of a point (M,)."""
    dev = points.device
    bd = [-(-d // block) for d in dims]
    ijk = ((points - lo) / voxel).round().long()
    b = torch.div(ijk, block, rounding_mode="floor")
    occ = torch.zeros(bd, dtype=torch.float32, device=dev)
    occ[b[:, 0].clamp(0, bd[0] - 1), b[:, 1].clamp(0, bd[1] - 1), b[:, 2].clamp(0, bd[2] - 1)] = 1.0
    reach = int(math.ceil(trunc / (block * voxel)))          # blocks a voxel within trunc of a point can be away
    occ = torch.nn.functional.max_pool3d(occ[None, None], 2 * reach + 1, stride=1, padding=reach)[0, 0] > 0
    blocks = torch.nonzero(occ)                                                        # (Nb, 3)
    r = torch.arange(block, device=dev)
    local = torch.stack(torch.meshgrid(r, r, r, indexing="ij"), -1).reshape(-1, 3)
    vox = (blocks[:, None, :] * block + local[None]).reshape(-1, 3)
    inside = (vox < torch.tensor(dims, device=dev)).all(-1)
    vox = vox[inside]
    return torch.sort((vox[:, 0] * dims[1] + vox[:, 1]) * dims[2] + vox[:, 2]).values


@torch.no_grad()
def fuse_depth_maps(depth: torch.Tensor, cams: Cameras, voxel: float, trunc: float,
                    colors: Optional[torch.Tensor] = None, valid: Optional[torch.Tensor] = None,
                    box: Optional[Sequence[Sequence[float]]] = None, carve: bool = True, block: int = 8,
                    max_voxels: int = 60_000_000) -> TSDFVolume:
    """Fuse V depth maps into a :class:`TSDFVolume` (see the module docstring).

    Args:
        depth: (V, H, W) camera z (world units); cams: V cameras of that size.
        voxel: voxel side; trunc: truncation distance (world units, > voxel).
        colors: (V, H, W, 3) in [0, 1] to fuse (default grey).
        valid: (V, H, W) bool, pixels with a surface (default: finite depth > 0); the others
            are empty (free space with ``carve``, ignored without).
        box: ((3,), (3,)) world box the grid may not leave (default: the points' bounds).
        block: band block side (voxels); max_voxels: bound on the grid (a UserError beyond it).
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
    index = _band(points, lo, voxel, dims, trunc, block)
    vol = TSDFVolume(lo, float(voxel), dims, float(trunc), index, torch.zeros(index.shape[0], dtype=dt, device=dev),
                     torch.zeros(index.shape[0], dtype=dt, device=dev),
                     torch.zeros(index.shape[0], 3, dtype=dt, device=dev),
                     torch.zeros(index.shape[0], dtype=dt, device=dev))
    centres = vol.centres()
    rgb = None if colors is None else colors.to(device=dev, dtype=dt).reshape(V, H * W, 3)
    for v in range(V):
        _integrate(vol, centres, cams[v], depth[v].reshape(-1), valid[v].reshape(-1),
                   None if rgb is None else rgb[v], carve)
    return vol


def _sample_depth(pix: torch.Tensor, depth: torch.Tensor, valid: torch.Tensor, width: int, height: int,
                  jump: float):
    """Depth at pixel positions (M, 2): bilinear in INVERSE depth (exact on a plane) where the four
    pixel centres around the position all hold a surface within ``jump`` of each other, else the
    pixel the position falls in. Returns depth (M,), the nearest pixel's index (M,), in-image (M,)
    and empty (M,): all four pixels around the position (and the one it falls in) hold no surface."""
    col, row = pix[:, 0].floor().long(), pix[:, 1].floor().long()
    inside = (col >= 0) & (col < width) & (row >= 0) & (row < height)
    at = torch.where(inside, row * width + col, torch.zeros_like(col))
    d = depth.index_select(0, at)
    g = pix - 0.5
    base = g.floor()
    fx, fy = (g - base).unbind(1)
    c0 = base[:, 0].long().clamp(0, width - 2)
    r0 = base[:, 1].long().clamp(0, height - 2)
    corners = [(r0 + dr) * width + c0 + dc for dr in (0, 1) for dc in (0, 1)]
    ds = torch.stack([depth.index_select(0, c) for c in corners])                   # (4, M)
    vs = torch.stack([valid.index_select(0, c) for c in corners])
    empty = ~vs.any(0) & ~valid.index_select(0, at)
    ok = vs.all(0)
    ok &= (ds.amax(0) - ds.amin(0) < jump) & (base[:, 0] >= 0) & (base[:, 1] >= 0) & \
        (base[:, 0] <= width - 2) & (base[:, 1] <= height - 2)
    wts = torch.stack([(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy])
    inv = (wts / torch.where(ok[None], ds, torch.ones_like(ds))).sum(0)
    return torch.where(ok, 1.0 / inv, d), at, inside, empty


def _integrate(vol: TSDFVolume, centres: torch.Tensor, cam: Cameras, depth: torch.Tensor, valid: torch.Tensor,
               rgb: Optional[torch.Tensor], carve: bool) -> None:
    """One view's update of every band voxel (in place)."""
    pix, z = cam.project(centres)
    pix, z = pix[0], z[0]
    d, at, inside, empty = _sample_depth(pix, depth, valid, cam.width, cam.height, vol.trunc)
    seen = (z > 0) & inside
    surface = valid.index_select(0, at) & seen
    sdf = d - z
    obs = torch.where(surface, (sdf / vol.trunc).clamp(max=1.0), torch.ones_like(sdf))
    update = torch.where(surface, sdf > -vol.trunc, seen & empty & carve)
    w = update.to(vol.weight.dtype)
    vol.tsdf = torch.where(update, (vol.tsdf * vol.weight + obs) / (vol.weight + w).clamp_min(1), vol.tsdf)
    vol.weight = vol.weight + w
    near = (surface & (sdf.abs() < COLOR_BAND * vol.voxel)).to(vol.weight.dtype)
    if rgb is not None:
        c = rgb.index_select(0, at)
        vol.color = (vol.color * vol.color_weight[:, None] + c * near[:, None]) / \
            (vol.color_weight + near).clamp_min(1)[:, None]
    else:
        vol.color = torch.where(near[:, None] > 0, torch.full_like(vol.color, 0.5), vol.color)
    vol.color_weight = vol.color_weight + near


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
