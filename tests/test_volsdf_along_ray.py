"""VolSDF's density of the distance along the ray (``density_along_ray``, render/sdf/densities.py): f / |n . d|
against the analytic distance to a plane, the transmittance at a plane the same at every angle (and not so
without it), a ray passing a sphere that stays clear (and not so without it), its gradient by hand, the hard
cases (zero gradient, a ray along the surface, huge values, bfloat16 autocast), and the config checks."""

import math

import pytest
import torch

from l3d_app.errors import UserError
from l3d_app.render.sdf.densities import LaplaceDensity, distance_along_ray
from l3d_app.render.sdf.volume import sdf_rgb_sigma_fn

BETA = 0.005


def _density(along_ray: bool, floor: float = 0.1) -> LaplaceDensity:
    return LaplaceDensity(BETA, None, learnable=False, beta_min=0.0, along_ray=along_ray, along_ray_floor=floor)


def _ray_tau(field, origin, direction, density, t_far=2.0, n=200001):
    """Per-segment optical depths of one ray through ``field(points) -> (f, grad)`` on n float64 samples,
    through the renderer's own callback (:func:`sdf_rgb_sigma_fn`)."""
    o, d = torch.tensor([origin], dtype=torch.float64), torch.nn.functional.normalize(
        torch.tensor([direction], dtype=torch.float64), dim=-1)
    t = torch.linspace(0.0, t_far, n, dtype=torch.float64)
    t0, t1, rays = t[:-1], t[1:], torch.zeros(n - 1, dtype=torch.long)

    def fn(points, dirs):
        f, g = field(points)
        return f, torch.zeros_like(points), g
    return t0, sdf_rgb_sigma_fn(fn, o, d, density)(t0, t1, rays)["tau"]


def _plane(points):    # the plane z = 0, solid below
    return points[:, 2], torch.tensor([0.0, 0.0, 1.0], dtype=points.dtype).expand_as(points)


def _sphere(radius):
    def field(points):
        r = points.norm(dim=-1, keepdim=True)
        return r[:, 0] - radius, points / r
    return field


@pytest.mark.parametrize("degrees", [0.0, 30.0, 60.0, 80.0])
def test_the_sdf_over_the_slope_is_the_distance_to_a_plane_along_the_ray(degrees):
    """f = z, a ray at ``degrees`` from the normal: f / |n . d| is the distance to z = 0 along it, in float64."""
    a = math.radians(degrees)
    d = torch.tensor([[math.sin(a), 0.0, -math.cos(a)]], dtype=torch.float64).expand(5, 3)
    z = torch.tensor([0.3, 0.01, 0.0, -0.02, -1.0], dtype=torch.float64)
    grad = torch.tensor([[0.0, 0.0, 2.0]], dtype=torch.float64).expand(5, 3)     # |grad f| need not be 1
    got = distance_along_ray(z, grad, d, floor=0.1)
    assert torch.allclose(got, z / math.cos(a), rtol=1e-12, atol=0)


@pytest.mark.parametrize("degrees", [30.0, 60.0, 80.0])
def test_a_plane_seen_at_any_angle_stops_the_ray_where_it_does_head_on(degrees):
    """Optical depth from the ray's start to the plane: alpha beta / 2 = 0.5 head-on (analytic). Along the
    ray it is 0.5 at every angle; reading f itself it grows as 1 / cos (the grazing bias)."""
    a = math.radians(degrees)
    start, direction = [-0.5 * math.tan(a), 0.0, 0.5], [math.sin(a), 0.0, -math.cos(a)]
    hit = 0.5 / math.cos(a)
    for along_ray, want in ((True, 0.5), (False, 0.5 / math.cos(a))):
        t0, tau = _ray_tau(_plane, start, direction, _density(along_ray), t_far=hit + 0.2)
        assert float(tau[t0 < hit].sum()) == pytest.approx(want, rel=2e-3)


def test_a_ray_that_passes_a_sphere_stays_clear_along_the_ray_and_not_otherwise():
    """A ray passing the sphere of radius 0.28 at h = 2 beta: reading f it gathers the analytic optical
    depth exp(-h / beta) sqrt(pi R / (2 beta)) (Laplace's approximation; 1.27: opaque); along the ray
    f / c >= sqrt(2 h R) = 0.075 = 15 beta until c reaches the floor, where f / 0.1 >= 20 beta."""
    radius, h = 0.28, 2 * BETA
    start, direction = [-1.0, radius + h, 0.0], [1.0, 0.0, 0.0]
    _, tau_f = _ray_tau(_sphere(radius), start, direction, _density(False))
    want = math.exp(-h / BETA) * math.sqrt(math.pi * radius / (2 * BETA))
    assert float(tau_f.sum()) == pytest.approx(want, rel=0.05)
    _, tau_ray = _ray_tau(_sphere(radius), start, direction, _density(True))
    assert float(tau_ray.sum()) < 1e-3


def test_the_gradient_flows_into_the_sdf_only():
    """d(f / c) / df = 1 / c (by hand); nothing reaches the gradient (the normal is held fixed)."""
    f = torch.tensor([0.02, -0.01, 0.0], dtype=torch.float64, requires_grad=True)
    g = torch.tensor([[0.0, 0.6, 0.8], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64, requires_grad=True)
    d = torch.tensor([[0.0, 0.0, -1.0], [-0.6, 0.8, 0.0], [0.0, 1.0, 0.0]], dtype=torch.float64)
    out = distance_along_ray(f, g, d, floor=0.1)
    out.sum().backward()
    assert torch.allclose(f.grad, torch.tensor([1 / 0.8, 1 / 0.6, 1 / 0.1], dtype=torch.float64), rtol=1e-12)
    assert g.grad is None or float(g.grad.abs().max()) == 0.0


def test_hard_cases_stay_finite_and_take_the_floor():
    """A zero gradient and a ray along the surface take c = floor; huge SDF values and bfloat16 autocast
    give finite densities with the float32 values (bf16's 3 significant digits)."""
    f = torch.tensor([0.01, 0.01, 1e6, -1e6, 0.0])
    g = torch.tensor([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    d = torch.tensor([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [0.0, 0.0, -1.0], [0.0, 0.0, -1.0], [0.0, 0.0, -1.0]])
    out = distance_along_ray(f, g, d, floor=0.25)
    assert torch.equal(out, torch.tensor([0.04, 0.04, 1e6, -1e6, 0.0]))
    dens = _density(True, floor=0.25)
    sigma = dens(dens.sdf_along_ray(f, g, d))
    assert torch.isfinite(sigma).all()
    assert torch.allclose(sigma, torch.tensor([0.5 * math.exp(-8.0), 0.5 * math.exp(-8.0), 0.0, 1.0, 0.5]) / BETA,
                          rtol=1e-5, atol=0)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        low = dens(dens.sdf_along_ray(f, g.bfloat16(), d.bfloat16()))
    assert torch.isfinite(low).all() and torch.allclose(low.float(), sigma, rtol=2e-2, atol=0)


def test_without_the_gradient_or_with_a_bad_floor_it_says_so():
    with pytest.raises(ValueError, match="gradient"):
        _density(True).sdf_along_ray(torch.zeros(2), None, torch.zeros(2, 3))
    assert torch.equal(_density(False).sdf_along_ray(torch.ones(2), None, torch.zeros(2, 3)), torch.ones(2))
    for floor in (0.0, 1.5):
        with pytest.raises(ValueError, match="along_ray_floor"):
            _density(True, floor)


def test_the_task_refuses_a_field_without_an_exact_gradient(compose, tmp_path):
    from l3d_app.app import run_task
    cfg = compose("task=volsdf", "density=volsdf", "model=sdf_field", "density_along_ray=true", "iters=1",
                  f"data.cache_dir={tmp_path / 'cache'}")
    with pytest.raises(UserError, match="density_along_ray needs a field with an exact gradient"):
        run_task(cfg, out_dir=tmp_path / "run")
    assert not (tmp_path / "run" / "metrics.json").exists()
