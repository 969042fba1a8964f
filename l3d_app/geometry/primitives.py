"""Procedural triangle meshes as :class:`~l3d_app.geometry.mesh.Mesh`.

Every shape is built in float64, returned as float32 vertices (V, 3) and int64 faces
(F, 3), counter-clockwise seen from outside (the right-hand normal points out), centred
at the origin with +Y up. Closed shapes (tetrahedron, cube, icosphere, uv_sphere,
cylinder, cone, torus) are watertight: every edge is shared by exactly two faces and
their signed volume is positive. ``plane`` is the only open surface.

Each constructor takes an optional ``color`` (3 floats in [0, 1]) that becomes constant
per-vertex colours; :func:`join` concatenates meshes (e.g. coloured parts of a scene).
"""

from __future__ import annotations

import math
from typing import Iterable, Optional, Sequence

import torch

from l3d_app.errors import UserError
from l3d_app.geometry.mesh import Mesh

Color = Optional[Sequence[float]]
_F64 = torch.float64


def _make(verts: torch.Tensor, faces: torch.Tensor, color: Color = None) -> Mesh:
    """Cast to the Mesh dtypes and attach constant per-vertex colours if asked."""
    verts = verts.to(torch.float32).contiguous()
    colors = None
    if color is not None:
        c = torch.as_tensor(color, dtype=torch.float32).reshape(-1)
        if c.numel() != 3 or not bool(((c >= 0) & (c <= 1)).all()):
            raise UserError(f"color must be 3 values in [0, 1], got {list(c.tolist())}")
        colors = c.expand_as(verts).clone()
    return Mesh(verts=verts, faces=faces.to(torch.int64).contiguous(), vert_colors=colors)


def _check_positive(**values: float) -> None:
    for name, value in values.items():
        if not value > 0:
            raise UserError(f"{name} must be > 0, got {value}")


def tetrahedron(radius: float = 1.0, color: Color = None) -> Mesh:
    """Regular tetrahedron with its 4 vertices at distance ``radius`` from the origin (4 faces)."""
    _check_positive(radius=radius)
    v = torch.tensor([[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]], dtype=_F64)
    f = torch.tensor([[0, 1, 2], [0, 3, 1], [0, 2, 3], [1, 3, 2]])
    return _make(v * (radius / math.sqrt(3.0)), f, color)


def cube(size: float = 1.0, color: Color = None) -> Mesh:
    """Axis-aligned cube of side ``size`` centred at the origin: 8 shared vertices, 12 faces."""
    _check_positive(size=size)
    idx = torch.arange(8)
    # vertex i has corner bits (x, y, z) = (i & 1, i >> 1 & 1, i >> 2 & 1)
    v = torch.stack([idx & 1, (idx >> 1) & 1, (idx >> 2) & 1], dim=-1).to(_F64) - 0.5
    f = torch.tensor([
        [0, 2, 3], [0, 3, 1],  # -Z
        [4, 5, 7], [4, 7, 6],  # +Z
        [0, 4, 6], [0, 6, 2],  # -X
        [1, 3, 7], [1, 7, 5],  # +X
        [0, 1, 5], [0, 5, 4],  # -Y
        [2, 6, 7], [2, 7, 3],  # +Y
    ])
    return _make(v * size, f, color)


def box(center: Sequence[float], size: Sequence[float], color: Color = None) -> Mesh:
    """Axis-aligned cuboid with the given ``center`` (3,) and side lengths ``size`` (3,)."""
    size_t = torch.as_tensor(size, dtype=_F64)
    _check_positive(**{f"size[{i}]": float(s) for i, s in enumerate(size_t)})
    m = cube(1.0)
    v = m.verts.to(_F64) * size_t + torch.as_tensor(center, dtype=_F64)
    return _make(v, m.faces, color)


def _icosahedron() -> tuple:
    t = (1.0 + math.sqrt(5.0)) / 2.0
    v = torch.tensor([
        [-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0],
        [0, -1, t], [0, 1, t], [0, -1, -t], [0, 1, -t],
        [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1]], dtype=_F64)
    f = torch.tensor([
        [0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11],
        [1, 5, 9], [5, 11, 4], [11, 10, 2], [10, 7, 6], [7, 1, 8],
        [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8], [3, 8, 9],
        [4, 9, 5], [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1]])
    return torch.nn.functional.normalize(v, dim=-1), f


def subdivide(verts: torch.Tensor, faces: torch.Tensor) -> tuple:
    """Loop-style 1-to-4 split without smoothing (vectorised).

    Args:
        verts: (V, 3) float positions.
        faces: (F, 3) long indices.
    Returns:
        ``(verts', faces')``: (V + E, 3) with one new vertex at the midpoint of each of
        the E unique edges (shared by its two faces), and (4F, 3) faces with the
        orientation of their parent.
    """
    edges = faces[:, [[0, 1], [1, 2], [2, 0]]].reshape(-1, 2)  # (3F, 2), edge k of face i at 3i+k
    uniq, inverse = torch.unique(edges.sort(dim=-1).values, dim=0, return_inverse=True)
    mids = 0.5 * (verts[uniq[:, 0]] + verts[uniq[:, 1]])
    m = inverse.reshape(-1, 3) + verts.shape[0]  # m0 = mid(v0 v1), m1 = mid(v1 v2), m2 = mid(v2 v0)
    v0, v1, v2 = faces.unbind(-1)
    m0, m1, m2 = m.unbind(-1)
    new_faces = torch.cat([
        torch.stack([v0, m0, m2], -1), torch.stack([v1, m1, m0], -1),
        torch.stack([v2, m2, m1], -1), torch.stack([m0, m1, m2], -1)])
    return torch.cat([verts, mids]), new_faces


def icosphere(level: int = 3, radius: float = 1.0, color: Color = None) -> Mesh:
    """Subdivided icosahedron: ``10 * 4**level + 2`` vertices, ``20 * 4**level`` faces.

    All vertices lie exactly (to float32 rounding) at ``radius``; edges are shared, so the
    mesh is watertight. ``level`` 0 is the icosahedron itself.
    """
    _check_positive(radius=radius)
    if int(level) != level or not 0 <= level <= 8:
        raise UserError(f"icosphere level must be an integer in [0, 8], got {level}")
    v, f = _icosahedron()
    for _ in range(int(level)):
        v, f = subdivide(v, f)
        v = torch.nn.functional.normalize(v, dim=-1)
    return _make(v * radius, f, color)


def _grid_faces(rows: int, cols: int, wrap_cols: bool, offset: int = 0) -> torch.Tensor:
    """Two triangles per cell of a (rows, cols) vertex grid stored row-major.

    Cell (i, j) joins vertices (i, j), (i, j+1), (i+1, j), (i+1, j+1); columns wrap
    around when ``wrap_cols``. Returns (2 * (rows-1) * ncells_per_row, 3) long,
    oriented so that the normal is (d/d row) x (d/d col).
    """
    ncols = cols if wrap_cols else cols - 1
    i = torch.arange(rows - 1).repeat_interleave(ncols)
    j = torch.arange(ncols).repeat(rows - 1)
    j1 = (j + 1) % cols
    a, b = i * cols + j + offset, i * cols + j1 + offset
    c, d = (i + 1) * cols + j + offset, (i + 1) * cols + j1 + offset
    return torch.cat([torch.stack([a, c, b], -1), torch.stack([b, c, d], -1)])


def uv_sphere(n_lat: int = 16, n_lon: int = 32, radius: float = 1.0, color: Color = None) -> Mesh:
    """Latitude/longitude sphere: 2 poles + (n_lat - 1) rings of n_lon vertices."""
    _check_positive(radius=radius)
    if n_lat < 2 or n_lon < 3:
        raise UserError(f"uv_sphere needs n_lat >= 2 and n_lon >= 3, got {n_lat}, {n_lon}")
    theta = torch.arange(1, n_lat, dtype=_F64) * (math.pi / n_lat)  # polar angle from +Y
    phi = torch.arange(n_lon, dtype=_F64) * (2 * math.pi / n_lon)
    th, ph = torch.meshgrid(theta, phi, indexing="ij")
    rings = torch.stack([th.sin() * ph.sin(), th.cos(), th.sin() * ph.cos()], -1).reshape(-1, 3)
    poles = torch.tensor([[0.0, 1.0, 0.0], [0.0, -1.0, 0.0]], dtype=_F64)
    v = torch.cat([rings, poles]) * radius
    top, bottom = rings.shape[0], rings.shape[0] + 1
    j = torch.arange(n_lon)
    j1 = (j + 1) % n_lon
    last = (n_lat - 2) * n_lon
    caps = torch.cat([
        torch.stack([torch.full_like(j, top), j, j1], -1),
        torch.stack([torch.full_like(j, bottom), last + j1, last + j], -1)])
    return _make(v, torch.cat([_grid_faces(n_lat - 1, n_lon, True), caps]), color)


def _disk_fan(ring_start: int, center: int, n: int, up: bool) -> torch.Tensor:
    """Fan of n triangles from ``center`` over a ring of n vertices (normal +Y if ``up``)."""
    j = torch.arange(n)
    a, b = ring_start + j, ring_start + (j + 1) % n
    c = torch.full_like(j, center)
    return torch.stack([c, a, b] if up else [c, b, a], -1)


def _ring(n: int, radius: float, y: float) -> torch.Tensor:
    """(n, 3) points on a horizontal circle; increasing index turns from +Z towards +X."""
    phi = torch.arange(n, dtype=_F64) * (2 * math.pi / n)
    return torch.stack([radius * phi.sin(), torch.full_like(phi, y), radius * phi.cos()], -1)


def cylinder(radius: float = 0.5, height: float = 1.0, n: int = 32, color: Color = None) -> Mesh:
    """Closed cylinder along Y, centred, with flat caps: 2n + 2 vertices, 4n faces."""
    _check_positive(radius=radius, height=height)
    if n < 3:
        raise UserError(f"cylinder needs n >= 3 segments, got {n}")
    v = torch.cat([_ring(n, radius, height / 2), _ring(n, radius, -height / 2),
                   torch.tensor([[0, height / 2, 0], [0, -height / 2, 0]], dtype=_F64)])
    f = torch.cat([_grid_faces(2, n, True), _disk_fan(0, 2 * n, n, True),
                   _disk_fan(n, 2 * n + 1, n, False)])
    return _make(v, f, color)


def cone(radius: float = 0.5, height: float = 1.0, n: int = 32, color: Color = None) -> Mesh:
    """Closed cone along Y, base at y = -height/2, apex at y = +height/2: n + 2 vertices, 2n faces."""
    _check_positive(radius=radius, height=height)
    if n < 3:
        raise UserError(f"cone needs n >= 3 segments, got {n}")
    v = torch.cat([_ring(n, radius, -height / 2),
                   torch.tensor([[0, height / 2, 0], [0, -height / 2, 0]], dtype=_F64)])
    f = torch.cat([_disk_fan(0, n, n, True), _disk_fan(0, n + 1, n, False)])
    return _make(v, f, color)


def torus(major_radius: float = 0.7, minor_radius: float = 0.3, n_major: int = 48,
          n_minor: int = 24, color: Color = None) -> Mesh:
    """Torus around the Y axis (lying in the XZ plane): n_major * n_minor vertices, twice as many faces.

    Analytic volume ``2 pi^2 R r^2``; the polygonal mesh encloses slightly less.
    """
    _check_positive(major_radius=major_radius, minor_radius=minor_radius)
    if minor_radius >= major_radius:
        raise UserError(f"torus needs minor_radius < major_radius, got {minor_radius} >= {major_radius}")
    if n_major < 3 or n_minor < 3:
        raise UserError(f"torus needs n_major, n_minor >= 3, got {n_major}, {n_minor}")
    u = torch.arange(n_major, dtype=_F64) * (2 * math.pi / n_major)  # around the Y axis
    w = torch.arange(n_minor, dtype=_F64) * (2 * math.pi / n_minor)  # around the tube
    uu, ww = torch.meshgrid(u, w, indexing="ij")
    ring = major_radius + minor_radius * ww.cos()
    v = torch.stack([ring * uu.sin(), minor_radius * ww.sin(), ring * uu.cos()], -1).reshape(-1, 3)
    # rows = steps around Y, columns = steps around the tube; both directions wrap.
    f = _grid_faces(n_major + 1, n_minor, True)
    f = torch.where(f >= n_major * n_minor, f - n_major * n_minor, f)
    return _make(v, f, color)


def plane(size: float = 2.0, n: int = 1, color: Color = None) -> Mesh:
    """Open square in the XZ plane (y = 0), side ``size``, facing +Y: (n+1)^2 vertices, 2n^2 faces."""
    _check_positive(size=size)
    if n < 1:
        raise UserError(f"plane needs n >= 1 cells per side, got {n}")
    t = torch.linspace(-size / 2, size / 2, n + 1, dtype=_F64)
    zz, xx = torch.meshgrid(t, t, indexing="ij")  # rows go along +Z, columns along +X
    v = torch.stack([xx, torch.zeros_like(xx), zz], -1).reshape(-1, 3)
    return _make(v, _grid_faces(n + 1, n + 1, False), color)


def join(meshes: Iterable[Mesh]) -> Mesh:
    """Concatenate meshes into one (vertex colours kept when every part has them).

    UV textures cannot be joined here (they would need an atlas): a textured part raises.
    """
    meshes = list(meshes)
    if not meshes:
        raise UserError("join needs at least one mesh")
    if any(m.has_texture for m in meshes):
        raise UserError("join does not combine UV-textured meshes")
    offsets = torch.tensor([0] + [m.num_verts for m in meshes[:-1]]).cumsum(0)
    faces = torch.cat([m.faces + int(o) for m, o in zip(meshes, offsets)])
    verts = torch.cat([m.verts for m in meshes])
    colors = None
    if all(m.vert_colors is not None for m in meshes):
        colors = torch.cat([m.vert_colors for m in meshes])
    return Mesh(verts=verts, faces=faces, vert_colors=colors)


def transformed(mesh: Mesh, rotation: Optional[torch.Tensor] = None,
                translation: Sequence[float] = (0.0, 0.0, 0.0), scale: float = 1.0) -> Mesh:
    """``x -> scale * R x + t`` applied to the vertices (column vectors; R is (3, 3))."""
    v = mesh.verts.to(_F64) * scale
    if rotation is not None:
        v = v @ torch.as_tensor(rotation, dtype=_F64).T
    v = v + torch.as_tensor(translation, dtype=_F64)
    return mesh.with_verts(v.to(mesh.verts.dtype))
