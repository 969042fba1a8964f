"""The hand-written compositing backward: gradcheck (float64) and plain autograd of the same forward."""

from __future__ import annotations

import pytest
import torch

from l3d_app.render.gaussians.composite import (ALPHA_MAX, CompositeFunction, bin_tiles, composite_pairs,
                                                splat_pixel_pairs)

DT = torch.float64
W, H = 11, 7


def _splats(n, seed, opaque=False, stacked=False):
    g = torch.Generator().manual_seed(seed)
    mean2d = torch.rand(n, 2, generator=g, dtype=DT) * torch.tensor([W, H], dtype=DT)
    if stacked:                                    # all on one spot: early termination
        mean2d = torch.tensor([W / 2, H / 2], dtype=DT) + 0.3 * torch.randn(n, 2, generator=g, dtype=DT)
    sx, sy = 0.8 + 2.5 * torch.rand(n, generator=g, dtype=DT), 0.8 + 2.5 * torch.rand(n, generator=g, dtype=DT)
    rho = 0.8 * (torch.rand(n, generator=g, dtype=DT) * 2 - 1)
    det = (sx * sy) ** 2 * (1 - rho ** 2)
    conic = torch.stack([sy ** 2, -rho * sx * sy, sx ** 2], -1) / det[:, None]
    opacity = 0.2 + 0.75 * torch.rand(n, generator=g, dtype=DT)
    if opaque:
        opacity[: n // 2] = 0.999999                  # alpha clamped to 0.99 near their centres
    if stacked:
        opacity = 0.9 + 0.08 * torch.rand(n, generator=g, dtype=DT)
    feats = torch.rand(n, 4, generator=g, dtype=DT)
    depth = torch.rand(n, generator=g, dtype=DT)
    return mean2d, conic, opacity, feats, depth


def _pairs(mean2d, conic, opacity, depth, tile=4):
    ext = torch.full((mean2d.shape[0], 2), 12.0, dtype=DT)
    sid, ts, tc = bin_tiles(mean2d, ext, depth, W, H, tile)
    return splat_pixel_pairs(sid, ts, tc, mean2d, conic, opacity, W, H, tile)


@pytest.mark.parametrize("case", ["random", "opaque", "stacked"])
def test_gradcheck_custom_backward(case):
    n = 10 if case == "stacked" else 6
    mean2d, conic, opacity, feats, depth = _splats(n, seed=1, opaque=case == "opaque", stacked=case == "stacked")
    pix, spl = _pairs(mean2d, conic, opacity, depth)
    assert pix.numel() > 20
    inputs = [x.clone().requires_grad_(True) for x in (mean2d, conic, opacity, feats)]

    def fn(m, c, o, f):
        return CompositeFunction.apply(pix, spl, m, c, o, f, W, H)

    with torch.no_grad():
        acc, alpha = fn(*inputs)
    if case == "stacked":                          # some pixels terminated early
        assert float(alpha.max()) > 1 - 2e-4
    if case == "opaque":
        assert float(alpha.max()) >= ALPHA_MAX - 1e-12
    assert torch.autograd.gradcheck(fn, inputs, eps=1e-6, atol=1e-7, rtol=1e-5)


@pytest.mark.parametrize("seed", [0, 3])
def test_custom_backward_matches_autograd_of_the_same_forward(seed):
    mean2d, conic, opacity, feats, depth = _splats(40, seed=seed, opaque=seed == 3)
    pix, spl = _pairs(mean2d, conic, opacity, depth)
    g = torch.Generator().manual_seed(seed + 10)
    wa, wb = torch.rand(W * H, 4, generator=g, dtype=DT), torch.rand(W * H, generator=g, dtype=DT)
    results = []
    for fn in (CompositeFunction.apply, composite_pairs):
        x = [t.clone().requires_grad_(True) for t in (mean2d, conic, opacity, feats)]
        acc, alpha = fn(pix, spl, *x, W, H)
        ((acc * wa).sum() + (alpha * wb).sum()).backward()
        results.append((acc.detach(), alpha.detach(), [t.grad for t in x]))
    (a1, b1, g1), (a2, b2, g2) = results
    torch.testing.assert_close(a1, a2, atol=1e-12, rtol=1e-10)
    torch.testing.assert_close(b1, b2, atol=1e-12, rtol=1e-10)
    for name, u, v in zip(("mean2d", "conic", "opacity", "feats"), g1, g2):
        assert torch.isfinite(u).all(), name
        torch.testing.assert_close(u, v, atol=1e-10, rtol=1e-8, msg=name)


def test_pairs_are_exactly_the_visible_contributions():
    """Every (pixel, splat) with alpha >= 1/255 appears once; each pixel's pairs are one run, by depth."""
    mean2d, conic, opacity, feats, depth = _splats(30, seed=5)
    pix, spl = _pairs(mean2d, conic, opacity, depth)
    v, u = torch.meshgrid(torch.arange(H, dtype=DT) + 0.5, torch.arange(W, dtype=DT) + 0.5, indexing="ij")
    d = torch.stack([u.reshape(-1), v.reshape(-1)], -1)[:, None, :] - mean2d[None]       # (HW, N, 2)
    power = -0.5 * (conic[:, 0] * d[..., 0] ** 2 + 2 * conic[:, 1] * d[..., 0] * d[..., 1] + conic[:, 2] * d[..., 1] ** 2)
    expect = set(map(tuple, torch.nonzero(opacity * torch.exp(power) >= 1 / 255).tolist()))
    assert set(zip(pix.tolist(), spl.tolist())) == expect and len(expect) == pix.numel()
    same = pix[1:] == pix[:-1]
    assert int((~same).sum()) + 1 == torch.unique(pix).numel()              # one contiguous run per pixel
    assert bool((depth[spl][1:] > depth[spl][:-1])[same].all())


def test_no_pairs():
    z = torch.zeros(0, dtype=torch.long)
    m = torch.zeros(3, 2, dtype=DT, requires_grad=True)
    acc, alpha = CompositeFunction.apply(z, z, m, torch.ones(3, 3, dtype=DT), torch.ones(3, dtype=DT),
                                         torch.ones(3, 4, dtype=DT), W, H)
    assert float(acc.detach().abs().sum()) == 0.0 and float(alpha.detach().abs().sum()) == 0.0
    (acc.sum() + alpha.sum()).backward()
    assert float(m.grad.abs().sum()) == 0.0


def _projection_inputs(seed=0):
    from l3d_app.geometry.cameras import look_at

    g = torch.Generator().manual_seed(seed)
    n = 9
    means = (torch.rand(n, 3, generator=g, dtype=DT) * 2 - 1) * 0.6
    log_scales = torch.log(0.05 + 0.2 * torch.rand(n, 3, generator=g, dtype=DT))
    quats = torch.randn(n, 4, generator=g, dtype=DT)
    log_scales[0] = torch.tensor([-12.0, -12.0, -12.0], dtype=DT)     # point-like: low-pass only
    log_scales[1] = torch.tensor([-10.0, 0.0, -2.0], dtype=DT)        # needle
    log_scales[2] = torch.tensor([6.0, 5.0, 6.5], dtype=DT)           # enormous
    quats[3] = 0.0                                                   # zero quaternion: identity
    R, t = look_at(3.0, 10.0, 30.0, dtype=DT)
    means[4] = -(R[0].T @ t[0]) + 0.5 * R[0, 2] + 3.0 * R[0, 0]       # far outside the frustum (clamped J)
    means[5] = -(R[0].T @ t[0]) - 0.5 * R[0, 2]                      # behind the camera
    return means, log_scales, quats, R[0], t[0]


def test_gradcheck_projection_hard_cases():
    from l3d_app.render.gaussians.project import ProjectFunction

    means, log_scales, quats, R, t = _projection_inputs()
    x = [v.clone().requires_grad_(True) for v in (means, log_scales, quats)]

    def fn(m, s, q):
        m2, conic, z, _, _, _ = ProjectFunction.apply(m, s, q, R, t, 30.0, 31.0, 12.0, 9.5, 24, 18, 0.01)
        return m2, conic * 1e-2, z                        # conics of point-like splats are ~3 px^-2

    out = fn(*x)
    assert all(torch.isfinite(o).all() for o in out)
    assert torch.autograd.gradcheck(fn, x, eps=1e-7, atol=1e-6, rtol=1e-5)


def test_projection_backward_matches_autograd_reference():
    from l3d_app.geometry.cameras import Cameras
    from l3d_app.render.gaussians.rasterize import project_gaussians

    means, log_scales, quats, R, t = _projection_inputs(1)
    cams = Cameras(R[None], t[None], 30.0, 31.0, 12.0, 9.5, 24, 18)
    g = torch.Generator().manual_seed(2)
    w2, wc, wz = torch.randn(1, 9, 2, generator=g, dtype=DT), torch.randn(1, 9, 3, generator=g, dtype=DT), \
        torch.randn(1, 9, generator=g, dtype=DT)
    res = []
    for custom in (True, False):
        x = [v.clone().requires_grad_(True) for v in (means, log_scales, quats)]
        p = project_gaussians(*x, torch.full((9,), 0.5, dtype=DT), cams, custom_backward=custom)
        ((p["means2d"] * w2).sum() + (p["conic"] * wc).sum() + (p["depth"] * wz).sum()).backward()
        res.append((p, [v.grad for v in x]))
    (p1, g1), (p2, g2) = res
    for k in ("means2d", "conic", "depth", "radius", "extent", "visible"):
        torch.testing.assert_close(p1[k], p2[k], atol=1e-12, rtol=1e-10, msg=k)
    for name, a, b in zip(("means", "log_scales", "quats"), g1, g2):
        assert torch.isfinite(a).all(), name
        torch.testing.assert_close(a, b, atol=1e-9, rtol=1e-7, msg=name)


def test_screen_coverage_of_one_round_splat_is_its_disc_and_shrinking_bounds_it():
    """A round splat of std s at depth z, focal f: sigma_px^2 = (f s / z)^2 + 0.3 (low-pass),
    disc radius sigma_px sqrt(2 ln(255 o)); coverage = pi r^2 / (W H)."""
    import math

    from l3d_app.geometry.cameras import Cameras
    from l3d_app.render.gaussians.coverage import screen_coverage, shrink_to_coverage

    W = H = 64
    f, z, s, o = 80.0, 4.0, 0.2, 0.5
    cams = Cameras(torch.eye(3)[None], torch.tensor([[0.0, 0.0, z]]), f, f, W / 2, H / 2, W, H)
    means = torch.zeros(1, 3)
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]])
    ls = torch.full((1, 3), math.log(s))
    r2 = ((f * s / z) ** 2 + 0.3) * 2 * math.log(255 * o)
    cov = float(screen_coverage(means, ls, quats, torch.tensor([o]), cams)[0])
    assert cov == pytest.approx(math.pi * r2 / (W * H), rel=1e-4)
    # 200 copies: coverage 200x; shrinking to a bound of 10 lands at (not far below) the bound
    many = means.expand(200, 3).contiguous()
    q, op = quats.expand(200, 4), torch.full((200,), o)
    ls200 = ls.expand(200, 3)
    out = shrink_to_coverage(many, ls200, q, op, cams, max_coverage=10.0)
    after = float(screen_coverage(many, out, q, op, cams)[0])
    assert 9.0 <= after <= 10.0 + 1e-6 and torch.all(out < ls200)
    assert torch.equal(shrink_to_coverage(means, ls, quats, torch.tensor([o]), cams, max_coverage=100.0), ls)


def test_isotropic_log_scales_render_and_differentiate_like_three_equal_ones():
    from l3d_app.geometry.cameras import Cameras
    from l3d_app.render.gaussians.rasterize import rasterize_gaussians

    g = torch.Generator().manual_seed(3)
    n = 40
    means = (torch.rand(n, 3, generator=g) - 0.5)
    quats = torch.randn(n, 4, generator=g)
    op = torch.randn(n, generator=g)
    sh = torch.randn(n, 1, 3, generator=g)
    cams = Cameras(torch.eye(3)[None], torch.tensor([[0.0, 0.0, 3.0]]), 30.0, 30.0, 12.0, 12.0, 24, 24)
    one = torch.log(0.05 + 0.1 * torch.rand(n, 1, generator=g)).requires_grad_(True)
    three = one.detach().expand(n, 3).clone().requires_grad_(True)
    a = rasterize_gaussians(means, one, quats, op, sh, 0, cams)["color"]
    b = rasterize_gaussians(means, three, quats, op, sh, 0, cams)["color"]
    torch.testing.assert_close(a, b)
    a.square().sum().backward()
    b.square().sum().backward()
    torch.testing.assert_close(one.grad[:, 0], three.grad.sum(-1))      # chain rule through the repeat


def test_depth_key_orders_like_the_depths():
    """The float32 bit-pattern key sorts exactly as the values (negatives, zeros, infinities)."""
    from l3d_app.render.gaussians.composite import _depth_key
    g = torch.Generator().manual_seed(5)
    d = torch.cat([torch.randn(5000, generator=g) * 10.0 ** torch.randint(-30, 30, (5000,), generator=g),
                   torch.tensor([0.0, -0.0, float("inf"), -float("inf"), 1e-45, -1e-45, 3.0, 3.0])])
    k = _depth_key(d)
    assert int(k.min()) >= 0 and int(k.max()) < 2 ** 32
    assert torch.equal(d[torch.argsort(k)], torch.sort(d).values)
    d64 = d.double()                                  # other dtypes: the rank
    assert torch.equal(d64[torch.argsort(_depth_key(d64))], torch.sort(d64).values)


def test_zero_extent_splats_overlap_no_tile():
    mean2d = torch.tensor([[5.0, 3.0], [5.0, 3.0], [2.0, 2.0]], dtype=DT)
    ext = torch.tensor([[3.0, 3.0], [0.0, 0.0], [0.0, 1.0]], dtype=DT)
    sid, ts, tc = bin_tiles(mean2d, ext, torch.tensor([1.0, 2.0, 3.0], dtype=DT), W, H, 4)
    assert set(sid.tolist()) == {0} and int(tc.sum()) == 6          # splat 0: x tiles 0-2, y tiles 0-1
