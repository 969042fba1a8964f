"""Multi-view patch consistency (l3d_app/losses/patch_consistency.py) against an analytic scene: a
textured plane rendered by exact ray-plane intersection in float64, independently of the loss."""

import math

import pytest
import torch

from l3d_app.geometry.cameras import look_at_cameras
from l3d_app.losses.patch_consistency import PatchConsistency, bilinear, ncc, nearest_views, patch_offsets
from l3d_app.render.volume.estimators.zero_crossing import crossing_bracket, first_crossing

SIZE = 64


def texture(x: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
    """Grey level of the plane y = 0 at (x, z): smooth, textured at a few pixels' scale."""
    return 0.5 + 0.35 * torch.sin(2 * math.pi * x / 0.31) * torch.cos(2 * math.pi * z / 0.37 + 0.4)


def plane_scene(n_views: int = 12):
    """Cameras on a ring at 55 degrees elevation round a textured plane y = 0 (look_at's +Y up), and
    their images by exact ray-plane intersection (float64)."""
    azim = torch.arange(n_views, dtype=torch.float64) * (360.0 / n_views)
    cams = look_at_cameras(3.0, torch.full((n_views,), 55.0), azim.float(), 40.0, SIZE).to(dtype=torch.float64)
    o, d = pixel_rays(cams)
    t = -o[..., 1] / d[..., 1]
    p = o + t[..., None] * d
    g = texture(p[..., 0], p[..., 2])
    return cams, g[..., None].expand(*g.shape, 3).contiguous()


def pixel_rays(cams):
    """Unit rays through every pixel centre (B, H, W, 3), written out from the camera convention."""
    j, i = torch.meshgrid(torch.arange(SIZE, dtype=torch.float64) + 0.5, torch.arange(SIZE, dtype=torch.float64) + 0.5,
                          indexing="xy")
    cam_dir = torch.stack([(j[None] - cams.cx[:, None, None]) / cams.fx[:, None, None],
                           (i[None] - cams.cy[:, None, None]) / cams.fy[:, None, None],
                           torch.ones(len(cams), SIZE, SIZE, dtype=torch.float64)], dim=-1)
    d = torch.nn.functional.normalize(torch.einsum("bji,bhwj->bhwi", cams.R, cam_dir), dim=-1)
    return cams.centers()[:, None, None].expand_as(d), d


def rays_of_view(cams, view: int, step: int = 3, margin: int = 8):
    o, d = pixel_rays(cams)
    rows, cols = torch.meshgrid(torch.arange(margin, SIZE - margin, step), torch.arange(margin, SIZE - margin, step),
                                indexing="ij")
    rows, cols = rows.reshape(-1), cols.reshape(-1)
    n = rows.numel()
    origins, dirs = o[view, rows, cols], d[view, rows, cols]
    t_true = -origins[:, 1] / dirs[:, 1]
    return (torch.full((n,), view, dtype=torch.long), torch.stack([rows, cols], -1), origins, dirs, t_true,
            torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64).expand(n, 3))


@pytest.fixture(scope="module")
def scene():
    cams, images = plane_scene()
    return cams, images, PatchConsistency.build(images, cams, n_sources=4, size=5, best=2)


def test_the_true_plane_correlates_and_a_shifted_one_does_not(scene):
    cams, _, pc = scene
    view, pixel, o, d, t, n = rays_of_view(cams, 0)
    hit = torch.ones(len(t), dtype=torch.bool)
    at_truth, figs = pc.loss(view, pixel, o, d, t, n, hit)
    assert figs["ncc_rays"] > 0.9 and figs["ncc"] > 0.97
    assert float(at_truth) < 0.015
    for shift in (0.03, -0.03, 0.08):
        off, _ = pc.loss(view, pixel, o, d, t + shift, n, hit)
        assert float(off) > 5 * float(at_truth), shift
    tilt = math.radians(25.0)
    tilted = torch.tensor([math.sin(tilt), math.cos(tilt), 0.0], dtype=torch.float64).expand_as(n)
    assert float(pc.loss(view, pixel, o, d, t, tilted, hit)[0]) > 2 * float(at_truth)


def test_its_gradient_moves_the_surface_point_towards_the_plane(scene):
    cams, _, pc = scene
    view, pixel, o, d, t, n = rays_of_view(cams, 5)
    hit = torch.ones(len(t), dtype=torch.bool)
    for shift in (0.015, -0.015):
        t_hit = (t + shift).clone().requires_grad_(True)
        pc.loss(view, pixel, o, d, t_hit, n, hit)[0].backward()
        agree = (torch.sign(t_hit.grad) == math.copysign(1.0, shift)).double().mean()
        assert agree > 0.85, (shift, float(agree))      # descent moves t_hit back to the plane


def test_a_tilted_normal_is_pulled_back_by_the_gradient(scene):
    cams, _, pc = scene
    view, pixel, o, d, t, _ = rays_of_view(cams, 2)
    hit = torch.ones(len(t), dtype=torch.bool)
    angle = torch.tensor(math.radians(10.0), dtype=torch.float64, requires_grad=True)
    normal = torch.stack([torch.sin(angle), torch.cos(angle), torch.zeros((), dtype=torch.float64)]).expand(len(t), 3)
    pc.loss(view, pixel, o, d, t, normal, hit)[0].backward()
    assert float(angle.grad) > 0       # descent lowers the tilt


def test_hard_cases_count_nothing_and_stay_finite(scene):
    cams, images, pc = scene
    view, pixel, o, d, t, n = rays_of_view(cams, 1)
    hit = torch.ones(len(t), dtype=torch.bool)
    t_hit = t.clone().requires_grad_(True)
    # a normal perpendicular to each ray (grazing plane): no ray counts, a zero loss, no NaN
    grazing = torch.nn.functional.normalize(torch.cross(d, torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)
                                                        .expand_as(d), dim=-1), dim=-1)
    loss, figs = pc.loss(view, pixel, o, d, t_hit, grazing, hit)
    assert figs["ncc_rays"] == 0.0 and float(loss) == 0.0
    # no ray reaches a surface
    loss, figs = pc.loss(view, pixel, o, d, t, n, torch.zeros_like(hit))
    assert figs["ncc_rays"] == 0.0 and float(loss) == 0.0
    # a surface point far outside every source view, a zero-length normal: finite, nothing counts
    loss, figs = pc.loss(view, pixel, o, d, t_hit * 0 + 1e6, torch.zeros_like(n), hit)
    assert figs["ncc_rays"] == 0.0 and torch.isfinite(loss)
    # textureless images: nothing to match
    flat = PatchConsistency.build(torch.full_like(images, 0.5), cams)
    assert flat.loss(view, pixel, o, d, t, n, hit)[1]["ncc_rays"] == 0.0
    # patches over the image border do not count; the rest still do
    edge = pixel.clone()
    edge[::2, 1] = 0
    loss, figs = pc.loss(view, edge, o, d, t, n, hit)
    assert 0.35 < figs["ncc_rays"] < 0.65
    # a surface half-way between counted and not: the gradient through t is finite everywhere
    t_mix = torch.where(torch.arange(len(t)) % 3 == 0, t + 1e6, t).requires_grad_(True)
    pc.loss(view, pixel, o, d, t_mix, n, hit)[0].backward()
    assert torch.isfinite(t_mix.grad).all()


def test_under_bf16_autocast_it_computes_in_float32(scene):
    """The step's forward runs under ``precision=bf16`` autocast: the loss must not warp in bf16."""
    from l3d_app.runtime.precision import autocast

    cams, images, _ = scene
    pc = PatchConsistency.build(images.float(), cams.to(dtype=torch.float32))
    view, pixel, o, d, t, n = (v.float() if v.is_floating_point() else v for v in rays_of_view(cams, 4))
    hit = torch.ones(len(t), dtype=torch.bool)
    t_ref = (t + 0.02).requires_grad_(True)
    ref, _ = pc.loss(view, pixel, o, d, t_ref, n, hit)
    ref.backward()
    t_auto = (t + 0.02).requires_grad_(True)
    with autocast("bf16", "cpu"):
        got, _ = pc.loss(view, pixel, o, d, t_auto, n, hit)
    got.backward()
    assert got.dtype == torch.float32 and float(got.detach()) == pytest.approx(float(ref.detach()), rel=1e-6)
    torch.testing.assert_close(t_auto.grad, t_ref.grad, rtol=1e-5, atol=1e-7)
    # a bf16 surface distance (an autocast network's output) is read in float32, not warped in bf16
    t_bf16 = (t + 0.02).to(torch.bfloat16)
    with autocast("bf16", "cpu"):
        got16, _ = pc.loss(view, pixel, o, d, t_bf16, n, hit)
    want16, _ = pc.loss(view, pixel, o, d, t_bf16.float(), n, hit)
    assert got16.dtype == torch.float32 and float(got16) == pytest.approx(float(want16), rel=1e-6)


def test_bilinear_against_a_naive_loop():
    g = torch.Generator().manual_seed(0)
    images = torch.rand(2, 5, 7, generator=g, dtype=torch.float64)
    uv = torch.rand(40, 2, generator=g, dtype=torch.float64) * torch.tensor([8.0, 6.0], dtype=torch.float64) - 0.5
    view = torch.randint(0, 2, (40,), generator=g)
    values, inside = bilinear(images, view, uv)
    for k in range(40):
        x, y = float(uv[k, 0]) - 0.5, float(uv[k, 1]) - 0.5
        ok = 0 <= x <= 6 and 0 <= y <= 4
        assert bool(inside[k]) == ok
        if ok:
            x0, y0 = min(int(math.floor(x)), 5), min(int(math.floor(y)), 3)
            ax, ay = x - x0, y - y0
            im = images[int(view[k])]
            want = ((1 - ax) * (1 - ay) * im[y0, x0] + ax * (1 - ay) * im[y0, x0 + 1]
                    + (1 - ax) * ay * im[y0 + 1, x0] + ax * ay * im[y0 + 1, x0 + 1])
            assert abs(float(values[k]) - float(want)) < 1e-12
        else:
            assert float(values[k]) == 0.0


def test_ncc_offsets_and_neighbours_by_hand():
    a = torch.tensor([0.1, 0.5, 0.2, 0.9], dtype=torch.float64)
    assert float(ncc(a, 2 * a + 1)) == pytest.approx(1.0, abs=1e-6)
    assert float(ncc(a, -a)) == pytest.approx(-1.0, abs=1e-6)
    assert patch_offsets(3).tolist() == [[-1, -1], [0, -1], [1, -1], [-1, 0], [0, 0], [1, 0], [-1, 1], [0, 1], [1, 1]]
    with pytest.raises(ValueError):
        patch_offsets(4)
    ring = torch.stack([torch.cos(torch.arange(8) * math.pi / 4), torch.sin(torch.arange(8) * math.pi / 4),
                        torch.zeros(8)], -1)
    assert sorted(nearest_views(ring, 2)[3].tolist()) == [2, 4]


def test_the_crossing_bracket_interpolates_what_first_crossing_does():
    f = torch.tensor([[0.3, 0.1, -0.3, -0.5], [0.2, 0.1, 0.05, 0.01]], requires_grad=True)
    t = torch.tensor([[1.0, 2.0, 3.0, 4.0], [1.0, 2.0, 3.0, 4.0]])
    i, frac, found = crossing_bracket(f)
    assert found.tolist() == [True, False] and i[0, 0] == 1 and float(frac[0].detach()) == pytest.approx(0.25)
    t_cross, _ = first_crossing(f, t)
    assert float(t_cross[0].detach()) == pytest.approx(2.25)
    t_cross[0].backward()        # d t / d f1 = (t2 - t1) * -f2 / (f1 - f2)^2 = -(-0.3) / 0.16
    assert float(f.grad[0, 1]) == pytest.approx(0.3 / 0.16, rel=1e-5)
