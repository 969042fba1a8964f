"""Volume rendering core: compositing, samplers, ray-box bounds, Laplace CDF (float64 references)."""

import math

import pytest
import torch

from l3d_app.geometry.cameras import look_at_cameras
from l3d_app.render.sdf.densities import laplace_cdf, volsdf_density
from l3d_app.render.volume.samplers import (bin_edges, importance_samples, ray_aabb, sample_pdf,
                                     stratified_samples)
from l3d_app.render.volume.renderer import VolumeRenderer, composite, render_rays_chunked, sample_deltas

D = torch.float64


# ------------------------------------------------------------------ transmittance
def test_four_segment_transmittance():
    """The course's transmittance exercise, to float64 precision.

    A ray leaves x, crosses empty space to y1, then density 1 over [y1, y2] (length 2),
    density 0.5 over [y2, y3] (length 1) and density 10 over [y3, y4] (length 3).
    The four quantities are transmittances between pairs of points::

        T(y1, y2) = e^-2                      (1 * 2)
        T(y2, y4) = e^-(0.5 * 1 + 10 * 3) = e^-30.5
        T(x,  y4) = e^-(2 + 0.5 + 30)     = e^-32.5
        T(x,  y3) = e^-(2 + 0.5)          = e^-2.5

    One sample per segment start (segment i = [t_i, t_i + delta_i)); ``transmittance[i]``
    is T(x, t_i), so T(a, b) = T(x, b) / T(x, a), and a ray starting at y2 gives
    T(y2, y4) directly.
    """
    empty = 1.7
    t = torch.tensor([[0.0, empty, empty + 2, empty + 3, empty + 6]], dtype=D)  # x, y1..y4
    sig = torch.tensor([[0.0, 1.0, 0.5, 10.0, 0.0]], dtype=D)
    out = composite(torch.zeros(1, 5, 3, dtype=D), t, sigmas=sig)
    T = out["transmittance"][0]
    got = {"T(y1,y2)": T[2] / T[1], "T(y2,y4)": T[4] / T[2], "T(x,y4)": T[4], "T(x,y3)": T[3]}
    want = {"T(y1,y2)": -2.0, "T(y2,y4)": -30.5, "T(x,y4)": -32.5, "T(x,y3)": -2.5}
    for k, logv in want.items():
        assert float(got[k]) == pytest.approx(math.exp(logv), rel=1e-12, abs=0.0), k
    # the ray from y2: samples y2, y3, y4
    sub = composite(torch.zeros(1, 3, 3, dtype=D), t[:, 2:] - t[:, 2:3], sigmas=sig[:, 2:])
    assert float(sub["transmittance"][0, 2]) == pytest.approx(math.exp(-30.5), rel=1e-12, abs=0.0)
    # alpha mode with the same segments' opacities gives the same transmittances, except
    # that 1 - alpha for the tau = 30 segment (alpha = 1 - 9e-14) only keeps ~3 digits once
    # alpha is rounded to float64: opacities near 1 lose information that densities keep.
    alphas = -torch.expm1(-sig * sample_deltas(t))
    alpha_out = composite(torch.zeros(1, 5, 3, dtype=D), t, alphas=alphas)
    torch.testing.assert_close(alpha_out["transmittance"][:, :4], out["transmittance"][:, :4],
                               rtol=1e-12, atol=0)
    torch.testing.assert_close(alpha_out["transmittance"][:, 4], out["transmittance"][:, 4],
                               rtol=1e-3, atol=0)


def test_huge_density_and_delta_are_finite_with_finite_gradients():
    t = torch.tensor([[0.0, 1.0, 2.0, 1e10], [0.0, 1e10, 2e10, 3e10]], dtype=D)
    sig = torch.tensor([[0.0, 1e10, 1.0, 1e10], [1e10, 1e10, 0.0, 1.0]], dtype=D, requires_grad=True)
    col = torch.rand(2, 4, 3, dtype=D, requires_grad=True)
    deltas = torch.tensor([[1.0, 1e10, 1.0, 1e10]] * 2, dtype=D)
    for kw in ({}, {"deltas": deltas}):
        out = composite(col, t, sigmas=sig, background=1.0, **kw)
        for v in out.values():
            assert torch.isfinite(v).all()
        (out["color"].sum() + out["depth"].sum() + out["opacity"].sum()).backward()
        assert torch.isfinite(sig.grad).all() and torch.isfinite(col.grad).all()
        # the first opaque segment takes all the weight
        torch.testing.assert_close(out["weights"][0], torch.tensor([0.0, 1.0, 0.0, 0.0], dtype=D))
        torch.testing.assert_close(out["weights"][1], torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=D))
        sig.grad = col.grad = None


def test_alpha_mode_fully_opaque_has_finite_gradients():
    alphas = torch.tensor([[0.0, 1.0, 1.0, 0.3]], dtype=D, requires_grad=True)
    t = torch.arange(4, dtype=D)[None]
    out = composite(torch.ones(1, 4, 3, dtype=D), t, alphas=alphas, background=0.5)
    out["color"].sum().backward()
    assert torch.isfinite(alphas.grad).all()
    assert float(out["weights"][0, 1].detach()) == 1.0 and float(out["depth"][0].detach()) == pytest.approx(1.0)
    assert float(out["weights"][0, 2:].sum().detach()) < 1e-15


def test_weights_sum_to_opacity_at_most_one_and_background():
    g = torch.Generator().manual_seed(0)
    t = torch.sort(torch.rand(64, 32, generator=g, dtype=D) * 4, dim=-1).values
    sig = torch.rand(64, 32, generator=g, dtype=D) * torch.logspace(-3, 2, 64, dtype=D)[:, None]
    col = torch.rand(64, 32, 3, generator=g, dtype=D)
    out = composite(col, t, sigmas=sig, deltas=sample_deltas(t, last_delta=0.1))
    torch.testing.assert_close(out["weights"].sum(-1), out["opacity"], rtol=1e-12, atol=1e-14)
    assert (out["opacity"] <= 1).all() and (out["opacity"] >= 0).all()
    assert out["opacity"].min() < 0.1 and out["opacity"].max() > 0.99   # the range is exercised
    bg = torch.tensor([0.2, 0.4, 0.6], dtype=D)
    white = composite(col, t, sigmas=sig, deltas=sample_deltas(t, 0.1), background=bg)
    torch.testing.assert_close(white["color"], out["color"] + (1 - out["opacity"])[:, None] * bg)


def test_reference_against_naive_product():
    g = torch.Generator().manual_seed(1)
    t = torch.sort(torch.rand(8, 16, generator=g, dtype=D), dim=-1).values
    sig = torch.rand(8, 16, generator=g, dtype=D) * 5
    col = torch.rand(8, 16, 3, generator=g, dtype=D)
    delta = sample_deltas(t)
    out = composite(col, t, sigmas=sig)
    a = 1 - torch.exp(-sig * delta)
    T = torch.ones(8, dtype=D)
    color = torch.zeros(8, 3, dtype=D)
    for i in range(16):
        color = color + (T * a[:, i])[:, None] * col[:, i]
        T = T * (1 - a[:, i])
    torch.testing.assert_close(out["color"], color, rtol=1e-12, atol=1e-14)


def test_depth_of_opaque_slab_is_entry_distance():
    t = torch.linspace(0, 10, 101, dtype=D)[None]
    sig = torch.where(t >= 3.0 - 1e-9, 1e10, 0.0)
    out = composite(torch.ones(1, 101, 1, dtype=D), t, sigmas=sig)
    assert float(out["depth"][0]) == pytest.approx(3.0, rel=1e-12)
    assert float(out["opacity"][0]) == pytest.approx(1.0, rel=1e-12)


def test_composite_needs_one_of_sigmas_or_alphas():
    t = torch.zeros(1, 2)
    with pytest.raises(ValueError):
        composite(torch.zeros(1, 2, 3), t)
    with pytest.raises(ValueError):
        composite(torch.zeros(1, 2, 3), t, sigmas=t, alphas=t)


# ------------------------------------------------------------------ samplers
def test_stratified_samples_inside_bins_and_sorted():
    near = torch.tensor([0.0, 1.0, 2.0], dtype=D)
    far = torch.tensor([1.0, 5.0, 2.5], dtype=D)
    base = stratified_samples(near, far, 16, dtype=D)
    torch.testing.assert_close(base[1], torch.linspace(1, 5, 16, dtype=D))   # linspace, ends included
    g = torch.Generator().manual_seed(0)
    t = stratified_samples(near, far, 16, perturb=True, generator=g)
    edges = bin_edges(base)
    assert ((t >= edges[:, :-1]) & (t <= edges[:, 1:])).all()
    assert (t[:, 1:] >= t[:, :-1]).all() and not torch.equal(t, base)
    g2 = torch.Generator().manual_seed(0)
    torch.testing.assert_close(stratified_samples(near, far, 16, perturb=True, generator=g2), t)
    assert stratified_samples(0.0, 5.0, 64, n_rays=7).shape == (7, 64)


def test_importance_sampling_concentrates_and_sorts():
    t = torch.linspace(0, 4, 33, dtype=D)[None].expand(5, -1).contiguous()
    w = torch.full((5, 33), 1e-3, dtype=D)
    w[:, 20] = 1.0  # bin of t = 2.5: [2.4375, 2.5625]
    for perturb in (False, True):
        g = torch.Generator().manual_seed(0)
        fine = sample_pdf(bin_edges(t), w, 64, perturb=perturb, generator=g)
        inside = ((fine >= 2.4375) & (fine <= 2.5625)).double().mean()
        assert inside > 0.8
        merged = importance_samples(t, w, 64, perturb=perturb, generator=g)
        assert merged.shape == (5, 97) and (merged[:, 1:] >= merged[:, :-1]).all()
    a = importance_samples(t, w, 64)
    torch.testing.assert_close(a, importance_samples(t, w, 64))   # deterministic
    zero = sample_pdf(bin_edges(t), torch.zeros_like(w), 16)      # all-zero weights: uniform, finite
    assert torch.isfinite(zero).all() and zero.min() >= 0 and zero.max() <= 4


# ------------------------------------------------------------------ ray / box
def test_ray_aabb_known_rays():
    bmin, bmax = (-1.0, -1.0, -1.0), (1.0, 2.0, 3.0)
    rays = [  # origin, direction, hit, near, far (analytic)
        ((-5.0, 0, 0), (1.0, 0, 0), True, 4.0, 6.0),      # axis-parallel through the box
        ((-5.0, 5, 0), (1.0, 0, 0), False, 0.0, 0.0),     # parallel to x, above the box
        ((0.0, 0, 0), (0.0, 0, 1), True, 0.0, 3.0),       # starts inside, going +z
        ((0.0, 0, 10), (0.0, 0, 1), False, 0.0, 0.0),     # box behind the ray
        ((-3.0, -3, 0), (1.0, 1, 0), True, 2.0, 4.0),     # diagonal, zero z component
        ((0.0, 0, 0), (0.0, 0, 0), False, 0.0, 0.0),      # zero direction
        ((-5.0, 1, 0), (1.0, 0.25, 0), False, 0.0, 0.0),  # touches the edge x=-1, y=2 only
        ((-5.0, 0, 0), (1.0, 0.4, 0), True, 4.0, 5.0),    # enters by x=-1, leaves by y=2
        ((-5.0, 0, 0), (-1.0, 0, 0), False, 0.0, 0.0),    # pointing away
    ]
    o = torch.tensor([r[0] for r in rays], dtype=D)
    d = torch.tensor([r[1] for r in rays], dtype=D)
    near, far, hit = ray_aabb(o, d, bmin, bmax)
    assert hit.tolist() == [r[2] for r in rays]
    torch.testing.assert_close(near, torch.tensor([r[3] for r in rays], dtype=D))
    torch.testing.assert_close(far, torch.tensor([r[4] for r in rays], dtype=D))
    near2, far2, _ = ray_aabb(o, d, bmin, bmax, min_t=0.5)       # rays starting at t = 0.5
    assert float(near2[2]) == 0.5 and float(far2[1]) == 0.5 and float(near2[0]) == 4.0


def test_ray_aabb_grazing_and_oblique():
    o = torch.tensor([[-5.0, 0.0, 0.0], [-5.0, 1.0, 0.5]], dtype=D)
    d = torch.nn.functional.normalize(torch.tensor([[1.0, 0.1, 0.0], [1.0, 0.0, 0.0]], dtype=D), dim=-1)
    near, far, hit = ray_aabb(o, d, (-1.0, -1.0, -1.0), (1.0, 1.0, 1.0))
    # ray 0: x in [-1, 1] for s in [4, 6] (s = x param), y = 0.1 s in [0.4, 0.6]: inside
    scale = math.sqrt(1 + 0.01)
    torch.testing.assert_close(near[0], torch.tensor(4 * scale, dtype=D))
    torch.testing.assert_close(far[0], torch.tensor(6 * scale, dtype=D))
    # ray 1 runs along the face y = 1 (origin on the slab boundary): a hit, boundary included
    assert hit.tolist() == [True, True]
    torch.testing.assert_close(far[1] - near[1], torch.tensor(2.0, dtype=D))


# ------------------------------------------------------------------ Laplace CDF
def test_laplace_cdf_extreme_float64():
    beta = 1e-4
    x = torch.tensor([-1e3, -1.0, -1e-3, -1e-4, -1e-6, 0.0, 1e-6, 1e-4, 1e-3, 1.0, 1e3], dtype=D,
                     requires_grad=True)
    y = laplace_cdf(x, beta)
    ref = [0.5 * math.exp(v / beta) if v <= 0 else 1 - 0.5 * math.exp(-v / beta) for v in x.tolist()]
    torch.testing.assert_close(y, torch.tensor(ref, dtype=D), rtol=1e-14, atol=1e-300)
    y.sum().backward()
    dref = torch.tensor([0.5 * math.exp(-abs(v) / beta) / beta for v in x.tolist()], dtype=D)
    assert torch.isfinite(x.grad).all()
    torch.testing.assert_close(x.grad, dref, rtol=1e-12, atol=1e-300)
    assert float(x.grad[5]) == pytest.approx(0.5 / beta)   # derivative at 0 from both sides
    # small-side values are resolved relative to themselves (no 1 - (1 - tiny) cancellation)
    assert float(y[4].detach()) == pytest.approx(0.5 * math.exp(-1e-2), rel=1e-14)
    beta_t = torch.tensor(0.05, dtype=D, requires_grad=True)
    volsdf_density(torch.tensor([-1e3, 0.0, 1e3], dtype=D), 2.0, beta_t).sum().backward()
    assert torch.isfinite(beta_t.grad)


# ------------------------------------------------------------------ chunking / renderer
def test_render_rays_chunked_matches_unchunked():
    o = torch.randn(3, 5, 7, 3)
    d = torch.randn(3, 5, 7, 3)
    fn = lambda a, b: {"x": (a * b).sum(-1), "y": torch.cat([a, b], -1)}  # noqa: E731
    full = fn(o.reshape(-1, 3), d.reshape(-1, 3))
    out = render_rays_chunked(fn, o, d, chunk=8)
    assert out["x"].shape == (3, 5, 7) and out["y"].shape == (3, 5, 7, 6)
    torch.testing.assert_close(out["x"].reshape(-1), full["x"])


def test_volume_renderer_sphere_depth_and_background():
    cams = look_at_cameras(3.0, 0.0, 0.0, 40.0, 16).to(dtype=D)

    def field(p, d):
        sigma = torch.where(p.norm(dim=-1) < 1.0, 1e4, 0.0).to(p.dtype)
        return sigma, torch.ones_like(p) * torch.tensor([1.0, 0.0, 0.0], dtype=p.dtype)

    r = VolumeRenderer(n_samples=401, near=1.0, far=5.0, chunk=50, background=(0.0, 0.0, 1.0))
    out = r(field, cams)
    assert out["image"].shape == (1, 16, 16, 3) and out["depth"].shape == (1, 16, 16)
    centre = out["depth"][0, 7:9, 7:9]
    assert torch.allclose(centre, torch.full_like(centre, 2.0), atol=0.02)   # sphere front at t = 2
    torch.testing.assert_close(out["image"][0, 0, 0], torch.tensor([0.0, 0.0, 1.0], dtype=D))
    torch.testing.assert_close(out["image"][0, 8, 8], torch.tensor([1.0, 0.0, 0.0], dtype=D))


# ------------------------------------------------- the one rendering function vs a naive per-ray loop
def _naive_render(t0, t1, rays, n_rays, sigma, rgb, background, alpha_mode=False):
    """Float64 reference: front-to-back product per ray, one Python loop (the test's own code)."""
    out_c, out_d, out_o = [], [], []
    for r in range(n_rays):
        trans, c, dep = torch.ones((), dtype=D), torch.zeros(3, dtype=D), torch.zeros((), dtype=D)
        for i in (rays == r).nonzero().flatten().tolist():
            a = sigma[i] if alpha_mode else 1.0 - torch.exp(-sigma[i] * (t1[i] - t0[i]))
            c = c + trans * a * rgb[i]
            dep = dep + trans * a * t0[i]
            trans = trans * (1.0 - a)
        out_c.append(c + trans * background)
        out_d.append(dep)
        out_o.append(1.0 - trans)
    return torch.stack(out_c), torch.stack(out_d), torch.stack(out_o)


class _Blob(torch.nn.Module):
    """A Gaussian density blob (float64) with a learnable scale, colour sigmoid(3 p)."""

    def __init__(self):
        super().__init__()
        self.scale = torch.nn.Parameter(torch.tensor(8.0, dtype=D))
        self.c = torch.tensor([0.1, -0.2, 0.05], dtype=D)

    def density(self, p):
        return self.scale * torch.exp(-((p - self.c) ** 2).sum(-1) / 0.18)

    def forward(self, p, d):
        return self.density(p), torch.sigmoid(3 * p)


def _blob_rays(n=24):
    g = torch.Generator().manual_seed(3)
    o = torch.nn.functional.normalize(torch.randn(n, 3, generator=g, dtype=D), dim=-1) * 2.5
    target = (torch.rand(n, 3, generator=g, dtype=D) - 0.5) * 1.2
    d = torch.nn.functional.normalize(target - o, dim=-1)
    d[0] = torch.nn.functional.normalize(torch.tensor([1.0, 0.0, 0.0], dtype=D) - o[0], dim=-1) * -1  # a miss
    return o, d


@pytest.mark.parametrize("kind", ["stratified", "occupancy"])
def test_render_rays_matches_a_naive_float64_loop_in_values_and_gradients(kind):
    from l3d_app.render.volume.estimators import OccupancyEstimator, StratifiedEstimator
    from l3d_app.render.volume.rendering import radiance_fn, render_rays

    box = ((-1.0,) * 3, (1.0,) * 3)
    o, d = _blob_rays()
    field = _Blob()
    if kind == "stratified":
        est = StratifiedEstimator(32, scene_box=box)
    else:
        est = OccupancyEstimator(box, n_samples=32, resolution=8)
        centres = est.grid.cell_centers().double()
        est.grid.mask.copy_((centres - field.c).norm(dim=-1) < 0.6)     # part of the grid empty
        assert 0.05 < est.grid.occupied_fraction < 0.5
    t0, t1, rays = est.sampling(o, d, perturb=True, generator=torch.Generator().manual_seed(0))
    assert bool((rays[1:] >= rays[:-1]).all()) and bool((t1 >= t0).all())
    bg = torch.tensor([0.2, 0.5, 1.0], dtype=D)
    out = render_rays(t0, t1, rays, o.shape[0], radiance_fn(field, o, d), background=bg)
    (g,) = torch.autograd.grad(out["color"].sum() + out["depth"].sum(), field.scale)
    pts = o[rays] + t0[:, None] * d[rays]
    sigma, rgb = field(pts, d[rays])
    ref_c, ref_d, ref_o = _naive_render(t0, t1, rays, o.shape[0], sigma, rgb, bg)
    (ref_g,) = torch.autograd.grad(ref_c.sum() + ref_d.sum(), field.scale)
    torch.testing.assert_close(out["color"], ref_c, atol=1e-12, rtol=1e-10)
    torch.testing.assert_close(out["depth"], ref_d, atol=1e-12, rtol=1e-10)
    torch.testing.assert_close(out["opacity"], ref_o, atol=1e-12, rtol=1e-10)
    torch.testing.assert_close(g, ref_g, atol=1e-10, rtol=1e-9)
    assert float(out["opacity"].detach().max()) > 0.5 and float(out["opacity"][0].detach()) == 0.0   # the blob is seen; a miss
    assert (rays == 0).sum() == 0                                                  # no samples for the miss
    if kind == "occupancy":
        dense = StratifiedEstimator(32, scene_box=box).sampling(o, d, perturb=True,
                                                                 generator=torch.Generator().manual_seed(0))
        assert t0.numel() < 0.7 * dense[0].numel()                       # the grid skipped samples


def test_render_rays_alpha_and_tau_modes_match_the_naive_loop():
    from l3d_app.render.volume.estimators import StratifiedEstimator
    from l3d_app.render.volume.rendering import points_of, render_rays

    o, d = _blob_rays(8)
    t0, t1, rays = StratifiedEstimator(16, near=0.5, far=4.5).sampling(o, d)
    field = _Blob()
    bg = torch.zeros(3, dtype=D)

    def alpha_fn(a, b, r):
        s, rgb = field(points_of(o, d, a, r)[0], None)
        return {"rgb": rgb, "alpha": 1.0 - torch.exp(-s), "extra": s}

    out = render_rays(t0, t1, rays, 8, alpha_fn, background=bg)
    s, rgb = field(points_of(o, d, t0, rays)[0], None)
    ref_c, ref_d, _ = _naive_render(t0, t1, rays, 8, 1.0 - torch.exp(-s), rgb, bg, alpha_mode=True)
    torch.testing.assert_close(out["color"], ref_c, atol=1e-12, rtol=1e-10)
    torch.testing.assert_close(out["aux"]["extra"], s)
    tau_out = render_rays(t0, t1, rays, 8, lambda a, b, r: {"rgb": rgb, "tau": s * (b - a)}, background=bg)
    sig_out = render_rays(t0, t1, rays, 8, lambda a, b, r: (rgb, s), background=bg)
    torch.testing.assert_close(tau_out["color"], sig_out["color"], atol=0, rtol=0)
    with pytest.raises(ValueError):
        render_rays(t0, t1, rays, 8, lambda a, b, r: {"rgb": rgb, "tau": s, "alpha": s})


def test_render_rays_with_no_sample_in_the_whole_chunk_gives_the_background():
    """An evaluation chunk of rays that all miss the box (or all fall in empty grid cells) has N = 0
    samples; it must composite to the background with opacity 0 (it crashed on the `around` scene at
    256 px, where a whole chunk of corner pixels missed the box)."""
    from l3d_app.render.volume.estimators import OccupancyEstimator
    from l3d_app.render.volume.rendering import radiance_fn, render_rays

    est = OccupancyEstimator(((-1.0,) * 3, (1.0,) * 3), n_samples=16, resolution=8)
    o = torch.tensor([[5.0, 5.0, 5.0], [5.0, -5.0, 5.0]], dtype=D)
    d = torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]], dtype=D)        # pointing away from the box
    t0, t1, rays = est.sampling(o, d)
    assert t0.numel() == 0
    field = _Blob()
    bg = torch.tensor([0.2, 0.5, 1.0], dtype=D)
    out = render_rays(t0, t1, rays, 2, radiance_fn(field, o, d), background=bg)
    torch.testing.assert_close(out["color"], bg.expand(2, 3))
    assert out["opacity"].tolist() == [0.0, 0.0] and out["depth"].tolist() == [0.0, 0.0]
    assert out["weights"].numel() == 0
