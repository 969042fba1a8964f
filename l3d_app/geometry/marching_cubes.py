"""Level sets of an SDF as triangle meshes: a grid evaluated in chunks + marching cubes.

``sdf_to_mesh(sdf, resolution)`` samples ``sdf`` on a ``resolution^3`` grid of points spanning
``bounds`` (world units), runs :func:`skimage.measure.marching_cubes` (Lewiner) at ``level`` and
returns a :class:`~l3d_app.geometry.mesh.Mesh` in world coordinates whose faces are
counter-clockwise seen from outside (right-hand normals point to increasing SDF, i.e. out of
the solid ``sdf < level``), as every Mesh in this library.
"""

from __future__ import annotations

from typing import Callable, Optional, Sequence, Tuple

import numpy as np
import torch

from l3d_app.errors import UserError
from l3d_app.geometry.mesh import Mesh


def grid_points(lo: Sequence[float], hi: Sequence[float], resolution: int,
                device=None, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """(R, R, R, 3) grid of world points, ``[i, j, k] = lo + (i, j, k) * (hi - lo) / (R - 1)``."""
    axes = [torch.linspace(float(a), float(b), resolution, device=device, dtype=dtype) for a, b in zip(lo, hi)]
    return torch.stack(torch.meshgrid(*axes, indexing="ij"), dim=-1)


# Peak host memory of sdf_to_mesh per grid point: the float32 values, their float64 copy and
# skimage's work; 17.2 / 16.6 bytes measured at 256^3 / 384^3 (a sphere, ru_maxrss).
GRID_BYTES_PER_POINT = 17


def require_grid_memory(resolution: int, available: Optional[int], what: str = "mesh_resolution") -> None:
    """UserError when a ``resolution``^3 marching-cubes grid needs more than ``available`` bytes of
    host memory (:data:`GRID_BYTES_PER_POINT` per point); nothing is checked when ``available`` is None."""
    need = GRID_BYTES_PER_POINT * int(resolution) ** 3
    if available is not None and need > available:
        raise UserError(f"{what}={int(resolution)} needs about {need / 2**30:.1f} GiB of memory for marching cubes "
                        f"({GRID_BYTES_PER_POINT} bytes per grid point); {available / 2**30:.1f} GiB are available: "
                        f"lower {what}")


# Points per SDF call on CPU: an MLP's activations for this many points stay in cache. Measured
# on 2 AVX2 cores: volsdf's grid SDF at 128^3 2.8-4.0 s in 2^14-point calls against
# 8.3-10.7 s in 2^18; neural_sdf's 128-wide MLP at 96^3 2.3-2.6 against 3.9-4.0 s.
CPU_CHUNK = 1 << 14
# On an accelerator larger calls amortise the launches.
ACCELERATOR_CHUNK = 1 << 18


@torch.no_grad()
def evaluate_grid(sdf: Callable[[torch.Tensor], torch.Tensor], lo: Sequence[float], hi: Sequence[float],
                  resolution: int, chunk_size: Optional[int] = None, device=None,
                  dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """(R, R, R) SDF values on :func:`grid_points`. The points are built slab by slab
    (``[i0:i1, :, :]``, by broadcasting) and ``sdf`` is called on (n, 3) rows of at most
    ``chunk_size`` points (default :data:`CPU_CHUNK` on CPU, :data:`ACCELERATOR_CHUNK` else), so
    peak memory is O(max(chunk_size, R^2)) points besides the (R, R, R) result.
    """
    R = int(resolution)
    axes = [torch.linspace(float(a), float(b), R, device=device, dtype=dtype) for a, b in zip(lo, hi)]
    out = torch.empty((R, R, R), device=device, dtype=dtype)
    if chunk_size is None:
        chunk_size = CPU_CHUNK if out.device.type == "cpu" else ACCELERATOR_CHUNK
    chunk = max(1, int(chunk_size))
    rows = max(1, chunk // (R * R))
    for i0 in range(0, R, rows):
        slab = torch.stack(torch.meshgrid(axes[0][i0:i0 + rows], axes[1], axes[2], indexing="ij"), dim=-1)
        points, values = slab.reshape(-1, 3), out[i0:i0 + rows].view(-1)
        for s in range(0, points.shape[0], chunk):
            values[s:s + chunk] = sdf(points[s:s + chunk]).reshape(-1).to(dtype)
    return out


def padded_bounds(bounds: Tuple[Sequence[float], Sequence[float]], resolution: int,
                  margin: float = 0.05) -> Tuple[Tuple[float, ...], Tuple[float, ...]]:
    """``bounds`` grown on each side by ``margin`` x the largest extent plus one unpadded grid
    cell, so the grid's outer layer lies strictly outside the surface and the mesh closes."""
    lo = np.asarray(bounds[0], dtype=np.float64)
    hi = np.asarray(bounds[1], dtype=np.float64)
    extent = float((hi - lo).max())
    pad = margin * extent + extent / (max(int(resolution), 2) - 1)
    return tuple((lo - pad).tolist()), tuple((hi + pad).tolist())


def sdf_to_mesh(sdf: Callable[[torch.Tensor], torch.Tensor], resolution: int = 64,
                bounds: Optional[Tuple[Sequence[float], Sequence[float]]] = None, level: float = 0.0,
                colors: Optional[str] = "normal", chunk_size: Optional[int] = None, device=None,
                dtype: torch.dtype = torch.float32) -> Mesh:
    """Triangle mesh of ``{p : sdf(p) = level}`` inside ``bounds``.

    Args:
        sdf: callable (..., 3) -> (...), positive outside (e.g. :mod:`l3d_app.geometry.sdf`).
        resolution: grid points per axis (>= 3); the spacing is ``(hi - lo) / (resolution - 1)``.
        bounds: ``(lo, hi)`` world box sampled by the grid. Default: ``sdf.bounds()`` grown by
            :func:`padded_bounds` (the grid's outer layer stays outside the surface).
        level: iso-value.
        colors: ``"normal"`` for vertex colours ``0.5 + 0.5 * vertex normal``, or None.
        chunk_size: SDF evaluations per call (default: :func:`evaluate_grid`'s per device).
        device, dtype: where and in which precision the SDF is evaluated.

    Returns:
        Mesh with float32 verts (V, 3) in world units and faces (F, 3), counter-clockwise seen
        from the side where ``sdf > level`` (outward for an SDF).

    Raises:
        UserError: if the level set does not cross the grid (all values on one side of it).
    """
    R = int(resolution)
    if R < 3:
        raise UserError(f"marching cubes resolution must be >= 3, got {resolution}")
    if bounds is None:
        if not hasattr(sdf, "bounds"):
            raise UserError("sdf_to_mesh needs bounds=(lo, hi) for an SDF without a bounds() method")
        bounds = padded_bounds(sdf.bounds(), R)
    lo = [float(x) for x in bounds[0]]
    hi = [float(x) for x in bounds[1]]
    if len(lo) != 3 or len(hi) != 3 or not all(b > a for a, b in zip(lo, hi)):
        raise UserError(f"bounds must be (lo, hi) with lo < hi per axis, got {bounds}")
    values = evaluate_grid(sdf, lo, hi, R, chunk_size, device, dtype)
    if not bool(torch.isfinite(values).all()):
        raise UserError("the SDF returned NaN or Inf on the marching-cubes grid")
    spacing = tuple((b - a) / (R - 1) for a, b in zip(lo, hi))
    mesh = grid_to_mesh(values, lo, spacing, level, device=values.device if device is None else device,
                        what=f"inside bounds {tuple(lo)}..{tuple(hi)}")
    if colors == "normal":
        mesh = Mesh(verts=mesh.verts, faces=mesh.faces, vert_colors=(0.5 + 0.5 * mesh.vertex_normals()).clamp(0, 1))
    elif colors is not None:
        raise UserError(f"colors must be 'normal' or None, got {colors!r}")
    return mesh


def grid_to_mesh(values: torch.Tensor, lo: Sequence[float], spacing: Sequence[float], level: float = 0.0,
                 mask: Optional[torch.Tensor] = None, device=None, what: str = "on the grid") -> Mesh:
    """Marching cubes (skimage, Lewiner) of a grid of values (X, Y, Z) whose point ``[i, j, k]`` lies
    at ``lo + (i, j, k) * spacing`` (world units): a Mesh (float32 verts, faces counter-clockwise
    seen from the side of values above ``level``, i.e. outward for an SDF).

    ``mask`` (X - 1, Y - 1, Z - 1) bool, one per cube (its lowest corner's index): only the cubes
    flagged True are meshed (e.g. where all eight corners hold a measurement), so the surface may
    end inside the grid.
    Raises :class:`UserError` when no value lies on each side of ``level`` (``what`` says where).
    """
    volume = values.detach().cpu().double().numpy()
    m = None
    seen = volume
    if mask is not None:            # skimage flags a cube by its HIGHEST corner: shift by one
        m = np.zeros(volume.shape, dtype=bool)
        m[1:, 1:, 1:] = mask.detach().cpu().numpy().astype(bool)
        corners = np.zeros(volume.shape, dtype=bool)
        for di in (0, 1):
            for dj in (0, 1):
                for dk in (0, 1):
                    corners[di:volume.shape[0] - 1 + di, dj:volume.shape[1] - 1 + dj,
                            dk:volume.shape[2] - 1 + dk] |= m[1:, 1:, 1:]
        seen = volume[corners]
    vmin, vmax = (float(seen.min()), float(seen.max())) if seen.size else (0.0, 0.0)
    if not (vmin < level < vmax):
        raise UserError(f"the level set sdf = {level} is empty {what} "
                        f"(values on the grid lie in [{vmin:.4g}, {vmax:.4g}])")
    from skimage.measure import marching_cubes

    # The volume is indexed [i, j, k] = (x, y, z), so vertex columns are x, y, z.
    # Winding: with skimage's default gradient_direction='descent' the right-hand (cross
    # product) normal of each face points toward INcreasing values -- outward for an SDF that
    # is negative inside; 'ascent' would turn every face inward. (Checked in
    # tests/test_marching_cubes.py by the signed volume, which must be positive.)
    verts, faces, _, _ = marching_cubes(volume, level=level, spacing=tuple(float(x) for x in spacing),
                                        gradient_direction="descent", mask=m)
    verts = torch.from_numpy(np.ascontiguousarray(verts)).to(torch.float32) + \
        torch.tensor([float(x) for x in lo], dtype=torch.float32)
    faces = torch.from_numpy(np.ascontiguousarray(faces)).to(torch.int64)
    if faces.numel() == 0:
        raise UserError(f"the level set sdf = {level} is empty {what} (no cube crosses it)")
    return Mesh(verts=verts.to(device), faces=faces.to(device))
