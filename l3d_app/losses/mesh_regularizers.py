"""Mesh regularisers for fitting: uniform Laplacian smoothing, normal consistency, edge length.

All take vertex positions (V, 3) (with autograd) and integer faces (F, 3), are vectorised
(``index_add`` / gathers, no Python loops over elements) and stay finite -- values and
gradients -- on degenerate (zero-area, repeated-vertex) faces.
"""

from __future__ import annotations

import torch

from l3d_app.geometry.sdf import safe_norm
from l3d_app.registry import LOSSES


def mesh_edges(faces: torch.Tensor) -> torch.Tensor:
    """(E, 2) unique undirected edges (sorted pairs) of (F, 3) faces; self-edges dropped."""
    e = faces[:, [[0, 1], [1, 2], [2, 0]]].reshape(-1, 2).sort(dim=-1).values
    e = e[e[:, 0] != e[:, 1]]
    return torch.unique(e, dim=0)


def uniform_laplacian(verts: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """(V, 3) uniform Laplacian ``L v_i = v_i - mean_{j in N(i)} v_j`` over the edge graph.

    Zero for a vertex that is the centroid of its neighbours (e.g. interior vertices of a
    regular flat grid) and for isolated vertices (no neighbours). World units.
    """
    e = mesh_edges(faces)
    src, dst = torch.cat([e[:, 0], e[:, 1]]), torch.cat([e[:, 1], e[:, 0]])
    sums = torch.zeros_like(verts).index_add(0, src, verts[dst])
    deg = torch.zeros(verts.shape[0], dtype=verts.dtype, device=verts.device).index_add(
        0, src, torch.ones_like(src, dtype=verts.dtype))
    has = (deg > 0).unsqueeze(-1)
    return torch.where(has, verts - sums / deg.clamp_min(1).unsqueeze(-1), torch.zeros_like(verts))


def laplacian_smoothing(verts: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """Scalar mean over vertices of ``|L v_i|^2`` (world units^2)."""
    return uniform_laplacian(verts, faces).square().sum(-1).mean()


def _edge_face_pairs(faces: torch.Tensor) -> torch.Tensor:
    """(P, 2) indices of face pairs sharing a manifold edge (edges with exactly two faces)."""
    e = faces[:, [[0, 1], [1, 2], [2, 0]]].reshape(-1, 2).sort(dim=-1).values  # (3F, 2)
    _, inverse, counts = torch.unique(e, dim=0, return_inverse=True, return_counts=True)
    order = torch.argsort(inverse, stable=True)
    face_of = order // 3
    starts = torch.cumsum(counts, 0) - counts
    two = counts == 2
    return torch.stack([face_of[starts[two]], face_of[starts[two] + 1]], dim=-1)


def normal_consistency(verts: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """Scalar mean over manifold edges of ``1 - cos`` of the angle between the two faces' normals.

    0 for a flat (or any planar, consistently oriented) mesh. Degenerate faces have a zero
    normal; the cosine uses ``n1.n2 / sqrt((|n1|^2 + d)(|n2|^2 + d))`` with ``d`` tiny relative
    to the mean face normal, so values and gradients stay finite there.
    """
    fv = verts[faces]
    n = torch.cross(fv[:, 1] - fv[:, 0], fv[:, 2] - fv[:, 0], dim=-1)  # (F, 3), |n| = 2 area
    pairs = _edge_face_pairs(faces)
    if pairs.shape[0] == 0:
        return verts.sum() * 0
    sq = n.square().sum(-1)
    d = (1e-6 * sq.detach().sqrt().mean()).square() + torch.finfo(verts.dtype).tiny
    n1, n2 = n[pairs[:, 0]], n[pairs[:, 1]]
    cos = (n1 * n2).sum(-1) / ((sq[pairs[:, 0]] + d) * (sq[pairs[:, 1]] + d)).sqrt()
    return (1 - cos).mean()


def edge_length(verts: torch.Tensor, faces: torch.Tensor, target_length: float = 0.0) -> torch.Tensor:
    """Scalar mean over unique edges of ``(|e| - target)^2`` (``|e|^2`` when target is 0), units^2."""
    e = mesh_edges(faces)
    vec = verts[e[:, 1]] - verts[e[:, 0]]
    if target_length == 0:
        return vec.square().sum(-1).mean()
    return (safe_norm(vec) - float(target_length)).square().mean()


@LOSSES.register("mesh_laplacian")
class LaplacianSmoothing:
    """``loss(verts, faces)``: :func:`laplacian_smoothing`."""

    def __call__(self, verts: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
        return laplacian_smoothing(verts, faces)


@LOSSES.register("normal_consistency")
class NormalConsistency:
    """``loss(verts, faces)``: :func:`normal_consistency`."""

    def __call__(self, verts: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
        return normal_consistency(verts, faces)


@LOSSES.register("edge_length")
class EdgeLength:
    """``loss(verts, faces)``: :func:`edge_length` with a fixed ``target_length``."""

    def __init__(self, target_length: float = 0.0):
        self.target_length = float(target_length)

    def __call__(self, verts: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
        return edge_length(verts, faces, self.target_length)
