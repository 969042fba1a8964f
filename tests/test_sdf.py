"""Analytic SDFs: exact values at known points, kinks with finite gradients, eikonal, union."""

import math

import pytest
import torch

from l3d_app.errors import UserError
from l3d_app.geometry.sdf import Box, Sphere, Superquadric, Torus, Translate, Union

F64 = torch.float64


def grad_of(sdf, points):
    p = points.clone().to(F64).requires_grad_(True)
    (g,) = torch.autograd.grad(sdf(p).sum(), p)
    return g


def test_sphere_values_and_centre_kink():
    s = Sphere(0.5, center=(1.0, 0.0, 0.0))
    p = torch.tensor([[1.0, 0, 0], [2.0, 0, 0], [1.0, 0.5, 0], [1.0, 0, -0.25]], dtype=F64)
    assert torch.allclose(s(p), torch.tensor([-0.5, 0.5, 0.0, -0.25], dtype=F64))
    g = grad_of(s, p)
    assert torch.isfinite(g).all()
    assert torch.allclose(g[1:].norm(dim=-1), torch.ones(3, dtype=F64))


def test_box_exact_values_inside_outside_corner():
    b = Box((2.0, 1.0, 4.0))  # half sizes 1, 0.5, 2
    p = torch.tensor([
        [0.0, 0.0, 0.0],      # centre: nearest face is y at 0.5
        [0.9, 0.0, 0.0],      # inside, near the x face
        [3.0, 0.0, 0.0],      # outside a face
        [2.0, 1.5, 0.0],      # outside an edge: sqrt(1 + 1)
        [2.0, 1.5, 4.0],      # outside a corner: sqrt(1 + 1 + 4)
        [1.0, 0.5, 2.0],      # exactly at a corner
    ], dtype=F64)
    want = torch.tensor([-0.5, -0.1, 2.0, math.sqrt(2), math.sqrt(6), 0.0], dtype=F64)
    assert torch.allclose(b(p), want)
    g = grad_of(b, p)
    assert torch.isfinite(g).all()
    assert torch.allclose(g[[1, 2, 3, 4]].norm(dim=-1), torch.ones(4, dtype=F64))
    assert torch.allclose(g[3], torch.tensor([1.0, 1.0, 0.0], dtype=F64) / math.sqrt(2))


def test_box_is_symmetric_and_centred():
    b = Box((1.0, 2.0, 3.0), center=(0.5, -1.0, 2.0))
    p = torch.randn(100, 3, dtype=F64)
    mirrored = 2 * torch.tensor([0.5, -1.0, 2.0], dtype=F64) - p
    assert torch.allclose(b(p), b(mirrored))
    assert b.bounds() == ((0.0, -2.0, 0.5), (1.0, 0.0, 3.5))


def test_torus_values_and_kinks():
    t = Torus(0.7, 0.3)
    p = torch.tensor([
        [0.7, 0.0, 0.0],      # on the core circle: -r (kink)
        [0.0, 0.0, 0.0],      # the centre, on the axis (kink): R - r
        [0.0, 0.3, -0.7],     # on the top of the tube
        [1.5, 0.0, 0.0],      # outside: 1.5 - 1.0
        [0.0, 2.0, 0.0],      # on the axis above (kink: the whole core circle is nearest)
    ], dtype=F64)
    want = torch.tensor([-0.3, 0.4, 0.0, 0.5, math.sqrt(4.49) - 0.3], dtype=F64)
    assert torch.allclose(t(p), want)
    g = grad_of(t, p)
    assert torch.isfinite(g).all()
    assert torch.allclose(g[2:4].norm(dim=-1), torch.ones(2, dtype=F64))
    assert torch.allclose(g[4], torch.tensor([0.0, 2.0 / math.sqrt(4.49), 0.0], dtype=F64))  # a subgradient


@pytest.mark.parametrize("sdf", [Sphere(0.6, (0.1, 0.2, 0.0)), Box((1.0, 0.6, 0.8), (0.0, 0.1, 0.2)),
                                 Torus(0.6, 0.2, (0.0, 0.1, 0.0)), Translate(Torus(0.5, 0.25), (0.3, 0, 0))])
def test_eikonal_almost_everywhere(sdf):
    p = torch.rand(4000, 3, generator=torch.Generator().manual_seed(0), dtype=F64) * 3 - 1.5
    g = grad_of(sdf, p)
    assert sdf.exact
    assert torch.isfinite(g).all()
    assert torch.allclose(g.norm(dim=-1), torch.ones(len(p), dtype=F64), atol=1e-9)


def test_float32_and_batch_shapes():
    t = Torus(0.7, 0.3)
    p = torch.rand(2, 5, 7, 3)
    d = t(p)
    assert d.shape == (2, 5, 7) and d.dtype == torch.float32
    assert torch.allclose(d.double(), t(p.double()), atol=1e-6)
    with pytest.raises(UserError):
        t(torch.zeros(4, 2))


def test_union_is_min_and_translate_moves():
    a, b = Sphere(0.5), Box((0.5, 0.5, 0.5), center=(1.0, 0.0, 0.0))
    u = Union([a, b])
    p = torch.randn(200, 3, dtype=F64)
    assert torch.equal(u(p), torch.minimum(a(p), b(p)))
    assert u.bounds() == ((-0.5, -0.5, -0.5), (1.25, 0.5, 0.5))
    assert torch.isfinite(grad_of(u, p)).all()
    moved = Translate(a, (1.0, 2.0, 3.0))
    assert torch.allclose(moved(p + torch.tensor([1.0, 2.0, 3.0], dtype=F64)), a(p))
    assert moved.bounds() == ((0.5, 1.5, 2.5), (1.5, 2.5, 3.5))
    assert (a | b)(p).equal(u(p))


def test_superquadric_sign_zero_set_and_sphere_case():
    q = Superquadric((0.8, 0.6, 0.5), (0.3, 1.5))
    p = torch.randn(500, 3, dtype=F64)
    F = q.inside_outside(p)
    d = q(p)
    assert torch.equal(d < 0, F < 1)
    # radial projection onto the surface: F = 1 and d = 0 there
    surf = p / F.pow(0.3 / 2)[:, None]
    assert torch.allclose(q.inside_outside(surf), torch.ones(500, dtype=F64))
    assert q(surf).abs().max() < 1e-12
    # a = b = c, e1 = e2 = 1 is a sphere: the distance is exact
    s = Superquadric((0.7, 0.7, 0.7), (1.0, 1.0))
    assert torch.allclose(s(p), p.norm(dim=-1) - 0.7)


@pytest.mark.parametrize("exponents", [(0.2, 0.2), (1.0, 1.0), (3.0, 3.5)])
def test_superquadric_gradients_finite_on_planes_and_centre(exponents):
    q = Superquadric((0.8, 0.6, 0.5), exponents)
    p = torch.tensor([[0.0, 0, 0], [0.3, 0, 0], [0, 0.2, 0], [0, 0, 0.9], [0.4, 0.0, 0.1], [1e-30, 0, 0]], dtype=F64)
    d = q(p)
    assert torch.isfinite(d).all()
    assert torch.isfinite(grad_of(q, p)).all()
    assert d[0] == pytest.approx(-0.8)   # at the centre: -radius along +X
    assert d[1] == pytest.approx(-0.5)


def test_bad_parameters_are_user_errors():
    with pytest.raises(UserError):
        Sphere(-1.0)
    with pytest.raises(UserError):
        Box((1.0, 0.0, 1.0))
    with pytest.raises(UserError):
        Superquadric(exponents=(0.0, 1.0))
    with pytest.raises(UserError):
        Union([])
