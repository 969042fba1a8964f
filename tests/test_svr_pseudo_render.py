"""Pseudo-renderer (Lin et al. 2018): exact pixel and inverse depth, naive reference, gradients."""

from __future__ import annotations

import math

import pytest
import torch

from l3d_app.errors import UserError
from l3d_app.geometry.cameras import look_at_cameras
from l3d_app.render.points.pseudo import pseudo_render


def naive_render(points, cams, U, values=None, active=None):
    """Float64 loops: sub-pixel z-buffer (largest 1/Z, first point wins ties), then the
    U x U block maximum (first in row-major order wins ties)."""
    B, N = points.shape[:2]
    H, W = cams.height, cams.width
    uv, z = cams.to(dtype=torch.float64).project(points.double())
    inv = torch.zeros(B, H, W, dtype=torch.float64)
    idx = torch.full((B, H, W), -1, dtype=torch.long)
    for b in range(B):
        sub = torch.zeros(U * H, U * W, dtype=torch.float64)
        sub_id = torch.full((U * H, U * W), -1, dtype=torch.long)
        for n in range(N):
            if active is not None and not bool(active[b, n]):
                continue
            if not z[b, n] > 1e-3:
                continue
            c, r = math.floor(float(uv[b, n, 0]) * U), math.floor(float(uv[b, n, 1]) * U)
            if 0 <= c < U * W and 0 <= r < U * H and 1 / float(z[b, n]) > sub[r, c]:
                sub[r, c], sub_id[r, c] = 1 / float(z[b, n]), n
        for i in range(H):
            for j in range(W):
                best, who = 0.0, -1
                for di in range(U):
                    for dj in range(U):
                        v = float(sub[i * U + di, j * U + dj])
                        if v > best:
                            best, who = v, int(sub_id[i * U + di, j * U + dj])
                inv[b, i, j], idx[b, i, j] = best, who
    out = {"inv_depth": inv, "index": idx}
    if values is not None:
        out["values"] = torch.stack([torch.where(idx[b, ..., None] >= 0, values[b][idx[b].clamp_min(0)],
                                                 torch.zeros(())) for b in range(B)])
    return out


def cams_2(size=8):
    return look_at_cameras(2.5, torch.tensor([15.0, -30.0]), torch.tensor([20.0, 200.0]), 50.0, size)


def test_single_point_lands_at_its_pixel_with_its_inverse_depth():
    cams = cams_2(16)[0]
    p = torch.tensor([[[0.1, -0.2, 0.3]]])
    uv, z = cams.project(p[0])
    out = pseudo_render(p, cams, upsample=3, values=torch.tensor([[[7.0]]]))
    i, j = int(uv[0, 0, 1]), int(uv[0, 0, 0])  # floor of the pixel coordinates
    assert out["covered"].sum() == 1 and bool(out["covered"][0, i, j])
    assert float(out["inv_depth"][0, i, j]) == pytest.approx(1 / float(z[0, 0]), rel=1e-6)
    assert float(out["depth"][0, i, j]) == pytest.approx(float(z[0, 0]), rel=1e-6)
    assert int(out["index"][0, i, j]) == 0 and float(out["values"][0, i, j, 0]) == 7.0
    assert float(out["inv_depth"].sum()) == pytest.approx(1 / float(z[0, 0]), rel=1e-6)


def test_nearest_point_wins():
    cams = cams_2(16)[0]
    centre = cams.centers()[0]
    far, near = torch.zeros(3), 0.5 * centre  # both on the ray through the image centre
    out = pseudo_render(torch.stack([far, near])[None], cams, upsample=2)
    hit = out["index"][out["covered"]]
    assert hit.tolist() == [1]
    assert float(out["depth"][out["covered"]]) == pytest.approx(float(centre.norm() / 2), rel=1e-5)


@pytest.mark.parametrize("U", [1, 3])
def test_matches_naive_reference(U):
    g = torch.Generator().manual_seed(U)
    cams = cams_2(8)
    pts = (torch.rand(2, 300, 3, generator=g) * 2 - 1) * 1.2
    vals = torch.randn(2, 300, 2, generator=g)
    active = torch.rand(2, 300, generator=g) > 0.3
    ours = pseudo_render(pts, cams, U, values=vals, active=active)
    ref = naive_render(pts, cams, U, vals, active)
    assert torch.equal(ours["index"], ref["index"])
    assert torch.allclose(ours["inv_depth"].double(), ref["inv_depth"], rtol=1e-6, atol=0)
    assert torch.allclose(ours["values"].double(), ref["values"].double())
    assert torch.equal(ours["covered"], ref["index"] >= 0)


def test_gradients_finite_and_analytic_on_hard_cases():
    cams = cams_2(8)[0]
    c = cams.centers()[0]
    pts = torch.stack([torch.zeros(3), 0.3 * torch.ones(3),       # ordinary points
                       c,                                          # at the camera centre (Z = 0)
                       c + (c - torch.zeros(3)),                   # behind the camera
                       torch.tensor([50.0, 0.0, 0.0]),             # far off-screen
                       c + 1e-7 * torch.ones(3)])[None].clone().requires_grad_(True)
    vals = torch.randn(1, 6, 1, requires_grad=True)
    out = pseudo_render(pts, cams, 4, values=vals)
    assert torch.isfinite(out["depth"]).all() and torch.isfinite(out["inv_depth"]).all()
    (out["depth"].sum() + out["values"].sum()).backward()
    assert torch.isfinite(pts.grad).all() and torch.isfinite(vals.grad).all()
    # d depth / d point = the camera's forward axis (third row of R), once per pixel won
    wins = torch.bincount(out["index"][out["covered"]], minlength=6).float()
    assert wins[2:].sum() == 0 and wins[:2].min() >= 1
    expected = wins[:, None] * cams.R[0, 2][None]
    assert torch.allclose(pts.grad[0], expected, atol=1e-5)
    assert torch.allclose(vals.grad[0, :, 0], wins)


def test_shared_cloud_and_bad_input():
    cams = cams_2(8)
    pts = torch.rand(50, 3) - 0.5
    a = pseudo_render(pts, cams, 2)
    b = pseudo_render(pts[None].expand(2, -1, -1), cams, 2)
    assert torch.equal(a["index"], b["index"])
    with pytest.raises(UserError, match="upsample"):
        pseudo_render(pts, cams, 0)
    with pytest.raises(UserError, match="points must be"):
        pseudo_render(torch.rand(3, 50, 3), cams, 2)
