"""Fast neural SDF pieces: grid Jacobian vs autograd, sphere init with a near-zero grid, the trilinear SDF cache, near-surface sample placement,
the learnable-beta VolSDF density."""

import math
from types import SimpleNamespace

import pytest
import torch

from l3d_app.errors import UserError
from l3d_app.geometry.sdf import Sphere
from l3d_app.losses.eikonal import eikonal_loss, sdf_gradient
from l3d_app.models.encodings import GridEncoding
from l3d_app.models.sdf_grid import SDFGridField, grid_encode_with_jacobian
from l3d_app.render.sdf.densities import LaplaceDensity, volsdf_density
from l3d_app.render.volume.estimators import SDFCacheProposal
from l3d_app.render.sdf.neus import NeuSDensity
from l3d_app.render.sdf.volume import SDFGridCache, render_sdf_rays

D = torch.float64
BOX = ((-1.0, -1.0, -1.0), (1.0, 1.0, 1.0))


def _random_field(**kw) -> SDFGridField:
    torch.manual_seed(0)
    field = SDFGridField(scene_box=BOX, n_levels=4, base_resolution=4, max_resolution=40, log2_hashmap_size=12,
                         hidden=16, n_layers=2, sdf_features=3, color_hidden=8, color_layers=1, **kw).double()
    with torch.no_grad():           # a non-trivial field: random table, grid columns switched on
        field.encoding.table.uniform_(-0.3, 0.3)
        field.layers[0].weight.normal_(0.0, 0.5)
    return field


def test_grid_jacobian_matches_autograd_dense_hashed_and_outside():
    enc = GridEncoding(n_levels=3, n_features=2, base_resolution=3, max_resolution=40, log2_hashmap_size=10,
                       bounds=BOX).double()
    assert bool(enc.hashed.any()) and not bool(enc.hashed.all())
    with torch.no_grad():
        enc.table.uniform_(-1, 1)
    x = torch.rand(120, 3, dtype=D) * 2.4 - 1.2                  # some points outside the box
    value, jac = grid_encode_with_jacobian(enc, x)
    torch.testing.assert_close(value, enc(x), atol=1e-12, rtol=0)
    xr = x.clone().requires_grad_(True)
    ref = torch.stack([torch.autograd.grad(enc(xr)[:, j].sum(), xr)[0] for j in range(enc.out_dim)], dim=1)
    torch.testing.assert_close(jac, ref, atol=1e-9, rtol=1e-9)
    outside = (x.abs() > 1).any(dim=-1)
    assert outside.any() and bool((jac[outside][..., (x[outside].abs() > 1)[:, None, :].expand(-1, enc.out_dim, -1)]
                                   == 0).all())


def test_field_gradient_analytic_equals_autograd():
    field = _random_field()
    x = torch.rand(200, 3, dtype=D) * 1.8 - 0.9
    f, feat, g = field.sdf_features_gradient(x)
    torch.testing.assert_close(f, field.sdf(x))
    # (torch's Softplus is exactly linear beyond beta z > 20, where sigmoid(beta z) = 1 - 2e-9)
    torch.testing.assert_close(g, sdf_gradient(field.sdf, x, create_graph=False), atol=1e-7, rtol=1e-7)
    # the analytic gradient is differentiable w.r.t. the table (eikonal backprop, no double backward)
    (gt,) = torch.autograd.grad(eikonal_loss(g), field.encoding.table)
    assert torch.isfinite(gt).all() and gt.abs().sum() > 0


def test_sphere_init_with_near_zero_grid_and_mlp_only_pretraining():
    torch.manual_seed(0)
    field = SDFGridField(scene_box=BOX, n_levels=4, base_resolution=4, max_resolution=32, log2_hashmap_size=12,
                         radius=0.5)
    table0 = field.encoding.table.detach().clone()
    assert float(table0.abs().max()) <= 1e-4
    x = torch.rand(3000, 3) * 2 - 1
    r = x.norm(dim=-1)
    with torch.no_grad():
        f0 = field.sdf(x)
    assert (f0[r < 0.2] < 0).float().mean() > 0.9 and (f0[r > 0.9] > 0).float().mean() > 0.9
    err = field.pretrain_sphere(BOX, steps=120, n_points=1024, lr=3e-3, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        f1 = field.sdf(x)
    assert err < 0.03 and float((f1 - (r - 0.5)).abs().mean()) < 0.03
    assert torch.equal(field.encoding.table.detach(), table0)            # the grid was not touched
    g = field.sdf_features_gradient(x)[2]
    assert float((g.detach().norm(dim=-1) - 1).abs().mean()) < 0.1


def test_level_mask_switches_off_fine_levels():
    field = _random_field()
    x = torch.rand(50, 3, dtype=D) * 2 - 1
    field.set_active_levels(1)
    assert field.active_levels == 1
    f1 = field.sdf(x)
    with torch.no_grad():                                      # change only the finer levels' rows
        start = int(field.encoding.offsets[1])
        field.encoding.table[start:] += 1.0
    torch.testing.assert_close(field.sdf(x), f1)
    field.set_active_levels(99)
    assert field.active_levels == 4 and not torch.allclose(field.sdf(x), f1)


def test_sdf_cache_is_trilinear_in_the_right_axis_order():
    lin = lambda p: 0.3 * p[..., 0] - 0.7 * p[..., 1] + 0.2 * p[..., 2] + 0.1     # noqa: E731
    cache = SDFGridCache(((-1, -0.5, 0.0), (1.0, 0.5, 2.0)), resolution=9)
    cache.update(lin)
    p = torch.rand(400, 3) * torch.tensor([2.0, 1.0, 2.0]) + torch.tensor([-1.0, -0.5, 0.0])
    torch.testing.assert_close(cache(p), lin(p), atol=1e-5, rtol=0)         # exact for linear fields
    sph = Sphere(0.5)
    cache = SDFGridCache(BOX, resolution=33)
    cache.update(sph)
    q = torch.rand(400, 3) * 2 - 1
    q = q[(q.norm(dim=-1) - 0.5).abs() < 0.3]
    cell = 2.0 / 32
    assert float((cache(q) - sph(q)).abs().max()) < cell ** 2 * 4          # O(h^2) curvature error
    with pytest.raises(ValueError):
        SDFGridCache(BOX, resolution=1)


@pytest.mark.parametrize("density", ["volsdf", "neus"])
def test_cached_coarse_pass_places_fine_samples_at_the_zero_level_set(density):
    sph = Sphere(0.5)
    est = SDFCacheProposal(BOX, n_coarse=96, n_fine=16, resolution=24, padding=1e-4)
    est.update(0, SimpleNamespace(sdf=sph))
    dens = LaplaceDensity(0.002, 500.0, learnable=False, beta_min=0.0) if density == "volsdf" else NeuSDensity(500.0)
    torch.manual_seed(0)
    o = torch.nn.functional.normalize(torch.randn(64, 3), dim=-1) * 2.5
    target = torch.nn.functional.normalize(torch.randn(64, 3), dim=-1) * torch.rand(64, 1) * 0.4   # inside
    d = torch.nn.functional.normalize(target - o, dim=-1)
    colour = lambda p, v: (sph(p), torch.full((p.shape[0], 3), 0.25))  # noqa: E731
    out = render_sdf_rays(colour, o, d, est, dens)
    f_at_samples = sph(o[:, None, :] + out["t"].reshape(64, 16)[..., None] * d[:, None, :])
    # uniform samples would put ~4% of them this close; the cache-guided ones hug the surface
    assert (f_at_samples.abs() < 0.06).float().mean() > 0.9
    assert out["opacity"].min() > 0.98
    b = (o * d).sum(-1)
    ref_t = -b - torch.sqrt(b ** 2 - (o.norm(dim=-1) ** 2 - 0.25))
    err = (out["depth"] - ref_t).abs()                       # grazing rays see a thicker surface
    assert float(err.median()) < 0.01 and float(err.max()) < 0.04
    assert float(out["fine_samples_per_ray"]) == 16.0 and float(out["samples_per_ray"]) == 112.0


def test_laplace_density_learnable_beta_and_tied_alpha():
    dens = LaplaceDensity(0.1, None, learnable=True, beta_min=1e-3)
    assert float(dens.beta.detach()) == pytest.approx(0.1) and float(dens.alpha.detach()) == pytest.approx(10.0)
    sdf = torch.tensor([-1e3, -0.05, 0.0, 0.05, 1e3], dtype=torch.float32)
    sigma = dens(sdf)
    torch.testing.assert_close(sigma, volsdf_density(sdf, 10.0, 0.1))
    (g,) = torch.autograd.grad(sigma.sum(), dens.rho)
    assert torch.isfinite(g)
    with torch.no_grad():
        dens.rho.fill_(-50.0)                                  # beta at its floor: still finite
    sigma = dens(sdf)
    assert torch.isfinite(sigma).all() and float(sigma[0].detach()) == pytest.approx(1e3, rel=1e-4)
    fixed = LaplaceDensity(0.05, 30.0, learnable=False)
    assert len(list(fixed.parameters())) == 0 and float(fixed.alpha) == 30.0
    with pytest.raises(ValueError):
        LaplaceDensity(1e-4, None, beta_min=1e-3)
    assert math.isfinite(float(fixed(sdf).sum()))


def _rays_at_a_ball(n: int, radius: float, seed: int):
    """n rays from random points 2.5 from the origin towards random points of a ball of ``radius``."""
    torch.manual_seed(seed)
    o = torch.nn.functional.normalize(torch.randn(n, 3), dim=-1) * 2.5
    aim = torch.nn.functional.normalize(torch.randn(n, 3), dim=-1) * torch.rand(n, 1) * radius
    return o, torch.nn.functional.normalize(aim - o, dim=-1)


def test_evaluation_renders_skip_the_field_on_rays_that_pass_no_surface():
    """Without gradients, rays whose coarse opacity is below ``skip_opacity`` get no fine sample:
    the image equals the full render (every ray sampled) to within that opacity, the rays that
    miss the sphere cost no field evaluation, and training renders (grad on) never skip."""
    sph = Sphere(0.5)
    dens = LaplaceDensity(0.01, None, learnable=False, beta_min=0.0)
    # aim at points spread over a ball of radius 1.4 about the sphere: some rays hit, some pass by
    o, d = _rays_at_a_ball(200, 1.4, seed=1)
    b = (o * d).sum(-1)
    miss_by = (o.norm(dim=-1) ** 2 - b ** 2).sqrt() - 0.5          # closest approach to the surface
    calls = {"n": 0}

    def colour(p, v):
        calls["n"] += p.shape[0]
        return sph(p), torch.full((p.shape[0], 3), 0.25)

    white = torch.ones(3)
    renders = {}
    for skip in (0.0, 1e-4):
        est = SDFCacheProposal(BOX, n_coarse=96, n_fine=16, resolution=32, skip_opacity=skip, eval_anchor=0)
        est.update(0, SimpleNamespace(sdf=sph))
        calls["n"] = 0
        with torch.no_grad():
            renders[skip] = (render_sdf_rays(colour, o, d, est, dens, background=white), calls["n"])
    (full, n_full), (fast, n_fast) = renders[0.0], renders[1e-4]
    assert n_full == 200 * 16
    far = miss_by > 0.3              # 30 betas (17 widened ones) from the surface: nothing to see
    assert int(far.sum()) > 40 and int((miss_by < 0).sum()) > 40
    assert n_fast <= 16 * int((~far).sum())          # the far rays were not evaluated
    assert float((fast["color"] - full["color"]).abs().max()) < 1e-3
    torch.testing.assert_close(fast["color"][far], white.expand(int(far.sum()), 3))
    assert float(fast["fine_samples_per_ray"]) == pytest.approx(n_fast / 200)
    # with gradients on (training) the same estimator samples every ray
    calls["n"] = 0
    est = SDFCacheProposal(BOX, n_coarse=96, n_fine=16, resolution=32, skip_opacity=1e-4)
    est.update(0, SimpleNamespace(sdf=sph))
    render_sdf_rays(colour, o.requires_grad_(), d, est, dens, background=white)
    assert calls["n"] == 200 * 16
    with pytest.raises(ValueError):
        SDFCacheProposal(BOX, skip_opacity=1.0)


def _grazing_opacity_exact(radius: float, beta: float, miss_by: torch.Tensor) -> torch.Tensor:
    """Opacity of rays along +x passing a sphere's surface at ``miss_by`` (VolSDF, alpha = 1/beta):
    a dense float64 midpoint integral of the density, written here from the paper's formula."""
    t = torch.linspace(-3.0, 3.0, 400001, dtype=D)
    mid, dt = 0.5 * (t[1:] + t[:-1]), t[1:] - t[:-1]
    out = []
    for h in miss_by.tolist():
        s = torch.sqrt(mid ** 2 + (radius + h) ** 2) - radius            # SDF along the ray
        psi = torch.where(s >= 0, 0.5 * torch.exp(-s.clamp_min(0) / beta), 1 - 0.5 * torch.exp(s.clamp_max(0) / beta))
        out.append(1.0 - math.exp(-float((psi / beta * dt).sum())))
    return torch.tensor(out, dtype=D)


@pytest.mark.parametrize("radius", [0.5, 1.0])
@pytest.mark.parametrize("beta", [0.005, 0.02])
def test_grazing_rays_are_as_opaque_as_the_exact_integral(radius, beta):
    """Hard case: rays that pass just outside (or just inside) a sphere. A fine sample in the
    faint tail must not own the rest of the ray: uncapped segments made these rays up to ~0.4
    too opaque (dilated silhouettes, an eroded surface after training)."""
    box = ((-1.5,) * 3, (1.5,) * 3)
    miss_by = torch.tensor([-0.01, 0.0, 0.005, 0.01, 0.015, 0.02, 0.03, 0.05])
    o = torch.stack([torch.full_like(miss_by, -3.0), radius + miss_by, torch.zeros_like(miss_by)], -1)
    d = torch.tensor([[1.0, 0.0, 0.0]]).expand_as(o).contiguous()
    sphere = SimpleNamespace(sdf=lambda p: p.norm(dim=-1) - radius)
    dens = LaplaceDensity(beta_init=beta, alpha=None, learnable=False, beta_min=0.0)
    exact = _grazing_opacity_exact(radius, beta, miss_by.double())

    def opacity(max_segment, perturb):
        est = SDFCacheProposal(box, n_coarse=128, n_fine=16, resolution=64, max_segment=max_segment, eval_anchor=0)
        est.update(0, sphere)
        gen = torch.Generator().manual_seed(0)
        with torch.no_grad():
            out = render_sdf_rays(lambda p, v: (sphere.sdf(p), torch.ones(p.shape[0], 3)), o, d, est, dens,
                                  perturb=perturb, generator=gen)
        return out["opacity"].double()

    for perturb in (False, True):
        err = (opacity(4.0, perturb) - exact).abs()
        assert float(err.max()) < 0.15, (perturb, err)
    if beta < 0.01:                                              # the old, uncapped segments fail this
        assert float((opacity(1e9, False) - exact).max()) > 0.25
    head_on = exact[:2]                                          # rays through the sphere: opaque either way
    assert float(head_on.min()) > 0.99
    with pytest.raises(ValueError):
        SDFCacheProposal(box, max_segment=0.0)


@pytest.mark.parametrize("kw", [{"radius": 0.0}, {"radius": -1.0}])
def test_non_positive_radius_is_a_user_error(kw):
    with pytest.raises(UserError, match="radius > 0"):
        SDFGridField(scene_box=BOX, n_levels=2, base_resolution=4, max_resolution=8, log2_hashmap_size=10, **kw)


def test_evaluation_sample_counts_apply_without_gradients_only():
    """eval_n_coarse / eval_n_fine: a no-grad render places that many samples (and reports them),
    a training render keeps n_coarse / n_fine; with enough of them the evaluation render of an
    analytic sphere comes closer to a dense one than the training counts' does."""
    sph = Sphere(0.5)
    dens = LaplaceDensity(0.005, None, learnable=False, beta_min=0.0)
    o, d = _rays_at_a_ball(300, 0.6, seed=2)
    calls = {"n": 0}

    def colour(p, v):
        calls["n"] += p.shape[0]
        return sph(p), (p * 0.5 + 0.5).clamp(0, 1)           # a colour that varies over the surface

    def render(est, grad):
        est.update(0, SimpleNamespace(sdf=sph), force=True)
        calls["n"] = 0
        with torch.set_grad_enabled(grad):
            out = render_sdf_rays(colour, o, d, est, dens, background=torch.ones(3))
        return out, calls["n"]

    kw = dict(resolution=32, skip_opacity=0.0, eval_anchor=0)
    base, n_base = render(SDFCacheProposal(BOX, n_coarse=64, n_fine=8, **kw), False)
    more, n_more = render(SDFCacheProposal(BOX, n_coarse=64, n_fine=8, eval_n_coarse=128, eval_n_fine=32, **kw), False)
    train, n_train = render(SDFCacheProposal(BOX, n_coarse=64, n_fine=8, eval_n_coarse=128, eval_n_fine=32, **kw), True)
    dense, _ = render(SDFCacheProposal(BOX, n_coarse=512, n_fine=128, **kw), False)
    assert (n_base, n_more, n_train) == (300 * 8, 300 * 32, 300 * 8)
    assert float(more["fine_samples_per_ray"]) == 32 and float(train["fine_samples_per_ray"]) == 8
    err = lambda out: float((out["color"] - dense["color"]).abs().mean())  # noqa: E731
    assert err(more) < 0.5 * err(base)
    with pytest.raises(ValueError, match="eval_n_fine"):
        SDFCacheProposal(BOX, eval_n_fine=1)


def test_sdf_cache_cell_size_is_the_widest_vertex_spacing():
    cache = SDFGridCache(((-1.0, -2.0, 0.0), (1.0, 2.0, 0.5)), resolution=5)
    assert cache.cell_size == pytest.approx(1.0)        # y: 4 / (5 - 1)


def test_cache_refresh_schedule_every():
    """The cache re-reads the field at step 0 and every ``every`` steps (a written-out list, not the rule);
    a bad value is a UserError."""
    sph = Sphere(0.5)
    read = []
    est = SDFCacheProposal(BOX, n_coarse=8, n_fine=2, resolution=4, every=8)
    for step in range(0, 30):
        est.update(step, SimpleNamespace(sdf=lambda p, step=step: (read.append(step), sph(p))[1]))
    assert sorted(set(read)) == [0, 8, 16, 24]
    with pytest.raises(UserError):
        SDFCacheProposal(BOX, every=0)
