"""The surfel primitive of the Gaussian rasteriser against a float64 per-pixel reference written here
(ray-plane intersection in world space), finite differences, and a plane seen from many views."""

from __future__ import annotations

import math

import pytest
import torch

from l3d_app.geometry.cameras import Cameras, look_at_cameras
from l3d_app.render.gaussians.composite import bin_tiles, splat_pixel_pairs
from l3d_app.render.gaussians.sh import rgb_to_sh
from l3d_app.render.gaussians.surfel_composite import SurfelCompositeFunction, surfel_composite_pairs
from l3d_app.render.gaussians.surfel_project import LOW_PASS_INV, project_surfels
from l3d_app.render.gaussians.surfels import rasterize_surfels

DT = torch.float64
S = 24           # image side (px)


def _camera(dtype=DT):
    """Looks down +Z from (0, 0, -4): world axes = camera axes, f = 30 px, centre (12, 12)."""
    return Cameras(torch.eye(3, dtype=dtype)[None], torch.tensor([[0.0, 0.0, 4.0]], dtype=dtype), 30.0, 30.0,
                   S / 2, S / 2, S, S)


def _quat_from_normal(n):
    """A unit quaternion (w, x, y, z) whose rotation's third column is the unit vector ``n``."""
    n = torch.nn.functional.normalize(torch.as_tensor(n, dtype=DT), dim=0)
    z = torch.tensor([0.0, 0.0, 1.0], dtype=DT)
    axis = torch.linalg.cross(z, n)
    s, c = float(axis.norm()), float((z * n).sum())
    if s < 1e-12:
        return torch.tensor([1.0, 0.0, 0.0, 0.0] if c > 0 else [0.0, 1.0, 0.0, 0.0], dtype=DT)
    half = math.atan2(s, c) / 2
    return torch.cat([torch.tensor([math.cos(half)], dtype=DT), math.sin(half) * axis / s])


def _reference(mean, log_scale, quat, opacity, cam):
    """Per pixel (float64, independent of the code under test): alpha of one surfel, the depth of
    its contribution and its camera-facing normal, by intersecting each pixel's ray with the
    splat's plane in WORLD space: ``lambda = n.(m - C) / n.d`` with ``d`` the ray of camera z = 1,
    local ``(u, v) = ((P - m).t_u / s_u, (P - m).t_v / s_v)``, the low-pass floor
    ``rho exp(-L (dx^2 + dy^2) / 2)`` around the projected centre (``L = LOW_PASS_INV``, the design's
    constant), ``rho = min(1, L |det J|)`` with ``J``
    the Jacobian of the pixel in (u, v) at the centre (central differences), alpha = min(0.99,
    o max(...)) (0 below 1/255); depth: lambda where the ray-splat term wins, else the centre's depth."""
    w, x, y, z = (quat / quat.norm()).tolist()
    Rq = torch.tensor([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                       [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                       [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]], dtype=DT)
    tu, tv, n = Rq[:, 0], Rq[:, 1], Rq[:, 2]
    su, sv = torch.exp(log_scale[:2]).tolist()
    C = (-cam.R[0].T @ cam.t[0]).to(DT)
    R = cam.R[0].to(DT)
    jj, ii = torch.meshgrid(torch.arange(S, dtype=DT) + 0.5, torch.arange(S, dtype=DT) + 0.5, indexing="xy")
    d_cam = torch.stack([(jj - float(cam.cx)) / float(cam.fx), (ii - float(cam.cy)) / float(cam.fy),
                         torch.ones_like(jj)], -1)
    d = d_cam @ R                                       # world direction with camera z = 1
    lam = ((mean - C) @ n) / (d @ n)
    P = C + lam[..., None] * d
    u, v = ((P - mean) @ tu) / su, ((P - mean) @ tv) / sv
    q3 = torch.where(lam > 0, u * u + v * v, torch.full_like(u, float("inf")))
    pc = R @ mean + cam.t[0].to(DT)

    def pixel(x):
        q = R @ x + cam.t[0].to(DT)
        return torch.stack([float(cam.fx) * q[0] / q[2] + float(cam.cx), float(cam.fy) * q[1] / q[2] + float(cam.cy)])

    uc, vc = pixel(mean).tolist()
    h = 1e-6                                  # the disk's projected area at its centre, px^2 per unit (u, v) area
    J = torch.stack([(pixel(mean + h * su * tu) - pixel(mean - h * su * tu)) / (2 * h),
                     (pixel(mean + h * sv * tv) - pixel(mean - h * sv * tv)) / (2 * h)], 1)
    rho = min(1.0, LOW_PASS_INV * abs(float(torch.linalg.det(J))))
    q2 = LOW_PASS_INV * ((jj - uc) ** 2 + (ii - vc) ** 2) - 2.0 * math.log(max(rho, 1e-12))
    q = torch.minimum(q3, q2)
    alpha = (opacity * torch.exp(-q / 2)).clamp(max=0.99)
    alpha = torch.where((alpha >= 1 / 255) & (pc[2] > 0.01), alpha, torch.zeros_like(alpha))
    depth = torch.where(q3 <= q2, lam, pc[2].expand_as(lam))
    normal = n if float((mean - C) @ n) < 0 else -n
    return alpha, depth, normal


def _one(normal, centre=(0.1, -0.2, 0.3), log_scale=(-1.0, -1.6), opacity=0.9):
    mean = torch.tensor(centre, dtype=DT)
    ls = torch.tensor([*log_scale, -9.0], dtype=DT)
    return mean, ls, _quat_from_normal(normal), torch.tensor(opacity, dtype=DT)


CASES = {
    "head-on": ((0.0, 0.0, -1.0), {}),
    "oblique": ((0.0, math.sin(1.1), -math.cos(1.1)), {}),
    "oblique-rotated": ((0.6, -0.5, -0.62), {"log_scale": (-0.8, -2.0)}),
    # the camera centre (0, 0, -4) lies in the splat's plane: no projected area, nothing drawn
    "edge-on": (None, {}),
    "grazing": ((0.0, math.sin(1.45), -math.cos(1.45)), {}),
    # smaller than a pixel: the floor draws it, with the opacity its projected area gives it
    "sub-pixel": ((0.2, 0.1, -1.0), {"log_scale": (-4.0, -4.3)}),
    "behind": ((0.0, 0.0, -1.0), {"centre": (0.1, 0.0, -5.0)}),
}


@pytest.mark.parametrize("case", list(CASES))
def test_single_surfel_alpha_depth_normal_match_the_world_space_reference(case):
    normal, kw = CASES[case]
    if normal is None:
        centre = torch.tensor([0.1, -0.2, 0.3], dtype=DT)
        to_cam = centre - torch.tensor([0.0, 0.0, -4.0], dtype=DT)
        normal = torch.linalg.cross(to_cam, torch.tensor([1.0, 0.0, 0.0], dtype=DT))
    mean, ls, quat, o = _one(normal, **kw)
    cam = _camera()
    sh = rgb_to_sh(torch.ones(1, 1, 3, dtype=DT))
    out = rasterize_surfels(mean[None], ls[None], quat[None], torch.logit(o)[None], sh, 0, cam)
    alpha, depth, n = _reference(mean, ls, quat, o, cam)
    torch.testing.assert_close(out["alpha"][0], alpha, atol=1e-10, rtol=1e-8)    # (rho by central differences)
    torch.testing.assert_close(out["color"][0], alpha[..., None].expand(S, S, 3), atol=1e-10, rtol=1e-8)
    hit = alpha > 0
    if case in ("behind", "edge-on"):
        assert not bool(hit.any()) and float(out["alpha"].max()) == 0.0
        return
    assert int(hit.sum()) >= (1 if case == "sub-pixel" else 10)
    if case == "sub-pixel":                   # the floor decided: faint, a pixel or so wide
        assert 1 / 255 < float(alpha.max()) < 0.3 and int(hit.sum()) < 10
    torch.testing.assert_close(out["expected_depth"][0][hit], depth[hit], atol=1e-10, rtol=1e-10)
    torch.testing.assert_close(out["median_depth"][0][hit], depth[hit], atol=1e-10, rtol=1e-10)
    torch.testing.assert_close(out["normal"][0][hit], alpha[hit][:, None] * n, atol=1e-10, rtol=1e-8)
    assert float(out["distortion"].abs().max()) < 1e-12              # one splat: nothing to spread


def test_oblique_depth_is_perspective_correct_not_the_centre_depth():
    mean, ls, quat, o = _one((0.0, math.sin(1.1), -math.cos(1.1)), log_scale=(-0.5, -0.5))
    out = rasterize_surfels(mean[None], ls[None], quat[None], torch.logit(o)[None],
                            rgb_to_sh(torch.ones(1, 1, 3, dtype=DT)), 0, _camera())
    d = out["expected_depth"][0][out["alpha"][0] > 0.5]
    assert float(d.max() - d.min()) > 0.5          # a tilted disk spans depths (3DGS would give one value)


def _scene(n=6, seed=0, dtype=DT):
    g = torch.Generator().manual_seed(seed)
    means = (torch.rand(n, 3, generator=g, dtype=dtype) - 0.5) * torch.tensor([1.2, 1.2, 0.8], dtype=dtype)
    ls = torch.log(0.15 + 0.2 * torch.rand(n, 3, generator=g, dtype=dtype))
    quats = torch.randn(n, 4, generator=g, dtype=dtype)
    quats[:, 3] += 2.0                       # normals mostly along -z/+z: facing the camera
    logits = torch.randn(n, generator=g, dtype=dtype) + 1.0
    sh = 0.3 * torch.randn(n, 4, 3, generator=g, dtype=dtype)
    return means, ls, quats, logits, sh


def _loss_weights(out, seed=5):
    g = torch.Generator().manual_seed(seed)
    return {k: torch.randn(out[k].shape, generator=g, dtype=out[k].dtype)
            for k in ("color", "alpha", "depth", "median_depth", "normal", "distortion")}


def test_gradients_match_central_finite_differences_float64():
    means, ls, quats, logits, sh = _scene()
    cam = _camera()
    params = [x.clone().requires_grad_(True) for x in (means, ls, quats, logits, sh)]
    out = rasterize_surfels(*params[:4], params[4], 1, cam)
    wts = _loss_weights(out)
    assert float(out["distortion"].detach().max()) > 1e-4 and int((out["alpha"] > 0).sum()) > 100

    def loss(*p):
        o = rasterize_surfels(*p[:4], p[4], 1, cam)
        return sum((o[k] * wts[k]).sum() for k in wts)

    loss(*params).backward()
    g = torch.Generator().manual_seed(9)
    eps = 1e-6
    for i, p in enumerate(params):
        idx = torch.randperm(p.numel(), generator=g)[:8]
        for j in idx.tolist():
            base = [x.detach().clone() for x in params]
            plus, minus = [x.clone() for x in base], [x.clone() for x in base]
            plus[i].view(-1)[j] += eps
            minus[i].view(-1)[j] -= eps
            with torch.no_grad():
                fd = (loss(*plus) - loss(*minus)) / (2 * eps)
            an = p.grad.view(-1)[j]
            assert abs(float(fd - an)) <= 1e-5 + 1e-4 * abs(float(fd)), (i, j, float(fd), float(an))


def test_hand_written_backward_matches_autograd_of_the_reference_forward():
    means, ls, quats, logits, sh = _scene(n=12, seed=3)
    quats[:3, 0] = 0.0
    quats[:3, 1:] = torch.tensor([1.0, 0.0, 0.0], dtype=DT)      # three edge-on-ish, as seen from the camera
    cam = _camera()
    grads, outs = [], []
    for custom in (True, False):
        params = [x.clone().requires_grad_(True) for x in (means, ls, quats, logits, sh)]
        out = rasterize_surfels(*params[:4], params[4], 1, cam, custom_backward=custom)
        wts = _loss_weights(out, seed=2)
        sum((out[k] * wts[k]).sum() for k in wts).backward()
        outs.append([out[k].detach() for k in wts])
        grads.append([p.grad for p in params] + [out["means2d"].grad])
    for a, b in zip(*outs):
        torch.testing.assert_close(a, b, atol=1e-10, rtol=1e-9)
    for a, b in zip(*grads):
        torch.testing.assert_close(a, b, atol=1e-9, rtol=1e-7)


def test_gradcheck_of_the_compositing_with_early_termination():
    N = 8
    means, ls, quats, logits, sh = _scene(n=N, seed=4)
    means[:, :2] *= 0.2                                     # stacked: pixels reach the transmittance floor
    logits = torch.full_like(logits, 6.0)
    cam = _camera()
    proj = project_surfels(means, ls, quats, torch.sigmoid(logits), cam.to(dtype=DT))
    low = torch.tensor([LOW_PASS_INV, 0.0, LOW_PASS_INV], dtype=DT).expand(N, 3)
    sid, ts, tc = bin_tiles(proj["box_centre"][0], proj["extent"][0], proj["depth"][0], S, S, 4)
    pix, spl = splat_pixel_pairs(sid, ts, tc, proj["means2d"][0], low, torch.sigmoid(logits), S, S, 4,
                                 rays=proj["rays"][0], floor=proj["floor"][0])
    inputs = [x.detach().clone().requires_grad_(True) for x in
              (proj["means2d"][0], proj["rays"][0], proj["depth_row"][0], torch.sigmoid(logits) * 0.999,
               proj["floor"][0] + 0.5, torch.rand(N, 4, dtype=DT))]

    def fn(m, r, d, o, fl, f):
        return SurfelCompositeFunction.apply(pix, spl, m, r, d, o, fl, f, S, S)

    from l3d_app.render.gaussians.composite import _segments, _transmittance
    from l3d_app.render.gaussians.surfel_composite import _pair_geometry
    with torch.no_grad():
        seg, last = _segments(pix)
        a, _, _ = _pair_geometry(pix, spl, *inputs[:5], S, S)
        assert not bool(_transmittance(a, seg, last)[1].all())       # some pixels terminate early
    assert torch.autograd.gradcheck(fn, inputs, eps=1e-6, atol=1e-5, rtol=1e-3, fast_mode=True)
    ref = surfel_composite_pairs(pix, spl, *inputs, S, S)
    for a, b in zip(fn(*inputs), ref):
        torch.testing.assert_close(a, b, atol=1e-10, rtol=1e-9)


def _plane_of_surfels(spacing=0.15, half=1.0, dtype=torch.float32):
    """Overlapping opaque surfels tiling the plane y = 0 over [-half, half]^2, normals +y."""
    ax = torch.arange(-half, half + 1e-9, spacing, dtype=dtype)
    gx, gz = torch.meshgrid(ax, ax, indexing="ij")
    means = torch.stack([gx.reshape(-1), torch.zeros(gx.numel(), dtype=dtype), gz.reshape(-1)], -1)
    n = means.shape[0]
    ls = torch.full((n, 3), math.log(1.5 * spacing), dtype=dtype)      # 2 px or more on screen: the ray term decides
    quats = _quat_from_normal((0.0, 1.0, 0.0)).to(dtype).expand(n, 4)
    return means, ls, quats, torch.full((n,), 4.0, dtype=dtype), torch.zeros(n, 1, 3, dtype=dtype)


def test_a_plane_of_surfels_renders_the_analytic_plane_depth_from_every_view():
    means, ls, quats, logits, sh = _plane_of_surfels()
    elev = torch.tensor([90.0, 70.0, 50.0, 35.0, 60.0, 40.0])
    azim = torch.tensor([0.0, 30.0, 100.0, 200.0, 290.0, 330.0])
    cams = look_at_cameras(2.5, elev, azim, 50.0, 40)
    out = rasterize_surfels(means, ls, quats, logits, sh, 0, cams)
    from l3d_app.geometry.rays import camera_rays
    origins, dirs = camera_rays(cams, normalize=False)              # camera z = 1 directions
    truth = -origins[..., 1] / dirs[..., 1]                           # the ray's depth where it meets y = 0
    inner = (out["alpha"] > 0.99)
    assert int(inner.sum()) > 0.5 * inner.numel()
    for key in ("expected_depth", "median_depth"):
        err = (out[key] - truth).abs()[inner] / truth[inner]
        assert float(err.max()) < 2e-5, key
    normal = torch.nn.functional.normalize(out["normal"], dim=-1)[inner]
    assert float((normal[:, 1] - 1).abs().max()) < 1e-5
    assert float(out["distortion"][inner].max()) < 1e-8              # every contribution at one depth
