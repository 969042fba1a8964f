"""Exact unsigned distance from points to a triangle mesh, pure PyTorch, vectorised.

Why: a chamfer distance between two *samplings* of surfaces is biased upwards by the
sampling itself (two independent 10k samplings of the same 6.3 square-unit surface are
about 0.012 world units apart on average, each way). Distances from sample points to the
other *mesh* have no such floor: they are the integrand of the true surface-to-surface
chamfer distance.

How (:func:`point_mesh_distance`): a k-d tree over the face centroids (scipy) gives each
point its nearest centroid; that face's exact point-triangle distance ``u`` is an upper
bound. A face can only be closer than ``u`` if its centroid lies within ``u + r_f`` (``r_f``
= the face's centroid-to-vertex radius), so the tree's ball query (radius ``u + max r``)
lists the candidates, the per-face test prunes them, and only those (point, face) pairs
are evaluated exactly (closest point on a triangle, Ericson, "Real-Time Collision
Detection", 5.1.5) in float64 and reduced with a scatter-min. The result is exact (up to
float64 rounding); the pruning only skips faces that cannot win.
"""

from __future__ import annotations

import numpy as np
import torch

from l3d_app.errors import UserError
from l3d_app.geometry.mesh import Mesh

_POINT_CHUNK = 4096       # points per k-d tree query batch
_PAIR_CHUNK = 1 << 20     # (point, face) pairs evaluated exactly at once


def point_triangle_distance(p: torch.Tensor, a: torch.Tensor, b: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
    """(P,) Euclidean distance from points p (P, 3) to triangles (a, b, c) (each (P, 3)).

    Closest-point by Voronoi regions (vertex, edge, face); degenerate triangles fall back
    to their edges and vertices through the same tests (no division by a zero area).
    """
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = (ab * ap).sum(-1), (ac * ap).sum(-1)
    bp = p - b
    d3, d4 = (ab * bp).sum(-1), (ac * bp).sum(-1)
    cp = p - c
    d5, d6 = (ab * cp).sum(-1), (ac * cp).sum(-1)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2

    def safe_div(num, den):
        return num / torch.where(den.abs() > 0, den, torch.ones_like(den))

    # face region (default), then override by edge and vertex regions (later wins)
    denom = va + vb + vc
    v = safe_div(vb, denom)
    w = safe_div(vc, denom)
    q = a + ab * v[:, None] + ac * w[:, None]
    # edge BC
    e_bc = (va <= 0) & ((d4 - d3) >= 0) & ((d5 - d6) >= 0)
    w_bc = safe_div(d4 - d3, (d4 - d3) + (d5 - d6))
    q = torch.where(e_bc[:, None], b + (c - b) * w_bc[:, None], q)
    # edge AC
    e_ac = (vb <= 0) & (d2 >= 0) & (d6 <= 0)
    w_ac = safe_div(d2, d2 - d6)
    q = torch.where(e_ac[:, None], a + ac * w_ac[:, None], q)
    # edge AB
    e_ab = (vc <= 0) & (d1 >= 0) & (d3 <= 0)
    v_ab = safe_div(d1, d1 - d3)
    q = torch.where(e_ab[:, None], a + ab * v_ab[:, None], q)
    # vertices
    q = torch.where(((d6 >= 0) & (d5 <= d6))[:, None], c, q)
    q = torch.where(((d3 >= 0) & (d4 <= d3))[:, None], b, q)
    q = torch.where(((d1 <= 0) & (d2 <= 0))[:, None], a, q)
    return (p - q).norm(dim=-1)


@torch.no_grad()
def point_mesh_distance(points: torch.Tensor, mesh: Mesh) -> torch.Tensor:
    """(N,) exact distance (world units) from each of ``points`` (N, 3) to the surface of
    ``mesh`` (its triangles); computed on the CPU in float64, returned on the points' device
    in their float dtype."""
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
    workers = max(1, torch.get_num_threads())
    out = torch.empty(pts.shape[0], dtype=torch.float64)
    for s in range(0, pts.shape[0], _POINT_CHUNK):
        p = pts[s:s + _POINT_CHUNK]
        _, first = tree.query(p.numpy(), k=1, workers=workers)
        f0 = tri[torch.from_numpy(first)]
        upper = point_triangle_distance(p, f0[:, 0], f0[:, 1], f0[:, 2])             # (C,)
        reach = (upper + radius.max()).numpy() + 1e-12
        balls = tree.query_ball_point(p.numpy(), reach, workers=workers)
        counts = torch.from_numpy(tree.query_ball_point(p.numpy(), reach, workers=workers,
                                                        return_length=True).astype(np.int64))
        rows = torch.repeat_interleave(torch.arange(p.shape[0]), counts)
        cols = torch.from_numpy(np.concatenate(balls).astype(np.int64)) if rows.numel() else rows
        keep = (p[rows] - centroid[cols]).norm(dim=-1) - radius[cols] <= upper[rows] + 1e-12
        rows, cols = rows[keep], cols[keep]
        best = upper.clone()
        for k in range(0, rows.numel(), _PAIR_CHUNK):
            r, c = rows[k:k + _PAIR_CHUNK], cols[k:k + _PAIR_CHUNK]
            t = tri[c]
            best.scatter_reduce_(0, r, point_triangle_distance(p[r], t[:, 0], t[:, 1], t[:, 2]), reduce="amin")
        out[s:s + _POINT_CHUNK] = best
    dtype = points.dtype if points.is_floating_point() else torch.float64
    return out.to(device=points.device, dtype=dtype)
