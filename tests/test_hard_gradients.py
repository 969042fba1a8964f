"""Hard cases with gradient VALUES (not only finiteness), each against a float64 closed form,
a brute-force float64 reference or central finite differences written here:

* float32 transmittance / compositing (render/volume/renderer.py ``composite``) with sigma * delta up
  to 1e20, against the float64 closed-form gradient;
* chamfer with duplicate and coincident points against brute force (duplicates get what
  brute force's first-index argmin gives them, identical copies in x identical gradients);
* the eikonal loss at a kink (a sphere's centre) and at vanishing gradients, against the
  closed form and finite differences in the SDF's parameter;
* the mesh regularisers on degenerate faces (zero area, repeated vertex, zero-length edge)
  against central finite differences.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from l3d_app.geometry.sdf import Sphere
from l3d_app.losses.eikonal import eikonal_at, eikonal_loss
from l3d_app.losses.mesh_regularizers import edge_length, laplacian_smoothing, normal_consistency
from l3d_app.metrics.chamfer import chamfer_distance
from l3d_app.render.volume.renderer import composite

D = torch.float64


def _central_fd(fn, x: torch.Tensor, h: float) -> torch.Tensor:
    """Central differences of scalar fn at x (float64), every entry."""
    g = torch.zeros_like(x)
    flat, gflat = x.reshape(-1), g.reshape(-1)
    for i in range(flat.numel()):
        old = float(flat[i])
        flat[i] = old + h
        fp = float(fn(x).detach())
        flat[i] = old - h
        fm = float(fn(x).detach())
        flat[i] = old
        gflat[i] = (fp - fm) / (2 * h)
    return g


# ------------------------------------------------------------------ transmittance
def _composite_reference(sigmas, deltas, colors, t):
    """float64 numpy closed form: values and d(sum g_c colour_c + g_d depth)/d sigma.

    With T_i = exp(-sum_{j<i} tau_j), w_i = T_i - T_{i+1}:
    d colour / d tau_i = T_{i+1} c_i - sum_{k>i} w_k c_k (likewise depth with t for c)."""
    tau = sigmas * deltas
    logT = -np.concatenate([np.zeros((tau.shape[0], 1)), np.cumsum(tau, -1)], -1)   # (R, S + 1)
    T = np.exp(logT)
    w = T[:, :-1] - T[:, 1:]
    w = np.where(tau < 1e-6, T[:, :-1] * -np.expm1(-tau), w)    # tiny tau: no cancellation
    colour = (w[..., None] * colors).sum(1)
    depth = (w * t).sum(1)
    suffix_c = np.flip(np.cumsum(np.flip(w[..., None] * colors, 1), 1), 1)           # sum_{k>=i}
    suffix_d = np.flip(np.cumsum(np.flip(w * t, 1), 1), 1)
    after_c = suffix_c - w[..., None] * colors                                         # sum_{k>i}
    after_d = suffix_d - w * t
    dcol_dtau = T[:, 1:, None] * colors - after_c
    ddep_dtau = T[:, 1:] * t - after_d
    return colour, depth, w, dcol_dtau * deltas[..., None], ddep_dtau * deltas


def test_float32_transmittance_with_huge_optical_depths_matches_float64_gradients():
    sig = np.array([[0.0, 1e-3, 0.5, 2.0, 1e10, 3.0],            # opaque wall at sample 4: 1e10 * 0.1
                    [0.0, 0.0, 1e-8, 1e-3, 0.0, 1e-10],          # nearly empty; last delta 1e10: tau 1
                    [1e10, 1e10, 1e10, 1e10, 1e10, 1e10],        # everything opaque
                    [0.2, 0.3, 0.1, 0.0, 0.05, 1.0]])            # ordinary, far samples (t ~ 1e4)
    t = np.array([[1.0, 1.1, 1.2, 1.3, 1.4, 1.5],
                  [2.0, 2.5, 3.0, 3.5, 4.0, 4.5],
                  [0.5, 0.6, 0.7, 0.8, 0.9, 1.0],
                  [1e4, 1e4 + 1, 1e4 + 2, 1e4 + 3, 1e4 + 4, 1e4 + 5]])
    deltas = np.concatenate([np.diff(t, axis=1), np.full((4, 1), 1e10)], 1)
    colors = np.random.default_rng(0).uniform(0.05, 1.0, (4, 6, 3))
    ref_c, ref_d, ref_w, ref_gc, ref_gd = _composite_reference(sig, deltas, colors, t)
    gcol = np.array([0.3, -0.7, 1.1])
    ref_g = (ref_gc * gcol).sum(-1) + 1e-4 * ref_gd

    s32 = torch.tensor(sig, dtype=torch.float32, requires_grad=True)
    c32 = torch.tensor(colors, dtype=torch.float32, requires_grad=True)
    out = composite(c32, torch.tensor(t, dtype=torch.float32), sigmas=s32)
    loss = (out["color"] * torch.tensor(gcol, dtype=torch.float32)).sum() + 1e-4 * out["depth"].sum()
    gs, gc = torch.autograd.grad(loss, [s32, c32])
    assert torch.isfinite(gs).all() and torch.isfinite(gc).all()
    np.testing.assert_allclose(out["weights"].detach().numpy(), ref_w, rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(out["color"].detach().numpy(), ref_c, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(out["depth"].detach().numpy(), ref_d, rtol=1e-5, atol=1e-6)
    # d loss / d colour = w g_c exactly; d loss / d sigma = the closed form (delta up to 1e10:
    # the last sample of the nearly empty ray has a gradient of about 1e10 * T e^-1)
    np.testing.assert_allclose(gc.numpy(), ref_w[..., None] * gcol, rtol=1e-5, atol=1e-7)
    scale = np.abs(ref_g).max(axis=1, keepdims=True)
    bad = np.abs(gs.numpy() - ref_g) > 1e-4 * np.abs(ref_g) + 1e-6 * scale
    assert not bad.any(), (gs.numpy()[bad], ref_g[bad])
    # behind the opaque walls nothing is seen and nothing is learnt: exact zeros, not NaN
    assert float(gs[0, 5]) == 0.0 and float(gs[2, 1:].abs().max()) == 0.0
    assert abs(float(gs[1, 5])) > 1e8                                # 1e10 * T_5 e^-1 (c . g)


# was a bug (torch's expm1 backward forms exp(-tau) as result + 1, 0 in float32 for tau > ~16.6);
# composite now takes d alpha / d tau = exp(-tau) directly (render/volume/renderer.py: opacity_from_optical_depth)
@pytest.mark.parametrize("tau", [10.0, 17.0, 20.0])
def test_float32_gradient_of_a_long_last_segment_matches_float64(tau):
    s = torch.tensor([[0.1, tau * 1e-10]], dtype=torch.float32, requires_grad=True)
    out = composite(torch.ones(1, 2, 1), torch.tensor([[1.0, 2.0]]), sigmas=s)   # last delta 1e10
    (g,) = torch.autograd.grad(out["color"].sum(), s)
    ref = 1e10 * math.exp(-0.1) * math.exp(-tau)                    # delta_1 T_2 c_1, float64
    assert float(g[0, 1]) == pytest.approx(ref, rel=1e-4)


def test_float32_alpha_mode_fully_opaque_sample_has_float64_gradients():
    """Alpha mode: an alpha of exactly 1 lets eps through; gradients of the samples in front
    and behind match the float64 closed form of prod (1 - alpha) compositing."""
    alpha = np.array([[0.2, 0.5, 1.0, 0.3]])
    colors = np.random.default_rng(1).uniform(0, 1, (1, 4, 3))
    a = torch.tensor(alpha, dtype=torch.float32, requires_grad=True)
    out = composite(torch.tensor(colors, dtype=torch.float32), torch.tensor([[1.0, 2, 3, 4]]), alphas=a)
    (ga,) = torch.autograd.grad(out["color"].sum(), a)
    # colour = sum_i T_i a_i c_i, T_i = prod_{j<i}(1 - a_j); d/da_i = T_i c_i - sum_{k>i} w_k c_k / (1 - a_i)
    T = np.concatenate([[1.0], np.cumprod(1 - alpha[0])[:-1]])
    w = T * alpha[0]
    cs = colors[0].sum(-1)
    ref = np.array([T[i] * cs[i] - sum(w[k] * cs[k] for k in range(i + 1, 4)) / (1 - alpha[0, i])
                    for i in range(2)])
    np.testing.assert_allclose(ga[0, :2].numpy(), ref, rtol=1e-5)
    eps32 = float(np.finfo(np.float32).eps)
    assert abs(float(ga[0, 3])) <= 2 * eps32 * T[2] * cs[3] + 1e-12      # behind: weight T_3 = eps * T_2
    assert torch.isfinite(ga).all()


# ------------------------------------------------------------------ chamfer
def _brute_chamfer(x, y, squared):
    """float64 brute force; argmin takes the first of equal distances (torch.argmin)."""
    d2 = ((x[:, None, :] - y[None, :, :]) ** 2).sum(-1)
    ixy, iyx = d2.argmin(1), d2.argmin(0)

    def dist(a, b):
        sq = ((a - b) ** 2).sum(-1)
        if squared:
            return sq
        return torch.where(sq > 0, sq.clamp_min(1e-300).sqrt(), torch.zeros_like(sq))  # 0 at coincidence

    return dist(x, y[ixy]).mean() + dist(y, x[iyx]).mean()


@pytest.mark.parametrize("squared", [True, False])
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_chamfer_with_duplicate_and_coincident_points_matches_brute_force_gradients(squared, dtype):
    g = torch.Generator().manual_seed(3)
    x = torch.rand(40, 3, generator=g, dtype=D)
    y = torch.rand(50, 3, generator=g, dtype=D)
    x = torch.cat([x, x[:5], x[:2]])                 # duplicates in x (three copies of x0, x1)
    y = torch.cat([y, y[:7], y[3:4]])                # duplicates in y
    x[10] = y[20]                                    # coincident across the sets
    x[11] = y[3]                                     # coincident with a point that has two copies
    xs, ys = x.to(dtype).requires_grad_(True), y.to(dtype).requires_grad_(True)
    val = chamfer_distance(xs, ys, squared=squared)
    gx, gy = torch.autograd.grad(val, [xs, ys])
    xr, yr = x.to(dtype).double().requires_grad_(True), y.to(dtype).double().requires_grad_(True)
    ref = _brute_chamfer(xr, yr, squared)
    rx, ry = torch.autograd.grad(ref, [xr, yr])
    tol = dict(rtol=1e-10, atol=1e-12) if dtype == torch.float64 else dict(rtol=2e-5, atol=2e-6)
    torch.testing.assert_close(val.double(), ref.detach(), **tol)
    torch.testing.assert_close(gx.double(), rx, **tol)
    torch.testing.assert_close(gy.double(), ry, **tol)
    # the copies of x0 differ only by the y -> x terms, which brute force sends to the first copy
    assert float((gx[40] - gx[45]).abs().max()) == 0.0 and float(gx[40].abs().max()) > 0
    # duplicate y points: brute force sends every term to the first copy; the group total is
    # the same whichever copy took it
    for i, copies in ((3, [3, 53, 57]), (0, [0, 50])):
        torch.testing.assert_close(gy[copies].sum(0).double(), ry[copies].sum(0), **tol)


# ------------------------------------------------------------------ eikonal at a kink
def test_eikonal_loss_value_and_gradient_against_the_closed_form_down_to_vanishing_gradients():
    mags = torch.tensor([0.0, 1e-150, 1e-20, 1e-3, 0.5, 1.0, 2.0, 1e3], dtype=D)
    dirs = torch.nn.functional.normalize(torch.tensor([[1.0, 2.0, -2.0]], dtype=D), dim=-1)
    g = (mags[:, None] * dirs).requires_grad_(True)
    loss = eikonal_loss(g)
    (gg,) = torch.autograd.grad(loss, g)
    n = mags.shape[0]
    assert float(loss.detach()) == pytest.approx(float(((mags - 1) ** 2).mean()), rel=1e-15)
    # d/dg mean((|g| - 1)^2) = 2 (|g| - 1) g / |g| / n, and 0 at g = 0 (the kink's subgradient)
    ref = torch.where(mags[:, None] > 0, 2 * (mags[:, None] - 1) * dirs / n, torch.zeros(1, 3, dtype=D))
    torch.testing.assert_close(gg, ref, rtol=1e-13, atol=0)


@pytest.mark.parametrize("s", [0.5, 1.0, 1.7])
def test_eikonal_through_a_kinked_sdf_matches_finite_differences_in_its_parameter(s):
    """f = s * (|p| - 0.5): |grad f| = s except at the centre (the kink), where the gradient
    is taken as 0. With k of N points at the centre, L(s) = ((N - k)(s - 1)^2 + k) / N;
    the double backward through the kink must give dL/ds = 2 (N - k)(s - 1) / N."""
    pts = torch.tensor([[0.0, 0.0, 0.0], [0.3, -0.2, 0.1], [0.0, 0.0, 0.0], [1.0, 2.0, 3.0], [0.0, 0.0, 1e-200]],
                       dtype=D)
    N, k = 5, 2                                                     # 1e-200: |p|^2 underflows -> a kink too
    k += 1
    sphere = Sphere(0.5)

    def loss(sv):
        return eikonal_at(lambda p: sv * sphere(p), pts)

    st = torch.tensor(s, dtype=D, requires_grad=True)
    val = loss(st)
    (gs,) = torch.autograd.grad(val, st)
    assert float(val.detach()) == pytest.approx(((N - k) * (s - 1) ** 2 + k) / N, rel=1e-13)
    assert float(gs) == pytest.approx(2 * (N - k) * (s - 1) / N, rel=1e-12, abs=1e-14)
    h = 1e-6
    fd = (float(loss(torch.tensor(s + h, dtype=D)).detach()) - float(loss(torch.tensor(s - h, dtype=D)).detach())) / (2 * h)
    assert float(gs) == pytest.approx(fd, rel=1e-7, abs=1e-9)


# ------------------------------------------------------------------ mesh regularisers, degenerate faces
def _degenerate_mesh():
    """A small fan plus: a zero-area face (collinear vertices 0, 1, 5), a repeated-vertex face
    (2, 2, 3), and a vertex 6 coincident with vertex 4 joined by an edge (zero length)."""
    v = torch.tensor([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 1.0, 0.2], [0.0, 1.0, -0.1],
                      [0.5, 0.5, 0.6], [2.0, 0.0, 0.0], [0.5, 0.5, 0.6]], dtype=D)
    f = torch.tensor([[0, 1, 4], [1, 2, 4], [2, 3, 4], [3, 0, 4], [0, 5, 1], [2, 2, 3], [4, 6, 2]])
    return v, f


@pytest.mark.parametrize("name,fn,h", [
    ("laplacian", laplacian_smoothing, 1e-5),
    ("edge_length_0", lambda v, f: edge_length(v, f), 1e-5),
    ("edge_length_target", lambda v, f: edge_length(v, f, 0.7), 1e-6),
    ("normal_consistency", normal_consistency, 1e-11),
])
def test_mesh_regularisers_on_degenerate_faces_match_finite_differences(name, fn, h):
    v, f = _degenerate_mesh()
    vr = v.clone().requires_grad_(True)
    val = fn(vr, f)
    (g,) = torch.autograd.grad(val, vr)
    assert torch.isfinite(val) and torch.isfinite(g).all()
    fd = _central_fd(lambda x: fn(x, f), v.clone(), h)
    scale = float(fd.abs().max())
    assert scale > 0
    # normal consistency is only C^1 in the regularised sense at the zero-area face: its
    # derivative there is ~1 / (1e-6 |n|), so it is checked relative to that scale
    tol = 1e-6 if name != "normal_consistency" else 1e-4
    torch.testing.assert_close(g, fd, rtol=tol, atol=tol * scale)
    if name == "edge_length_target":
        # the zero-length edge (4, 6): (|e| - t)^2 has the symmetric subgradient 0 at e = 0,
        # exactly what central differences see; ours must not be NaN nor push 4 and 6 apart
        assert torch.isfinite(g[6]).all()
