"""Sphere tracing vs analytic ray-sphere / ray-box intersections; misses, grazing, inside."""

import math

import pytest
import torch

from l3d_app.errors import UserError
from l3d_app.geometry.sdf import Box, Sphere, Torus, Union
from l3d_app.render.sdf.sphere_tracing import render_sdf_shaded, sdf_normals, sphere_trace, sphere_trace_box


def _ray_sphere(o, d, c, r):
    """Analytic first positive hit distance (nan for a miss) of unit rays with a sphere (float64)."""
    oc = o - torch.as_tensor(c, dtype=o.dtype)
    b = (oc * d).sum(-1)
    disc = b * b - ((oc * oc).sum(-1) - r * r)
    t = -b - disc.clamp_min(0).sqrt()
    return torch.where(disc >= 0, t, torch.full_like(t, float("nan")))


def _random_rays(n, seed, dtype=torch.float64):
    g = torch.Generator().manual_seed(seed)
    o = torch.randn(n, 3, generator=g, dtype=dtype)
    o = 3.0 * o / o.norm(dim=-1, keepdim=True)
    target = 1.2 * (torch.rand(n, 3, generator=g, dtype=dtype) - 0.5) * 2
    d = target - o
    return o, d / d.norm(dim=-1, keepdim=True)


def test_sphere_hits_and_misses_match_the_analytic_intersection():
    sph = Sphere(0.8, center=(0.1, -0.2, 0.05))
    o, d = _random_rays(4000, 0)
    ref = _ray_sphere(o, d, sph.center, sph.radius)
    res = sphere_trace(sph, o, d, far=10.0, max_iters=400, eps=1e-7)
    analytic_hit = torch.isfinite(ref)
    # rays very close to tangent may go either way: exclude a thin band
    oc = o - torch.tensor(sph.center, dtype=o.dtype)
    b = (oc * d).sum(-1)
    miss_dist = ((oc * oc).sum(-1) - b * b).clamp_min(0).sqrt()
    clear = (miss_dist - sph.radius).abs() > 1e-3
    assert analytic_hit[clear].any() and (~analytic_hit[clear]).any()
    assert torch.equal(res.hit[clear], analytic_hit[clear])
    ok = clear & analytic_hit
    torch.testing.assert_close(res.t[ok], ref[ok], atol=2e-4, rtol=0)
    torch.testing.assert_close(res.points[ok], o[ok] + ref[ok, None] * d[ok], atol=2e-4, rtol=0)
    assert not res.inside.any()
    assert (res.t[clear & ~analytic_hit] == 10.0).all()     # misses end at far


def test_box_hits_match_the_slab_intersection():
    box = Box((0.6, 1.0, 0.4), center=(0.0, 0.1, -0.1))
    o, d = _random_rays(3000, 1)
    lo = torch.tensor(box.center, dtype=o.dtype) - torch.tensor(box.size, dtype=o.dtype) / 2
    hi = lo + torch.tensor(box.size, dtype=o.dtype)
    t0, t1 = (lo - o) / d, (hi - o) / d
    near = torch.minimum(t0, t1).max(-1).values
    far = torch.maximum(t0, t1).min(-1).values
    hit = (far > near) & (far > 0)
    robust = hit & (far - near > 1e-2) | ~hit & (near - far > 1e-2)   # not within 1e-2 of an edge
    res = sphere_trace(box, o, d, far=10.0, max_iters=2000, eps=1e-7)
    assert hit[robust].any() and (~hit[robust]).any()
    assert torch.equal(res.hit[robust], hit[robust])
    torch.testing.assert_close(res.t[robust & hit], near[robust & hit], atol=1e-4, rtol=0)


def test_grazing_rays():
    sph = Sphere(1.0)
    z = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    offsets = torch.tensor([1.0 + 1e-3, 1.0 + 1e-6, 1.0, 1.0 - 1e-3], dtype=torch.float64)
    o = torch.stack([torch.zeros_like(offsets), offsets, torch.full_like(offsets, -3.0)], -1)
    d = z.expand_as(o)
    res = sphere_trace(sph, o, d, far=8.0, max_iters=2000, eps=1e-5)
    # a ray passing within eps of the surface (1e-6 < eps) counts as touching it
    assert res.hit.tolist() == [False, True, True, True]
    assert abs(float(sph(res.points[1:2])[0])) < 1e-5
    # tangent: the hit is the tangent point (within sqrt(2 r eps) along the ray)
    assert abs(float(res.t[2]) - 3.0) < math.sqrt(2 * 1e-5) + 1e-6
    # just inside the silhouette: analytic t, tolerance eps / |cos(incidence)|
    ref = 3.0 - math.sqrt(1.0 - (1 - 1e-3) ** 2)
    cos = math.sqrt(1.0 - (1 - 1e-3) ** 2)
    assert abs(float(res.t[3]) - ref) <= 1e-5 / cos + 1e-9
    # a run out of iterations before converging on a grazing ray is a miss, not a false hit
    few = sphere_trace(sph, o[2:3], d[2:3], far=8.0, max_iters=20, eps=1e-9)
    assert not bool(few.hit[0])


def test_rays_starting_inside_report_a_hit_at_near_marked_inside():
    sph = Sphere(1.0)
    o = torch.tensor([[0.0, 0.0, 0.0], [0.5, 0.0, 0.0], [0.0, 0.0, -3.0]])
    d = torch.tensor([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    res = sphere_trace(sph, o, d, near=torch.tensor([0.0, 0.2, 0.0]), far=10.0)
    assert res.inside.tolist() == [True, True, False]
    assert res.hit.all()
    assert res.t.tolist()[:2] == [0.0, pytest.approx(0.2)]
    assert res.iterations[:2].tolist() == [1, 1]
    # tracing the negated SDF from there finds the exit
    exit_ = sphere_trace(lambda p: -sph(p), o[:1], d[:1], far=10.0, eps=1e-6)
    assert abs(float(exit_.t[0]) - 1.0) < 1e-5


def test_union_torus_and_box_bounded_tracing_land_on_the_surface():
    scene = Union([Sphere(0.3, center=(-0.5, 0, 0)), Torus(0.4, 0.1, center=(0.4, 0, 0))])
    o, d = _random_rays(2000, 2, dtype=torch.float32)
    res = sphere_trace_box(scene, o, d, ((-1, -1, -1), (1, 1, 1)), max_iters=300, eps=1e-5)
    assert res.hit.sum() > 100
    assert scene(res.points[res.hit]).abs().max() < 1e-4
    # misses of the box are misses with t = 0
    far_away = sphere_trace_box(scene, torch.tensor([[5.0, 5.0, 5.0]]), torch.tensor([[1.0, 0.0, 0.0]]),
                                ((-1, -1, -1), (1, 1, 1)))
    assert not bool(far_away.hit[0]) and float(far_away.t[0]) == 0.0
    n = sdf_normals(scene, res.points[res.hit])
    assert torch.isfinite(n).all() and torch.allclose(n.norm(dim=-1), torch.ones(n.shape[0]), atol=1e-4)


def test_shaded_render_and_input_checks():
    o, d = _random_rays(64, 3, dtype=torch.float32)
    img = render_sdf_shaded(Sphere(0.5), o, d, ((-1, -1, -1), (1, 1, 1)))
    assert img.shape == (64, 3) and torch.isfinite(img).all() and (img < 1).any() and (img == 1).any()
    with pytest.raises(UserError):
        sphere_trace(Sphere(1.0), o, d[:3])
    with pytest.raises(UserError):
        sphere_trace(Sphere(1.0), o, d, eps=0.0)
