"""Gaussian rasteriser against a naive float64 reference (every splat at every pixel).

The reference shares nothing with the code under test: its SH colour comes from
tests/sh_reference.py (a recurrence, checked against scipy in test_sh_reference.py),
its rotation from the quaternion formula below, its compositing from a per-splat loop."""

from __future__ import annotations

import math

import pytest
import torch

from l3d_app.geometry.cameras import Cameras, look_at
from l3d_app.render.gaussians.sh import eval_sh, rgb_to_sh, sh_to_rgb
from l3d_app.render.gaussians.rasterize import rasterize_gaussians
from sh_reference import sh_colour

torch.set_num_threads(1)
DT = torch.float64


def _cams(W=37, H=29, elev=(15.0, -30.0), azim=(20.0, 200.0), dist=3.0):
    R, t = look_at(dist, elev, azim, dtype=DT)
    f = 0.9 * max(W, H)
    return Cameras(R, t, f, f * 1.05, W / 2 + 1.3, H / 2 - 0.7, W, H)


def _scene(n=40, seed=0, spread=0.7, deg=3):
    g = torch.Generator().manual_seed(seed)
    means = (torch.rand(n, 3, generator=g, dtype=DT) * 2 - 1) * spread
    log_scales = torch.log(0.03 + 0.15 * torch.rand(n, 3, generator=g, dtype=DT))
    quats = torch.randn(n, 4, generator=g, dtype=DT)
    logits = torch.randn(n, generator=g, dtype=DT) * 1.5 + 0.5
    sh = torch.randn(n, 16, 3, generator=g, dtype=DT) * 0.3
    sh[:, 0] = rgb_to_sh(torch.rand(n, 3, generator=g, dtype=DT))
    return [means, log_scales, quats, logits, sh]


def _rot(q):
    q = q / q.norm(dim=-1, keepdim=True)
    w, x, y, z = q.unbind(-1)
    # R = (w^2 - v.v) I + 2 v v^T + 2 w [v]_x
    v = torch.stack([x, y, z], -1)
    eye = torch.eye(3, dtype=q.dtype)
    vx = torch.zeros(*q.shape[:-1], 3, 3, dtype=q.dtype)
    vx[..., 0, 1], vx[..., 0, 2], vx[..., 1, 2] = -z, y, -x
    vx = vx - vx.transpose(-1, -2)
    return ((w * w - (v * v).sum(-1))[..., None, None] * eye + 2 * v[..., :, None] * v[..., None, :]
            + 2 * w[..., None, None] * vx)


def reference(means, log_scales, quats, logits, sh, deg, cams, bg, near=0.01):
    """Dense float64 reference: every Gaussian at every pixel, sorted by depth, loop front-to-back."""
    B, H, W = cams.batch_size, cams.height, cams.width
    op = torch.sigmoid(logits)
    S = torch.diag_embed(torch.exp(2 * log_scales))
    Rq = _rot(quats)
    cov3 = Rq @ S @ Rq.transpose(-1, -2)
    jj, ii = torch.meshgrid(torch.arange(W, dtype=DT) + 0.5, torch.arange(H, dtype=DT) + 0.5, indexing="xy")
    pix = torch.stack([jj, ii], -1)                                     # (H, W, 2)
    cols, alphas, depths = [], [], []
    for b in range(B):
        R, t = cams.R[b].to(DT), cams.t[b].to(DT)
        fx, fy, cx, cy = (float(v[b]) for v in (cams.fx, cams.fy, cams.cx, cams.cy))
        pc = means @ R.T + t
        x, y, z = pc.unbind(-1)
        xz = (x / z).clamp((-0.15 * W - cx) / fx, (1.15 * W - cx) / fx)
        yz = (y / z).clamp((-0.15 * H - cy) / fy, (1.15 * H - cy) / fy)
        J = torch.zeros(len(z), 2, 3, dtype=DT)
        J[:, 0, 0], J[:, 0, 2] = fx / z, -fx * xz / z
        J[:, 1, 1], J[:, 1, 2] = fy / z, -fy * yz / z
        cov2 = J @ R @ cov3 @ R.T @ J.transpose(1, 2) + 0.3 * torch.eye(2, dtype=DT)
        conic = torch.linalg.inv(cov2)
        mu = torch.stack([fx * x / z + cx, fy * y / z + cy], -1)
        dirs = means - (-R.T @ t)
        dirs = dirs / dirs.norm(dim=-1, keepdim=True)
        rgb = sh_colour(deg, sh, dirs)
        T = torch.ones(H, W, dtype=DT)
        alive = torch.ones(H, W, dtype=torch.bool)
        C = torch.zeros(H, W, 3, dtype=DT)
        D = torch.zeros(H, W, dtype=DT)
        for i in torch.argsort(z).tolist():
            if not z[i] > near:
                continue
            d = pix - mu[i]
            power = -0.5 * torch.einsum("hwi,ij,hwj->hw", d, conic[i], d)
            a = (op[i] * torch.exp(power)).clamp(max=0.99)
            a = torch.where(a >= 1 / 255, a, torch.zeros_like(a))
            test_t = T * (1 - a)
            alive = alive & (test_t >= 1e-4)
            w = torch.where(alive, a * T, torch.zeros_like(a))
            C = C + w[..., None] * rgb[i]
            D = D + w * z[i]
            T = torch.where(alive, test_t, T)
        cols.append(C + T[..., None] * bg)
        alphas.append(1 - T)
        depths.append(D)
    return {"color": torch.stack(cols), "alpha": torch.stack(alphas), "depth": torch.stack(depths)}


def _render(params, deg, cams, bg, **kw):
    return rasterize_gaussians(*params[:4], params[4], deg, cams, bg, **kw)


@pytest.mark.parametrize("tile,max_el", [(8, 1 << 22), (16, 1 << 22), (4, 200)])
def test_matches_dense_reference_values(tile, max_el):
    params, cams = _scene(60, seed=1), _cams()
    bg = torch.tensor([0.2, 0.5, 0.9], dtype=DT)
    out = _render(params, 3, cams, bg, tile_size=tile, max_elements=max_el)
    ref = reference(*params, 3, cams, bg)
    assert out["color"].shape == (2, 29, 37, 3)
    assert float(ref["alpha"].max()) > 0.5                         # the scene covers the image
    for k in ("color", "alpha", "depth"):
        torch.testing.assert_close(out[k], ref[k], atol=1e-9, rtol=1e-9)


@pytest.mark.parametrize("deg", [0, 1, 3])
def test_gradients_match_reference_autograd(deg):
    params, cams = _scene(30, seed=2), _cams()
    bg = torch.tensor([0.3, 0.3, 0.3], dtype=DT)
    g = torch.Generator().manual_seed(5)
    wc = torch.rand(2, 29, 37, 3, generator=g, dtype=DT)
    wa = torch.rand(2, 29, 37, generator=g, dtype=DT)
    grads = []
    for fn in (lambda p: _render(p, deg, cams, bg, tile_size=4), lambda p: reference(*p, deg, cams, bg)):
        p = [x.clone().requires_grad_(True) for x in params]
        o = fn(p)
        ((o["color"] * wc).sum() + (o["alpha"] * wa).sum() + 0.1 * o["depth"].sum()).backward()
        grads.append([x.grad for x in p])
    for name, a, b in zip(("means", "log_scales", "quats", "logits", "sh"), *grads):
        assert torch.isfinite(a).all(), name
        assert float(b.abs().max()) > 0, name
        torch.testing.assert_close(a, b, atol=1e-8, rtol=1e-6, msg=name)


def test_finite_differences():
    params, cams = _scene(20, seed=3), _cams()
    bg = torch.tensor([0.1, 0.2, 0.3], dtype=DT)
    wc = torch.rand(2, 29, 37, 3, generator=torch.Generator().manual_seed(1), dtype=DT)

    def loss(p):
        return (_render(p, 2, cams, bg)["color"] * wc).sum()

    p = [x.clone().requires_grad_(True) for x in params]
    loss(p).backward()
    for which, idx in ((0, (3, 0)), (0, (7, 2)), (1, (5, 1)), (2, (4, 2)), (3, (6,)), (4, (2, 5, 1))):
        eps = 1e-6
        plus = [x.clone() for x in params]
        minus = [x.clone() for x in params]
        plus[which][idx] += eps
        minus[which][idx] -= eps
        fd = (loss(plus) - loss(minus)) / (2 * eps)
        assert abs(float(fd) - float(p[which].grad[idx])) <= 1e-5 * max(1.0, abs(float(fd))), (which, idx)


def _finite_everything(params, cams, bg, deg=1):
    p = [x.clone().requires_grad_(True) for x in params]
    out = _render(p, deg, cams, bg)
    (out["color"].sum() + out["alpha"].sum() + out["depth"].sum()).backward()
    for k in ("color", "alpha", "depth"):
        assert torch.isfinite(out[k]).all(), k
    for x in p:
        if x.grad is None:                       # not in the graph at all: zero gradient
            x.grad = torch.zeros_like(x)
        assert torch.isfinite(x.grad).all()
    return out, p


def test_near_singular_and_huge_covariances():
    params, cams = _scene(12, seed=4), _cams()
    params[1][0] = torch.tensor([-30.0, -30.0, -30.0], dtype=DT)     # point-like: low-pass only
    params[1][1] = torch.tensor([-25.0, 0.0, -2.0], dtype=DT)        # needle
    params[1][2] = torch.tensor([30.0, 30.0, 30.0], dtype=DT)        # enormous
    params[1][3] = torch.tensor([40.0, -40.0, 0.0], dtype=DT)
    bg = torch.tensor([0.5, 0.5, 0.5], dtype=DT)
    out, _ = _finite_everything(params, cams, bg)
    ref = reference(*params, 1, cams, bg)
    torch.testing.assert_close(out["color"], ref["color"], atol=1e-6, rtol=1e-6)
    # float32 too: nothing overflows
    p32 = [x.float() for x in params]
    out32 = rasterize_gaussians(*p32, 1, cams.to(dtype=torch.float32), bg.float())
    assert torch.isfinite(out32["color"]).all()
    torch.testing.assert_close(out32["color"].double(), ref["color"], atol=2e-3, rtol=0)


def test_gaussians_at_or_behind_the_camera_are_culled():
    cams = _cams(elev=(0.0,), azim=(0.0,))
    centre = cams.centers()[0]
    forward = cams.R[0, 2]
    params = _scene(5, seed=5)
    params[0] = torch.stack([centre, centre - forward, centre - 0.001 * forward,
                             centre + 1e-9 * forward, centre + 1e-3 * cams.R[0, 0]])
    bg = torch.tensor([0.25, 0.5, 0.75], dtype=DT)
    out, p = _finite_everything(params, cams, bg)
    assert not out["visible"].any()
    torch.testing.assert_close(out["color"], bg.expand_as(out["color"]))
    assert float(out["alpha"].abs().max()) == 0.0
    assert all(float(x.grad.abs().max()) == 0.0 for x in p)


def test_all_splats_off_screen():
    cams = _cams(elev=(0.0,), azim=(0.0,))
    params = _scene(10, seed=6, spread=0.1)
    params[0] = params[0] + 50.0 * cams.R[0, 0]                      # far to the right
    bg = torch.tensor([1.0, 0.0, 0.0], dtype=DT)
    out, _ = _finite_everything(params, cams, bg)
    assert int(out["n_pairs"].sum()) == 0
    torch.testing.assert_close(out["color"], bg.expand_as(out["color"]))


def test_single_opaque_splat():
    W = H = 33
    cams = Cameras(torch.eye(3, dtype=DT), torch.tensor([0.0, 0.0, 2.0], dtype=DT), 40.0, 40.0, 16.5, 16.5, W, H)
    rgb = torch.tensor([[0.9, 0.2, 0.1]], dtype=DT)
    params = [torch.zeros(1, 3, dtype=DT), torch.full((1, 3), math.log(0.2), dtype=DT),
              torch.tensor([[1.0, 0, 0, 0]], dtype=DT), torch.tensor([20.0], dtype=DT),
              rgb_to_sh(rgb)[:, None, :]]
    bg = torch.tensor([0.0, 0.0, 1.0], dtype=DT)
    out = _render(params, 0, cams, bg)
    centre = out["color"][0, 16, 16]
    torch.testing.assert_close(centre, 0.99 * rgb[0] + 0.01 * bg)
    assert abs(float(out["alpha"][0, 16, 16]) - 0.99) < 1e-12
    torch.testing.assert_close(out["depth"][0, 16, 16] / out["alpha"][0, 16, 16], torch.tensor(2.0, dtype=DT))
    assert float(out["alpha"][0, 0, 0]) == 0.0                      # corner: below 1/255
    # symmetric about the centre
    torch.testing.assert_close(out["alpha"][0], out["alpha"][0].flip(0).flip(1))


def test_zero_quaternion_is_identity_with_finite_gradients():
    params, cams = _scene(8, seed=7), _cams()
    bg = torch.zeros(3, dtype=DT)
    params[2][0] = 0.0
    out, p = _finite_everything(params, cams, bg)
    ident = [x.clone() for x in params]
    ident[2][0] = torch.tensor([1.0, 0, 0, 0], dtype=DT)
    torch.testing.assert_close(out["color"], _render(ident, 1, cams, bg)["color"])


def test_screen_space_gradient_is_retained():
    params, cams = _scene(10, seed=8), _cams()
    p = [x.clone().requires_grad_(True) for x in params]
    out = _render(p, 0, cams, None)
    out["color"].sum().backward()
    g = out["means2d"].grad
    assert g is not None and g.shape == (2, 10, 2)
    assert float(g[out["visible"]].abs().sum()) > 0
    assert float(g[~out["visible"]].abs().sum()) == 0


def test_sh_finite_at_the_poles_and_dc_round_trip():
    dirs = torch.tensor([[0, 0, 1.0], [0, 0, -1.0], [0, 1.0, 0], [0, -1.0, 0], [1.0, 0, 0]], dtype=DT)
    coeffs = torch.randn(5, 16, 3, dtype=DT, requires_grad=True)
    d = dirs.clone().requires_grad_(True)
    for deg in range(4):
        v = eval_sh(deg, coeffs, d)
        assert torch.isfinite(v).all()
        gr = torch.autograd.grad(v.sum(), [coeffs, d], allow_unused=True)
        assert all(x is None or torch.isfinite(x).all() for x in gr)
    # degree 1 at +z is Y00 c0 + Y10 c2 with Y00 = 1 / sqrt(4 pi), Y10(+z) = sqrt(3 / 4 pi)
    v1 = eval_sh(1, coeffs, dirs)
    torch.testing.assert_close(v1[0], coeffs[0, 0] / math.sqrt(4 * math.pi) + math.sqrt(3 / (4 * math.pi)) * coeffs[0, 2])
    rgb = torch.rand(4, 3, dtype=DT)
    torch.testing.assert_close(sh_to_rgb(rgb_to_sh(rgb)), rgb)
    # bands of degree >= 1 integrate to zero over the sphere (orthogonality to Y_00)
    g = torch.Generator().manual_seed(0)
    u = torch.nn.functional.normalize(torch.randn(200000, 3, generator=g, dtype=DT), dim=-1)
    c = torch.zeros(16, 1, dtype=DT)
    c[1:] = 1.0
    assert abs(float(eval_sh(3, c, u).mean())) < 0.01


def test_sh_basis_is_orthonormal_on_the_sphere():
    """The degree-3 basis is orthonormal: int Y_i Y_j dOmega = delta_ij, by a product quadrature
    (Gauss-Legendre in z, trapezoid in azimuth) that is exact for these degree-6 products."""
    import numpy as np

    from l3d_app.render.gaussians.sh import sh_basis

    zq, wq = np.polynomial.legendre.leggauss(8)
    phi = np.arange(16) * (2 * math.pi / 16)
    z = torch.from_numpy(zq)[:, None].expand(8, 16)
    p = torch.from_numpy(phi)[None, :].expand(8, 16)
    r = torch.sqrt(1 - z * z)
    u = torch.stack([r * torch.cos(p), r * torch.sin(p), z], -1).reshape(-1, 3)
    w = (torch.from_numpy(wq)[:, None] * (2 * math.pi / 16)).expand(8, 16).reshape(-1)
    Y = sh_basis(3, u)
    gram = Y.T @ (w[:, None] * Y)
    torch.testing.assert_close(gram, torch.eye(16, dtype=DT), atol=1e-12, rtol=0)
