"""PointRenderer against a naive float64 reference (every point x every pixel)."""

from __future__ import annotations

import math

import pytest
import torch

from l3d_app.errors import UserError
from l3d_app.geometry.cameras import Cameras, look_at
from l3d_app.geometry.pointcloud import PointCloud
from l3d_app.geometry.rays import pixel_centers
from l3d_app.registry import RENDERERS
from l3d_app.render.points.renderer import PointRenderer

H, W = 20, 26  # non-square, to catch row/column swaps


def make_cams(dtype=torch.float64, azim=(0.0, 70.0), dist=3.0, size=(H, W)):
    R, t = look_at(dist, 15.0, list(azim), dtype=dtype)
    # fx != fy and an off-centre principal point exercise the intrinsics.
    return Cameras(R, t, fx=30.0, fy=26.0, cx=size[1] / 2 + 1.3, cy=size[0] / 2 - 0.7,
                   width=size[1], height=size[0])


def naive_render(points, colors, cams, radius, units="pixels", background=(1.0, 1.0, 1.0),
                 opacity=1.0, k=8, near=1e-3):
    """Every point against every pixel, float64; order by (float32 depth, index)."""
    pts, colors = points.double(), colors.double()
    cams = cams.to(dtype=torch.float64)
    view = cams.world_to_view(pts)  # (B, N, 3)
    z = view[..., 2]
    uv = cams.view_to_pixels(view)
    if units == "world":
        r = 0.5 * (cams.fx + cams.fy)[:, None] * radius / torch.where(z > near, z, torch.ones_like(z))
    else:
        r = torch.full_like(z, radius)
    pc = pixel_centers(cams.height, cams.width, dtype=torch.float64).reshape(-1, 2)  # (P, 2)
    d2 = ((pc[None, :, None, :] - uv[:, None, :, :]) ** 2).sum(-1)  # (B, P, N)
    inside = (d2 < r[:, None, :] ** 2) & (z[:, None, :] > near)
    key = torch.where(inside, z[:, None, :].float(), torch.tensor(float("inf")))
    order = torch.argsort(key, dim=-1, stable=True)[..., :k]  # (B, P, k)
    sel_in = torch.gather(inside, 2, order)
    w = opacity * (1 - torch.gather(d2, 2, order) / torch.gather(r[:, None, :].expand_as(d2), 2, order) ** 2)
    w = torch.where(sel_in, w, torch.zeros_like(w))
    image = torch.zeros(*w.shape[:2], 3, dtype=torch.float64)
    trans = torch.ones_like(w[..., 0])
    for j in range(w.shape[-1]):
        image = image + (trans * w[..., j])[..., None] * colors[order[..., j]]
        trans = trans * (1 - w[..., j])
    image = image + trans[..., None] * torch.tensor(background, dtype=torch.float64)
    zsel = torch.gather(z[:, None, :].expand_as(d2), 2, order[..., :1])[..., 0]
    depth = torch.where(sel_in[..., 0], zsel, torch.zeros_like(zsel))
    B = cams.batch_size
    return {"image": image.view(B, cams.height, cams.width, 3),
            "alpha": (1 - trans).view(B, cams.height, cams.width),
            "depth": depth.view(B, cams.height, cams.width)}


def random_cloud(n, seed=0, scale=0.6, dtype=torch.float64):
    g = torch.Generator().manual_seed(seed)
    return (torch.randn(n, 3, generator=g, dtype=dtype) * scale,
            torch.rand(n, 3, generator=g, dtype=dtype))


def compare(points, colors, cams, grads=True, atol=1e-9, **kw):
    """Values equal and gradients (w.r.t. points and colours) equal, both in float64."""
    renderer_kw = {k: v for k, v in kw.items() if k != "max_candidates"}
    p1 = points.clone().requires_grad_(True)
    c1 = colors.clone().requires_grad_(True)
    ref = naive_render(p1, c1, cams, kw.get("radius", 2.0), kw.get("radius_units", "pixels"),
                       kw.get("background", (1.0, 1.0, 1.0)), kw.get("opacity", 1.0),
                       kw.get("max_per_pixel", 8), kw.get("near", 1e-3))
    p2 = points.clone().requires_grad_(True)
    c2 = colors.clone().requires_grad_(True)
    out = PointRenderer(**renderer_kw, max_candidates=kw.get("max_candidates", 1 << 22))(
        PointCloud(p2, c2), cams)
    for key in ("image", "alpha", "depth"):
        assert out[key].shape == ref[key].shape
        torch.testing.assert_close(out[key], ref[key], atol=atol, rtol=0)
    if grads:
        g = torch.Generator().manual_seed(1)
        wts = {k: torch.randn(ref[k].shape, generator=g, dtype=torch.float64) for k in ref}
        loss_ref = sum((ref[k] * wts[k]).sum() for k in ref)
        loss_out = sum((out[k] * wts[k]).sum() for k in ref)
        gp1, gc1 = torch.autograd.grad(loss_ref, (p1, c1))
        gp2, gc2 = torch.autograd.grad(loss_out, (p2, c2))
        for a, b in ((gp2, gp1), (gc2, gc1)):
            assert torch.isfinite(a).all()
            torch.testing.assert_close(a, b, atol=1e-7, rtol=1e-7)
    return out, ref


@pytest.mark.parametrize("radius,k", [(1.5, 8), (3.0, 8), (2.5, 1), (4.0, 3)])
def test_matches_naive_reference_pixels(radius, k):
    pts, col = random_cloud(80, seed=int(radius * 10) + k)
    out, _ = compare(pts, col, make_cams(), radius=radius, max_per_pixel=k)
    assert out["alpha"].max() > 0.5  # the scene is actually on screen


@pytest.mark.parametrize("opacity", [1.0, 0.6])
def test_matches_naive_reference_world_units(opacity):
    pts, col = random_cloud(60, seed=3)
    compare(pts, col, make_cams(), radius=0.05, radius_units="world", opacity=opacity,
            background=(0.1, 0.2, 0.3))


def test_float32_close_to_float64_reference():
    pts, col = random_cloud(80, seed=5, dtype=torch.float32)
    out = PointRenderer(radius=2.0)(PointCloud(pts, col), make_cams(torch.float32))
    ref = naive_render(pts, col, make_cams(), 2.0)
    assert out["image"].dtype == torch.float32
    for key in ref:
        torch.testing.assert_close(out[key].double(), ref[key], atol=2e-4, rtol=0)


def test_chunking_and_compaction_give_identical_results():
    pts, col = random_cloud(150, seed=7)
    compare(pts, col, make_cams(), radius=3.0, max_per_pixel=2, max_candidates=37, grads=False)


def test_points_behind_camera_are_culled():
    pts, col = random_cloud(60, seed=11)
    cams = make_cams(azim=(0.0,), dist=0.3)  # camera inside the cloud: many points behind
    z = cams.world_to_view(pts)[0, :, 2]
    assert (z < 0).sum() > 10 and (z > 0).sum() > 10
    compare(pts, col, cams, radius=2.0)
    compare(pts, col, cams, radius=0.02, radius_units="world")
    behind = pts[z < 0]
    out = PointRenderer()(PointCloud(behind, col[z < 0]), cams)
    assert torch.all(out["alpha"] == 0) and torch.all(out["image"] == 1) and torch.all(out["depth"] == 0)


def test_point_at_near_plane_world_units_finite():
    cams = make_cams(azim=(0.0,))
    centre = cams.centers()[0]
    forward = cams.R[0, 2]
    pts = torch.stack([centre + 2e-3 * forward, centre + 1.0 * forward, centre - 1e-9 * forward])
    col = torch.tensor([[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0]], dtype=torch.float64)
    out, _ = compare(pts, col, cams, radius=0.01, radius_units="world", max_candidates=100)
    assert out["alpha"].min() > 0  # the near splat (radius 150 px) covers everything


def test_all_points_off_screen():
    pts, col = random_cloud(40, seed=2)
    pts = pts + torch.tensor([50.0, 0.0, 0.0], dtype=torch.float64)
    p = pts.clone().requires_grad_(True)
    out = PointRenderer(radius=3.0, background=(0.2, 0.4, 0.6))(PointCloud(p, col), make_cams())
    assert torch.all(out["alpha"] == 0) and torch.all(out["depth"] == 0)
    torch.testing.assert_close(out["image"], torch.tensor([0.2, 0.4, 0.6], dtype=torch.float64)
                               .expand_as(out["image"]))
    out["image"].sum().backward()
    assert torch.isfinite(p.grad).all() and torch.all(p.grad == 0)


def test_splat_partly_on_screen_matches_reference():
    cams = make_cams(azim=(0.0,))
    pts, col = random_cloud(30, seed=4)
    # push points to the image border so their discs are clipped
    view = cams.world_to_view(pts)[0]
    view[:, 0] = view[:, 2] * (torch.linspace(-0.6, 0.6, 30, dtype=torch.float64) * W / 30)
    pts = ((view - cams.t[0]) @ cams.R[0])
    compare(pts, col, cams, radius=5.0)


def test_coincident_points_lower_index_in_front():
    pts, col = random_cloud(20, seed=9)
    pts = torch.cat([pts, pts[:5], pts[:5]])  # three copies of 5 points
    col = torch.cat([col, torch.zeros(5, 3, dtype=torch.float64), torch.ones(5, 3, dtype=torch.float64)])
    out, _ = compare(pts, col, make_cams(), radius=3.0, opacity=0.7)
    # with K = 1 only the first copy is seen
    compare(pts, col, make_cams(), radius=3.0, max_per_pixel=1)


def test_single_point_disc_area():
    r = 6.0
    cams = make_cams(azim=(0.0,), size=(40, 40))
    pt = ((torch.tensor([[0.2, -0.1, 3.0]], dtype=torch.float64) - cams.t[0]) @ cams.R[0])
    out, _ = compare(pt, torch.tensor([[1.0, 0.0, 0.0]], dtype=torch.float64), cams, radius=r)
    covered = (out["alpha"] > 0).sum().item()
    assert abs(covered - math.pi * r * r) < 0.08 * math.pi * r * r
    # integral of (1 - d^2 / r^2) over the disc is pi r^2 / 2
    assert abs(out["alpha"].sum().item() - math.pi * r * r / 2) < 0.08 * math.pi * r * r / 2
    assert torch.allclose(out["depth"][out["alpha"] > 0], torch.tensor(3.0, dtype=torch.float64))


def test_position_gradient_moves_splat_towards_target():
    """A splat left of a target pixel: the gradient of that pixel's alpha pulls it right."""
    cams = make_cams(azim=(0.0,))
    view = torch.tensor([[0.0, 0.0, 2.0]], dtype=torch.float64)
    pts = ((view - cams.t[0]) @ cams.R[0]).requires_grad_(True)
    out = PointRenderer(radius=4.0)(PointCloud(pts), cams)
    u = cams.project(pts.detach())[0][0, 0]
    col = int(u[0]) + 2
    out["alpha"][0, int(u[1]), col].backward()
    du = (cams.R[0] @ pts.grad[0])[0]  # gradient along camera +X (image right)
    assert du > 0


def test_no_colors_is_grey_and_registry():
    pts, _ = random_cloud(30, seed=1)
    renderer = RENDERERS.build({"name": "points", "radius": 3.0, "background": [0, 0, 0]})
    out = renderer(PointCloud(pts), make_cams())
    assert (out["alpha"] > 0.99).any()
    # black background: every pixel is grey 0.5 times its coverage
    torch.testing.assert_close(out["image"], 0.5 * out["alpha"][..., None].expand(-1, -1, -1, 3))


def test_empty_cloud_and_bad_arguments():
    out = PointRenderer()(PointCloud(torch.zeros(0, 3)), make_cams(torch.float32))
    assert out["image"].shape == (2, H, W, 3) and torch.all(out["alpha"] == 0)
    for bad in ({"radius": 0.0}, {"radius_units": "mm"}, {"opacity": 0.0}, {"max_per_pixel": 0}):
        with pytest.raises(UserError):
            PointRenderer(**bad)
