"""Exact point-to-mesh distances, the observed-surface mask and the surface scores built on them."""

import math

import pytest
import torch

from l3d_app.errors import UserError
from l3d_app.geometry import primitives as P
from l3d_app.geometry.cameras import look_at_cameras
from l3d_app.geometry.mesh import Mesh
from l3d_app.geometry.sampling import sample_surface
from l3d_app.geometry.point_mesh_distance import point_mesh_distance, point_triangle_distance
from l3d_app.metrics.observed import observed_mask
from l3d_app.metrics.surface_scores import surface_scores
from l3d_app.render.mesh.rgbd import true_depth_maps


def _naive_point_triangle(p, a, b, c):
    """float64 reference: min of the in-plane projection (when inside) and the 3 segments."""
    def seg(p, u, v):
        d = v - u
        L = (d * d).sum(-1).clamp_min(1e-300)
        t = (((p - u) * d).sum(-1) / L).clamp(0, 1)
        return (p - (u + t[:, None] * d)).norm(dim=-1)
    n = torch.cross(b - a, c - a, dim=-1)
    nn_ = n.norm(dim=-1, keepdim=True)
    unit = n / nn_.clamp_min(1e-300)
    h = ((p - a) * unit).sum(-1)
    q = p - h[:, None] * unit
    # inside test by signs of sub-triangle normals
    s1 = (torch.cross(b - a, q - a, dim=-1) * n).sum(-1)
    s2 = (torch.cross(c - b, q - b, dim=-1) * n).sum(-1)
    s3 = (torch.cross(a - c, q - c, dim=-1) * n).sum(-1)
    inside = (s1 >= 0) & (s2 >= 0) & (s3 >= 0) & (nn_[:, 0] > 1e-12)
    edge = torch.stack([seg(p, a, b), seg(p, b, c), seg(p, c, a)]).amin(0)
    return torch.where(inside, h.abs(), edge)


def test_point_triangle_distance_matches_the_naive_reference_in_float64():
    g = torch.Generator().manual_seed(0)
    a, b, c = (torch.randn(4000, 3, generator=g, dtype=torch.float64) for _ in range(3))
    p = 2 * torch.randn(4000, 3, generator=g, dtype=torch.float64)
    got = point_triangle_distance(p, a, b, c)
    assert torch.allclose(got, _naive_point_triangle(p, a, b, c), atol=1e-12, rtol=1e-10)


def test_point_triangle_distance_is_finite_on_degenerate_triangles():
    p = torch.tensor([[0.3, 1.0, 0.0], [2.0, 0.0, 0.0], [0.0, 0.0, 0.0]], dtype=torch.float64)
    a = torch.zeros(3, 3, dtype=torch.float64)
    b = torch.tensor([[1.0, 0, 0]] * 3, dtype=torch.float64)
    c = torch.tensor([[2.0, 0, 0], [0.0, 0, 0], [0.0, 0, 0]], dtype=torch.float64)   # collinear / repeated
    d = point_triangle_distance(p, a, b, c)
    assert torch.isfinite(d).all()
    assert d.tolist() == pytest.approx([1.0, 1.0, 0.0], abs=1e-12)


def test_point_mesh_distance_equals_brute_force_over_all_faces():
    g = torch.Generator().manual_seed(1)
    mesh = P.icosphere(2, 0.5)
    mesh = Mesh(verts=mesh.verts + 0.03 * torch.randn(mesh.verts.shape, generator=g), faces=mesh.faces)
    pts = torch.cat([torch.randn(300, 3, generator=g) * 0.6, torch.randn(20, 3, generator=g) * 5,
                     sample_surface(mesh, 50, generator=g).points])
    tri = mesh.verts.double()[mesh.faces]
    F = tri.shape[0]
    p = pts.double().repeat_interleave(F, 0)
    t = tri.repeat(pts.shape[0], 1, 1)
    brute = point_triangle_distance(p, t[:, 0], t[:, 1], t[:, 2]).view(-1, F).amin(1)
    res = point_mesh_distance(pts.double(), mesh)
    got = res.distance
    assert torch.allclose(got, brute, atol=1e-12)
    # the reported face and barycentrics give a point at exactly that distance
    closest = torch.einsum("pk,pkc->pc", res.bary, tri[res.face])
    assert torch.allclose((pts.double() - closest).norm(dim=-1), brute, atol=1e-12)
    assert torch.allclose(res.bary.sum(-1), torch.ones_like(brute)) and (res.bary >= -1e-12).all()
    assert got[-50:].max() < 1e-6                       # samples on the surface


def test_point_mesh_distance_of_a_box_is_analytic():
    cube = P.cube(2.0)                                 # [-1, 1]^3
    g = torch.Generator().manual_seed(2)
    pts = torch.rand(2000, 3, generator=g, dtype=torch.float64) * 6 - 3
    q = pts.abs() - 1
    outside = q.clamp_min(0).norm(dim=-1)
    inside = -q.amax(dim=-1)
    expect = torch.where(q.amax(dim=-1) > 0, outside, inside)
    assert torch.allclose(point_mesh_distance(pts, cube).distance, expect, atol=1e-12)
    with pytest.raises(UserError):
        point_mesh_distance(torch.zeros(3, 2), cube)


def _ring_cameras(n=12, elev=40.0):
    return look_at_cameras(4.0, torch.full((n,), elev), torch.arange(n) * 360.0 / n, 40.0, 48)


def test_observed_mask_hides_the_bottom_of_a_box_seen_from_above():
    cube = P.cube(1.0)
    cams = _ring_cameras()
    depth = true_depth_maps(cube, cams, scale=2)
    s = sample_surface(cube, 6000, generator=torch.Generator().manual_seed(3))
    normals = cube.face_normals()[s.face_index]
    seen = observed_mask(s.points, cams, depth, 0.01, normals=normals)
    bottom = normals[:, 1] < -0.9
    assert not seen[bottom].any()
    assert seen[~bottom].float().mean() > 0.99
    # a point inside the box is hidden in every view; a floater in front of it is seen
    probe = torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.9, 0.0]])
    assert observed_mask(probe, cams, depth, 0.01).tolist() == [False, True]


def test_surface_scores_zero_for_the_truth_and_exact_for_an_offset_box():
    cube = P.cube(1.0)
    same = surface_scores(cube, cube, n=3000, threshold=0.01)
    assert same["chamfer"] < 1e-6 and same["f1"] == 1.0
    delta = 0.02
    big = P.cube(1.0 + 2 * delta)
    s = surface_scores(big, cube, n=4000, threshold=0.05)
    # completeness: every point of the true (smaller) box is exactly delta inside the big one;
    # accuracy: delta, plus a little near the big box's edges (sqrt(delta^2 + overhang^2))
    assert s["completeness_distance"] == pytest.approx(delta, abs=1e-6)   # float32 vertices
    assert delta <= s["accuracy_distance"] <= delta * 1.05
    assert s["chamfer"] == pytest.approx(s["accuracy_distance"] + s["completeness_distance"])
    assert s["chamfer_rel_diag"] == pytest.approx(s["chamfer"] / math.sqrt(3.0))
    assert s["f1"] == 1.0


def test_surface_scores_observed_variant_ignores_the_unseen_bottom():
    cube = P.cube(1.0)
    # a "reconstruction" with a wrong bottom: the box extended 0.3 downwards
    guess = P.box((0.0, -0.15, 0.0), (1.0, 1.3, 1.0))
    cams = _ring_cameras()
    s = surface_scores(guess, cube, cameras=cams, depth_maps=true_depth_maps(cube, cams, scale=4),
                       n=6000, threshold=0.05)
    assert s["observed_fraction"] == pytest.approx(5 / 6, abs=0.02)
    assert s["chamfer"] > 0.05                         # the full score sees the wrong bottom
    assert s["chamfer_observed"] < 0.05 * s["chamfer"]  # the seen part is right
    assert s["recall_observed"] == 1.0


def test_cameras_without_depth_maps_is_an_error_metrics_do_not_render():
    import trimesh

    t = trimesh.creation.box((1.0, 1.0, 1.0))
    cube = Mesh(torch.tensor(t.vertices, dtype=torch.float32), torch.tensor(t.faces, dtype=torch.long))
    cams = look_at_cameras(3.0, 30.0, torch.tensor([0.0]), 40.0, 16)
    with pytest.raises(ValueError, match="depth_maps"):
        surface_scores(cube, cube, cameras=cams)
