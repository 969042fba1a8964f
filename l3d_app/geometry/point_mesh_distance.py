"""Exact unsigned distance from points to a triangle mesh, with the closest face and point.

Why exact: a chamfer distance between two *samplings* of surfaces is biased upwards by the
sampling itself (two independent 10k samplings of the same 6.3 square-unit surface are
about 0.012 world units apart on average, each way). Distances from sample points to the
other *mesh* have no such floor: they are the integrand of the true surface-to-surface
chamfer distance. RGB-D round trips (:mod:`l3d_app.geometry.rgbd`) use the closest face
and barycentrics to compare colours at the closest surface point.

How (:func:`point_mesh_distance`): a k-d tree over the face centroids (scipy) gives each
point its nearest centroid; that face's exact point-triangle distance ``u`` is an upper
bound. A face can only be closer than ``u`` if its centroid lies within ``u + r_f`` (``r_f``
= the face's centroid-to-vertex radius). The faces are grouped by size (``r_f`` within a
factor of two), one tree per group, and each group's ball query (radius ``u + max r`` of
the group) lists the candidates: a few large faces in a finely tessellated mesh (a
32-triangle tray on a 160k-triangle slab) then widen only their own group's query, not
every face's (one global ``max r`` would list ~20k candidates per point there). The per-face test prunes them, and only those (point, face) pairs are evaluated
exactly (:func:`closest_point_barycentrics`) in float64 and reduced with a scatter-min.
The result is exact (up to float64 rounding); the pruning only skips faces that cannot
win. Ties between faces go to the lowest face index.

This is the only point-to-mesh distance of the library (metrics use it too).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch

from l3d_app.errors import UserError
from l3d_app.geometry.mesh import Mesh

_POINT_CHUNK = 4096       # points per k-d tree query batch
_PAIR_CHUNK = 1 << 20     # (point, face) pairs evaluated exactly at once


class MeshDistance(NamedTuple):
    """Result of :func:`point_mesh_distance` (indexable: ``result[0]`` is the distance)."""

    distance: torch.Tensor  # (P,) world units, the points' float dtype
    face: torch.Tensor      # (P,) long, index of the closest face
    bary: torch.Tensor      # (P, 3) barycentrics of the closest point w.r.t. mesh.faces[face]


def closest_point_barycentrics(p: torch.Tensor, a: torch.Tensor, b: torch.Tensor, c: torch.Tensor
                               ) -> torch.Tensor:
    """Barycentrics (..., 3) of the closest point to ``p`` on triangles (a, b, c), all
    broadcastable (..., 3).

    The best of four candidates: the projection onto the plane when it falls inside a
    non-degenerate triangle (Ericson, "Real-Time Collision Detection", 5.1.5), and the
    closest point of each edge as a segment (a zero-length edge gives its end point), so
    degenerate triangles (collinear or repeated vertices) are exact too, without dividing
    by a zero area.
    """
    dot = lambda x, y: (x * y).sum(-1)  # noqa: E731
    safe = lambda d: torch.where(d > 0, d, torch.ones_like(d))  # noqa: E731
    ab, ac, ap, bp, cp = b - a, c - a, p - a, p - b, p - c
    d1, d2, d3, d4, d5, d6 = dot(ab, ap), dot(ac, ap), dot(ab, bp), dot(ac, bp), dot(ab, cp), dot(ac, cp)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    denom = va + vb + vc  # = |ab x ac|^2 >= 0
    inside = (va >= 0) & (vb >= 0) & (vc >= 0) & (denom > 0)
    z = torch.zeros_like(d1)
    best_b = torch.stack([va, vb, vc], -1) / safe(denom)[..., None]
    q = best_b[..., :1] * a + best_b[..., 1:2] * b + best_b[..., 2:] * c
    best_d = torch.where(inside, dot(p - q, p - q), torch.full_like(d1, float("inf")))
    bc = c - b
    edges = (  # (start, direction, start-to-p, param -> barycentrics)
        (a, ab, ap, lambda t: torch.stack([1 - t, t, z], -1)),
        (a, ac, ap, lambda t: torch.stack([1 - t, z, t], -1)),
        (b, bc, bp, lambda t: torch.stack([z, 1 - t, t], -1)),
    )
    for start, e, rel, to_bary in edges:
        t = (dot(rel, e) / safe(dot(e, e))).clamp(0, 1)
        q = start + t[..., None] * e
        d = dot(p - q, p - q)
        better = d < best_d
        best_d = torch.where(better, d, best_d)
        best_b = torch.where(better[..., None], to_bary(t), best_b)
    return best_b


def point_triangle_distance(p: torch.Tensor, a: torch.Tensor, b: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
    """(...,) Euclidean distance from points ``p`` to triangles (a, b, c), all (..., 3)."""
    bary = closest_point_barycentrics(p, a, b, c)
    q = bary[..., :1] * a + bary[..., 1:2] * b + bary[..., 2:] * c
    return (p - q).norm(dim=-1)


@torch.no_grad()
def point_mesh_distance(points: torch.Tensor, mesh: Mesh) -> MeshDistance:
    """Exact distance from each of ``points`` (N, 3) to the surface of ``mesh``.

    Computed on the CPU in float64 (no gradient); returned on the points' device, the
    distance and barycentrics in the points' float dtype (float64 for integer input).

    Returns:
        :class:`MeshDistance` (distance (N,), face (N,) long, bary (N, 3)).
    Raises:
        UserError: points not (N, 3), or a mesh without faces.
    """
    from scipy.spatial import cKDTree

    if points.dim() != 2 or points.shape[-1] != 3:
        raise UserError(f"point_mesh_distance: points must be (N, 3), got {tuple(points.shape)}")
    if mesh.num_faces == 0:
        raise UserError("point_mesh_distance: the mesh has no faces")
    pts = points.detach().to("cpu", torch.float64)
    tri = mesh.verts.detach().to("cpu", torch.float64)[mesh.faces.cpu()]              # (F, 3, 3)
    centroid = tri.mean(dim=1)                                                       # (F, 3)
    radius = (tri - centroid[:, None]).norm(dim=-1).amax(dim=1)                      # (F,)
    tree = cKDTree(centroid.numpy())
    groups = _size_groups(centroid, radius)
    workers = max(1, torch.get_num_threads())
    dist = torch.empty(pts.shape[0], dtype=torch.float64)
    face = torch.empty(pts.shape[0], dtype=torch.long)
    for s in range(0, pts.shape[0], _POINT_CHUNK):
        p = pts[s:s + _POINT_CHUNK]
        _, first = tree.query(p.numpy(), k=1, workers=workers)
        first = torch.from_numpy(np.asarray(first, dtype=np.int64))
        f0 = tri[first]
        upper = point_triangle_distance(p, f0[:, 0], f0[:, 1], f0[:, 2])             # (C,)
        rows, cols = _candidates(p, upper, groups, workers)
        keep = (p[rows] - centroid[cols]).norm(dim=-1) - radius[cols] <= upper[rows] + 1e-12
        rows, cols = rows[keep], cols[keep]
        pair_d = torch.cat([point_triangle_distance(p[rows[k:k + _PAIR_CHUNK]], *tri[cols[k:k + _PAIR_CHUNK]].unbind(1))
                            for k in range(0, rows.numel(), _PAIR_CHUNK)]) if rows.numel() else upper[:0]
        best = upper.scatter_reduce(0, rows, pair_d, reduce="amin")
        # the winning face: lowest index among the pairs at the best distance (else the first)
        winner = torch.where(pair_d <= best[rows], cols, torch.full_like(cols, tri.shape[0]))
        best_face = torch.full_like(first, tri.shape[0]).scatter_reduce(0, rows, winner, reduce="amin")
        best_face = torch.where(best_face < tri.shape[0], best_face, first)
        dist[s:s + _POINT_CHUNK] = best
        face[s:s + _POINT_CHUNK] = best_face
    t = tri[face]
    bary = closest_point_barycentrics(pts, t[:, 0], t[:, 1], t[:, 2])
    dtype = points.dtype if points.is_floating_point() else torch.float64
    return MeshDistance(dist.to(device=points.device, dtype=dtype), face.to(points.device),
                        bary.to(device=points.device, dtype=dtype))


def _size_groups(centroid: torch.Tensor, radius: torch.Tensor):
    """Faces grouped by size (radius within a factor of two): [(tree, face ids, max radius)]."""
    from scipy.spatial import cKDTree

    size_class = torch.floor(torch.log2(radius.clamp_min(1e-30))).long()
    groups = []
    for c in torch.unique(size_class).tolist():
        ids = torch.nonzero(size_class == c).squeeze(1)
        groups.append((cKDTree(centroid[ids].numpy()), ids, float(radius[ids].max())))
    return groups


def _candidates(p: torch.Tensor, upper: torch.Tensor, groups, workers: int):
    """(point row, face id) pairs whose face centroid lies within ``upper + max r`` of the
    point, the ``max r`` of the face's own size group (a superset of the faces that can win)."""
    rows, cols = [], []
    for tree, ids, r_max in groups:
        reach = (upper + r_max).numpy() + 1e-12
        balls = tree.query_ball_point(p.numpy(), reach, workers=workers)
        counts = torch.from_numpy(tree.query_ball_point(p.numpy(), reach, workers=workers,
                                                        return_length=True).astype(np.int64))
        if int(counts.sum()) == 0:
            continue
        rows.append(torch.repeat_interleave(torch.arange(p.shape[0]), counts))
        cols.append(ids[torch.from_numpy(np.concatenate(balls).astype(np.int64))])
    if not rows:
        empty = torch.zeros(0, dtype=torch.long)
        return empty, empty
    return torch.cat(rows), torch.cat(cols)
