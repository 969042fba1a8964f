"""Exact k-nearest neighbours and PCA normal estimation for point clouds.

:func:`knn` is brute force, exact and chunked over the queries so that the distance block
stays small (50k x 50k points run in a few hundred MB). :func:`estimate_normals` fits a
plane to each point's k nearest neighbours: the normal is the eigenvector of the smallest
eigenvalue of the neighbourhood covariance (Hoppe et al. 1992), computed for all points at
once with a batched ``torch.linalg.eigh``. PCA normals have no sign; ``orient`` picks one.
"""

from __future__ import annotations

from typing import Optional, Tuple, Union

import torch

from l3d_app.errors import UserError

# Entries of the (chunk, N) distance block computed at once (16M floats = 64 MB in float32).
_BLOCK_ELEMENTS = 1 << 24
# Extra candidates taken from the fast matmul distances, then re-ranked with exact ones.
_EXTRA_CANDIDATES = 8


def _check_points(points: torch.Tensor, name: str = "points") -> None:
    if points.dim() != 2 or points.shape[-1] != 3:
        raise UserError(f"{name} must be (N, 3), got {tuple(points.shape)}")
    if not points.is_floating_point():
        raise UserError(f"{name} must be a float tensor, got {points.dtype}")


def knn(points: torch.Tensor, k: int, queries: Optional[torch.Tensor] = None,
        chunk_size: Optional[int] = None) -> Tuple[torch.Tensor, torch.Tensor]:
    """Exact k nearest neighbours (Euclidean), brute force in chunks of queries.

    Each chunk ranks candidates by ``|p|^2 - 2 q.p`` (one ``addmm``, the matrix-multiply
    form of ``torch.cdist`` without the constant ``|q|^2`` and the square root), keeps
    ``k + 8`` of them, recomputes their squared distances exactly as ``|q - p|^2`` and
    re-ranks, so the result matches a direct brute force up to exact ties.

    Args:
        points: (N, 3) reference points.
        k: number of neighbours, 1 <= k <= N.
        queries: (M, 3) query points; default ``points`` itself, in which case each point
            is its own first neighbour (distance 0) -- or a duplicate of it.
        chunk_size: queries per chunk; default keeps the (chunk, N) block near 16M entries
            (50k points: 335 queries per chunk, 64 MB).
    Returns:
        indices (M, k) long into ``points`` and squared distances (M, k) (same dtype as
        ``points``, world units squared), both sorted by increasing distance. Not
        differentiable (computed without autograd).
    """
    _check_points(points)
    queries = points if queries is None else queries
    _check_points(queries, "queries")
    n, m = points.shape[0], queries.shape[0]
    if not 1 <= k <= n:
        raise UserError(f"knn needs 1 <= k <= number of points ({n}), got k={k}")
    if chunk_size is None:
        chunk_size = max(1, _BLOCK_ELEMENTS // max(n, 1))
    n_cand = min(n, k + _EXTRA_CANDIDATES)
    with torch.no_grad():
        ref = points.detach()
        centre = ref.mean(dim=0)  # centring keeps the matmul form's cancellation small
        ref_c = ref - centre
        ref_sq = ref_c.square().sum(dim=-1)  # (N,)
        ref_ct = ref_c.T.contiguous()  # (3, N)
        idx_out, d2_out = [], []
        for start in range(0, m, chunk_size):
            q = queries[start:start + chunk_size].detach()
            approx = torch.addmm(ref_sq[None], q - centre, ref_ct, alpha=-2)  # (C, N) = d^2 - |q|^2
            cand = approx.topk(n_cand, dim=-1, largest=False, sorted=False).indices  # (C, n_cand)
            exact = (q.unsqueeze(1) - ref[cand]).square().sum(dim=-1)  # (C, n_cand)
            d2, order = exact.topk(k, dim=-1, largest=False, sorted=True)
            idx_out.append(cand.gather(1, order))
            d2_out.append(d2)
        if m == 0:
            return (torch.zeros(0, k, dtype=torch.long, device=points.device),
                    torch.zeros(0, k, dtype=points.dtype, device=points.device))
        return torch.cat(idx_out), torch.cat(d2_out)


def orient_normals(normals: torch.Tensor, points: torch.Tensor,
                   orient: Union[str, torch.Tensor]) -> torch.Tensor:
    """Flip ``normals`` (N, 3) so that they point a consistent way.

    Args:
        normals: (N, 3) normals of any sign.
        points: (N, 3) their positions.
        orient: ``"outward"`` (away from the centroid of ``points``: ``n . (p - c) >= 0``),
            ``"inward"`` (towards it), or a viewpoint tensor (3,) or per-point (N, 3) in
            world units (towards it: ``n . (v - p) >= 0``, e.g. the camera centre of a scan).
    Returns:
        (N, 3) normals, each multiplied by +1 or -1 (a zero dot product keeps the sign).
    """
    if isinstance(orient, str):
        if orient not in ("outward", "inward"):
            raise UserError(f"orient must be 'outward', 'inward' or a viewpoint tensor, got '{orient}'")
        direction = points - points.mean(dim=0)
        if orient == "inward":
            direction = -direction
    else:
        view = torch.as_tensor(orient, dtype=points.dtype, device=points.device)
        if view.shape not in ((3,), points.shape):
            raise UserError(f"orient viewpoint must be (3,) or {tuple(points.shape)}, got {tuple(view.shape)}")
        direction = view - points
    flip = (normals * direction).sum(dim=-1, keepdim=True) < 0
    return torch.where(flip, -normals, normals)


def estimate_normals(points: torch.Tensor, k: int = 16,
                     orient: Optional[Union[str, torch.Tensor]] = None) -> torch.Tensor:
    """Unit normals of a point cloud by PCA over each point's k nearest neighbours.

    The local covariance ``C_i = 1/k sum_j (p_j - mean_i)(p_j - mean_i)^T`` over the k
    nearest neighbours (the point included) is diagonalised for all points at once in
    float64; the normal is the eigenvector of its smallest eigenvalue. Degenerate
    neighbourhoods (duplicate points, collinear neighbours) still give a finite unit
    vector, though an arbitrary one in the directions the data does not determine.

    Args:
        points: (N, 3) positions, world units; N >= 3.
        k: neighbourhood size, 3 <= k (clamped to N).
        orient: None (arbitrary sign per point), ``"outward"`` / ``"inward"`` (relative to
            the centroid; right for star-shaped objects such as a sphere) or a viewpoint
            tensor (3,) / (N, 3) to face, see :func:`orient_normals`.
    Returns:
        (N, 3) unit normals, same dtype as ``points``. Not differentiable (computed
        without autograd: eigenvector gradients are unbounded at repeated eigenvalues).
    """
    _check_points(points)
    n = points.shape[0]
    if n < 3:
        raise UserError(f"estimating normals needs at least 3 points, got {n}")
    if k < 3:
        raise UserError(f"estimating normals needs k >= 3 neighbours, got k={k}")
    k = min(k, n)
    with torch.no_grad():
        pts = points.detach()
        idx, _ = knn(pts, k)
        nbrs = pts[idx].to(torch.float64)  # (N, k, 3)
        centred = nbrs - nbrs.mean(dim=1, keepdim=True)
        cov = centred.transpose(1, 2) @ centred / k  # (N, 3, 3), symmetric PSD
        _, eigvecs = torch.linalg.eigh(cov)  # eigenvalues ascending
        normals = torch.nn.functional.normalize(eigvecs[..., 0], dim=-1).to(points.dtype)
        if orient is not None:
            normals = orient_normals(normals, pts, orient)
    return normals
