"""Area-weighted, uniform, differentiable sampling of points on mesh surfaces."""

import math

import pytest
import torch
from scipy.stats import chisquare

from l3d_app.errors import UserError
from l3d_app.geometry.mesh import Mesh
from l3d_app.geometry.primitives import cube, icosphere
from l3d_app.geometry.sampling import (sample_points_on_mesh, sample_surface, sampling_weights,
                                       uniform_barycentrics)


def _triangles(scales, degenerate=0):
    """Disjoint right triangles with legs ``s`` (area s^2 / 2), then collinear ones."""
    verts, faces = [], []
    for i, s in enumerate(scales):
        o = torch.tensor([3.0 * i, 0.0, 0.0])
        verts += [o, o + torch.tensor([s, 0.0, 0.0]), o + torch.tensor([0.0, s, 0.0])]
        faces.append([3 * i, 3 * i + 1, 3 * i + 2])
    for j in range(degenerate):
        b = 3 * (len(scales) + j)
        o = torch.tensor([0.0, -5.0 - j, 1.0])
        verts += [o, o + torch.tensor([1.0, 1.0, 1.0]), o + torch.tensor([2.0, 2.0, 2.0])]
        faces.append([b, b + 1, b + 2])
    return Mesh(torch.stack(verts), torch.tensor(faces))


def _gen(seed=0):
    return torch.Generator().manual_seed(seed)


def test_face_counts_proportional_to_area():
    scales = [0.1, 0.3, 1.0, 2.0, 4.5]  # areas span a factor ~2000
    mesh = _triangles(scales)
    n = 400_000
    s = sample_surface(mesh, n, _gen(1))
    counts = torch.bincount(s.face_index, minlength=len(scales)).double()
    areas = torch.tensor(scales, dtype=torch.float64) ** 2 / 2
    expected = n * areas / areas.sum()
    assert float(expected.min()) > 5  # chi-square validity
    assert chisquare(counts.numpy(), expected.numpy()).pvalue > 1e-3
    # and the test has power: equal weights would be rejected outright
    assert chisquare(counts.numpy()).pvalue < 1e-12


def test_uniform_within_triangle():
    # a skewed triangle; uniformity is affine-invariant, so test in barycentric space
    a, b, c = torch.tensor([[0.2, -1.0, 0.5], [2.0, 0.3, -0.4], [0.7, 1.5, 1.0]], dtype=torch.float64)
    mesh = Mesh(torch.stack([a, b, c]), torch.tensor([[0, 1, 2]]))
    n, g = 200_000, 8
    pts = sample_points_on_mesh(mesh, n, _gen(2)).points
    # recover (w1, w2) from the positions: p - a = w1 (b - a) + w2 (c - a)
    basis = torch.stack([b - a, c - a], dim=1)  # (3, 2)
    w = torch.linalg.lstsq(basis, (pts - a).T).solution.T  # (n, 2)
    assert torch.allclose(basis @ w.T, (pts - a).T, atol=1e-10)  # points lie in the plane
    assert bool((w >= -1e-12).all()) and bool((w.sum(-1) <= 1 + 1e-12).all())
    # g^2 congruent sub-triangles of equal area: expected counts equal
    x, y = w[:, 0] * g, w[:, 1] * g
    i, j = x.floor().clamp(max=g - 1), y.floor().clamp(max=g - 1)
    upper = ((x - i) + (y - j)) >= 1
    # cell (i, j) lower exists for i + j <= g - 1, upper for i + j <= g - 2
    cell = ((i * g + j) * 2 + upper.double()).long()
    counts = torch.bincount(cell, minlength=2 * g * g).double()
    ii, jj = torch.meshgrid(torch.arange(g), torch.arange(g), indexing="ij")
    exists = torch.stack([ii + jj <= g - 1, ii + jj <= g - 2], -1).reshape(-1)
    assert float(counts[~exists].sum()) == 0
    assert int(exists.sum()) == g * g
    assert chisquare(counts[exists].numpy()).pvalue > 1e-3
    # moments: the mean is the centroid
    assert torch.allclose(pts.mean(0), (a + b + c) / 3, atol=0.01)


def test_naive_barycentrics_would_fail_uniformity():
    """Sanity check of the test's power: sqrt dropped -> clustering at vertex 0 is detected."""
    r = torch.rand(100_000, 2, generator=_gen(3), dtype=torch.float64)
    naive = torch.stack([r[:, 0] * (1 - r[:, 1]), r[:, 0] * r[:, 1]], -1)
    good = uniform_barycentrics(100_000, _gen(3), dtype=torch.float64)[:, 1:]
    # fraction in the half-area sub-triangle near vertex 0 (w1 + w2 < 1/sqrt(2))
    near0 = lambda w: float(((w.sum(-1)) < 1 / math.sqrt(2)).double().mean())
    assert abs(near0(good) - 0.5) < 0.01
    assert abs(near0(naive) - 0.5) > 0.1


def test_degenerate_faces_get_no_samples():
    mesh = _triangles([1.0, 0.5], degenerate=3)
    w = sampling_weights(mesh)
    assert torch.equal(w[2:], torch.zeros(3, dtype=w.dtype))
    s = sample_surface(mesh, 20_000, _gen(4))
    assert int(s.face_index.max()) <= 1
    assert torch.isfinite(s.points).all()
    pc = sample_points_on_mesh(mesh, 1000, _gen(4), return_normals=True)
    assert torch.isfinite(pc.normals).all()
    assert torch.allclose(pc.normals.norm(dim=-1), torch.ones(1000))


def test_all_degenerate_mesh_is_a_user_error():
    mesh = _triangles([], degenerate=2)
    with pytest.raises(UserError, match="zero area"):
        sample_points_on_mesh(mesh, 10)
    with pytest.raises(UserError):
        sample_points_on_mesh(Mesh(torch.zeros(3, 3), torch.zeros(0, 3, dtype=torch.long)), 10)
    with pytest.raises(UserError):
        sample_points_on_mesh(cube(), -1)


def test_points_on_surface_and_normals():
    mesh = icosphere(2)
    s = sample_surface(mesh, 5000, _gen(5))
    fv = mesh.face_verts()[s.face_index]  # (S, 3, 3)
    assert torch.allclose(s.points, (s.barycentrics[..., None] * fv).sum(1), atol=1e-6)
    assert bool((s.barycentrics >= 0).all())
    assert torch.allclose(s.barycentrics.sum(-1), torch.ones(5000), atol=1e-6)
    pc = sample_points_on_mesh(mesh, 5000, _gen(5), return_normals=True)
    assert torch.equal(pc.points, s.points)
    assert bool(((pc.normals * pc.points).sum(-1) > 0.9).all())  # outward on a unit sphere
    assert pc.colors is None


def test_gradients_wrt_verts():
    mesh = icosphere(1).to(dtype=torch.float64)
    verts = mesh.verts.clone().requires_grad_(True)
    s = sample_surface(mesh.with_verts(verts), 3000, _gen(6))
    weights = torch.randn(3, dtype=torch.float64)
    (s.points * weights).sum().backward()
    # d/dv of sum_s sum_j w_sj v_{f_s j} . weights = (sum of w_sj over uses of v) * weights
    bary_sum = torch.zeros(mesh.num_verts, dtype=torch.float64).index_add_(
        0, mesh.faces[s.face_index].reshape(-1), s.barycentrics.reshape(-1))
    assert torch.isfinite(verts.grad).all()
    assert torch.allclose(verts.grad, bary_sum[:, None] * weights, atol=1e-10)
    assert abs(float(bary_sum.sum()) - 3000) < 1e-8
    # translating all vertices by t moves every sample by t (same faces, barycentrics)
    t = torch.tensor([0.3, -1.0, 2.0], dtype=torch.float64)
    moved = sample_surface(mesh.with_verts(mesh.verts + t), 3000, _gen(6))
    assert torch.equal(moved.face_index, s.face_index)
    assert torch.allclose(moved.points, s.points.detach() + t, atol=1e-12)


def test_gradients_through_degenerate_faces_are_finite():
    mesh = _triangles([1.0], degenerate=1).to(dtype=torch.float64)
    verts = mesh.verts.clone().requires_grad_(True)
    pc = sample_points_on_mesh(mesh.with_verts(verts), 500, _gen(7), return_normals=True)
    (pc.points.sum() + pc.normals.sum()).backward()
    assert torch.isfinite(verts.grad).all()
    assert float(verts.grad[3:].abs().sum()) == 0  # degenerate face: never sampled


def test_reproducible_with_same_generator():
    mesh = icosphere(2)
    a = sample_points_on_mesh(mesh, 1000, _gen(8)).points
    b = sample_points_on_mesh(mesh, 1000, _gen(8)).points
    c = sample_points_on_mesh(mesh, 1000, _gen(9)).points
    assert torch.equal(a, b)
    assert not torch.equal(a, c)


def test_vertex_colors_interpolated():
    mesh = _triangles([1.0])
    mesh = Mesh(mesh.verts, mesh.faces, vert_colors=torch.eye(3))
    s = sample_surface(mesh, 500, _gen(10))
    pc = sample_points_on_mesh(mesh, 500, _gen(10), return_colors=True)
    # vertex j has colour e_j, so the colour equals the barycentric weights
    assert torch.allclose(pc.colors, s.barycentrics, atol=1e-6)
    with pytest.raises(UserError, match="colours"):
        sample_points_on_mesh(_triangles([1.0]), 10, return_colors=True)


def test_texture_colors():
    # texture with red increasing with u (left to right) and green with v (bottom to top)
    ht = wt = 64
    u = (torch.arange(wt) + 0.5) / wt
    v = 1 - (torch.arange(ht) + 0.5) / ht  # top row first
    tex = torch.stack([u[None].expand(ht, wt), v[:, None].expand(ht, wt), torch.zeros(ht, wt)], -1)
    verts = torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]])
    uvs = torch.tensor([[0.2, 0.2], [0.8, 0.2], [0.2, 0.8]])
    mesh = Mesh(verts, torch.tensor([[0, 1, 2]]), verts_uvs=uvs, faces_uvs=torch.tensor([[0, 1, 2]]),
                texture=tex)
    pc = sample_points_on_mesh(mesh, 2000, _gen(11), return_colors=True)
    expected_uv = 0.2 + 0.6 * pc.points[:, :2]  # the UV map is affine in x, y here
    assert torch.allclose(pc.colors[:, :2], expected_uv, atol=1e-5)
