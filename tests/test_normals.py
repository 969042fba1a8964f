"""Exact kNN and PCA normal estimation."""

import pytest
import torch

from l3d_app.errors import UserError
from l3d_app.geometry.normals import estimate_normals, knn, orient_normals


def _gen(seed=0):
    return torch.Generator().manual_seed(seed)


def _sphere_points(n, seed=0, dtype=torch.float32):
    p = torch.randn(n, 3, generator=_gen(seed), dtype=torch.float64)
    return torch.nn.functional.normalize(p, dim=-1).to(dtype)


def test_knn_matches_brute_force():
    pts = torch.rand(700, 3, generator=_gen(1)) * 4 + 10  # offset: exercises cancellation
    queries = torch.rand(300, 3, generator=_gen(2)) * 4 + 10
    idx, d2 = knn(pts, 7, queries=queries, chunk_size=64)
    ref = (queries[:, None].double() - pts[None].double()).square().sum(-1)  # (300, 700)
    ref_d2, ref_idx = ref.topk(7, dim=-1, largest=False, sorted=True)
    assert idx.shape == (300, 7) and d2.shape == (300, 7)
    assert torch.equal(idx, ref_idx)
    assert torch.allclose(d2.double(), ref_d2, rtol=1e-5, atol=1e-6)
    # self query: each point is its own nearest neighbour; default chunking agrees
    idx_self, d2_self = knn(pts, 4)
    assert torch.equal(idx_self[:, 0], torch.arange(700))
    assert bool((d2_self[:, 0] == 0).all())
    assert bool((d2_self[:, 1:] >= d2_self[:, :-1]).all())


def test_knn_bad_k():
    with pytest.raises(UserError):
        knn(torch.rand(5, 3), 6)
    with pytest.raises(UserError):
        knn(torch.rand(5, 2), 1)


def test_plane_normals():
    n_true = torch.nn.functional.normalize(torch.tensor([0.3, -0.5, 0.8]), dim=0)
    u = torch.nn.functional.normalize(torch.linalg.cross(n_true, torch.tensor([1.0, 0.0, 0.0])), dim=0)
    v = torch.linalg.cross(n_true, u)
    ab = torch.rand(2000, 2, generator=_gen(3)) * 2 - 1
    origin = torch.tensor([1.0, 2.0, -0.5])
    pts = origin + ab[:, :1] * u + ab[:, 1:] * v
    view = origin + 5 * n_true
    normals = estimate_normals(pts, k=12, orient=view)
    assert float((normals - n_true).norm(dim=-1).max()) < 1e-4
    flipped = estimate_normals(pts, k=12, orient=origin - 5 * n_true)
    assert float((flipped + n_true).norm(dim=-1).max()) < 1e-4
    # unoriented: right up to sign
    raw = estimate_normals(pts, k=12)
    assert float(1 - (raw @ n_true).abs().min()) < 1e-6


def test_sphere_normals_radial_and_outward():
    pts = _sphere_points(3000, seed=4)
    normals = estimate_normals(pts, k=16, orient="outward")
    radial = torch.nn.functional.normalize(pts, dim=-1)
    cos = (normals * radial).sum(-1)
    assert bool((cos > 0).all())
    angle = torch.rad2deg(torch.arccos(cos.clamp(max=1)))
    assert float(angle.mean()) < 2.0
    assert float(angle.max()) < 10.0
    assert torch.allclose(normals.norm(dim=-1), torch.ones(3000), atol=1e-5)
    inward = estimate_normals(pts, k=16, orient="inward")
    assert torch.allclose(inward, -normals)
    # orienting towards the centre as a viewpoint is the same as inward here
    assert torch.allclose(orient_normals(normals, pts, torch.zeros(3)), -normals)


def test_duplicate_points_do_not_give_nan():
    base = torch.rand(50, 3, generator=_gen(5))
    pts = torch.cat([base.repeat(20, 1), torch.zeros(30, 3)])  # every point 20x; 30 at one spot
    normals = estimate_normals(pts, k=16, orient="outward")
    assert torch.isfinite(normals).all()
    assert torch.allclose(normals.norm(dim=-1), torch.ones(len(pts)), atol=1e-5)
    idx, d2 = knn(pts, 16)
    assert torch.isfinite(d2).all() and bool((d2 == 0).all())  # 16 copies at distance 0


def test_bad_orient():
    with pytest.raises(UserError):
        estimate_normals(_sphere_points(100), orient="up")
    with pytest.raises(UserError):
        estimate_normals(_sphere_points(100), orient=torch.zeros(2))


def test_large_cloud_runs_chunked():
    pts = torch.rand(12_000, 3, generator=_gen(6))
    idx, d2 = knn(pts, 8)
    assert idx.shape == (12_000, 8)
    sub = torch.arange(0, 12_000, 997)
    ref = (pts[sub, None] - pts[None]).square().sum(-1).topk(8, largest=False).values
    assert torch.allclose(d2[sub], ref, atol=1e-7)
