"""A photo capture's splat start (models/gaussian_start.py, render/gaussians/coverage.py): the coverage
bound met by capping only the splats that cover the most, and splats for the view cells left uncovered,
placed on a known wall. References: float64 bisection, the pinhole geometry of a plane, pooled pixels."""

import math

import pytest
import torch

from l3d_app.geometry.cameras import Cameras
from l3d_app.models.gaussian_start import cover_views, fill_splats
from l3d_app.models.gaussians import init_from_points
from l3d_app.render.gaussians.coverage import (cap_to_coverage, screen_coverage, shrink_to_coverage,
                                               splat_coverage, water_level)

W, H, F, Z = 64, 48, 60.0, 4.0


def _camera():
    return Cameras(torch.eye(3)[None], torch.tensor([[0.0, 0.0, Z]]), F, F, W / 2, H / 2, W, H)


def _level_by_bisection(cover, bound):
    lo, hi = 0.0, float(cover.max())
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if float(cover.clamp(max=mid).sum()) < bound else (lo, mid)
    return 0.5 * (lo + hi)


def test_the_water_level_matches_a_bisection():
    g = torch.Generator().manual_seed(0)
    for _ in range(5):
        cover = torch.rand(300, generator=g, dtype=torch.float64) ** 4 * 10.0
        bound = 0.3 * float(cover.sum())
        level = water_level(cover, bound)
        assert level == pytest.approx(_level_by_bisection(cover, bound), rel=1e-9)
        assert float(cover.clamp(max=level).sum()) == pytest.approx(bound, rel=1e-9)
    assert water_level(torch.tensor([10.0, 5.0, 1.0]), 8.0) == pytest.approx(3.5)    # 3.5 + 3.5 + 1 = 8
    assert water_level(torch.tensor([1.0, 2.0]), 3.0) == math.inf                   # already within


def test_capping_lowers_only_the_splats_that_cover_the_most():
    """60 small splats and 3 huge ones (an isolated point's neighbour distance): the bound is met,
    the small ones keep their scales bit for bit (a common shrink makes them dots), the huge
    ones end at one common coverage."""
    cam = _camera()
    g = torch.Generator().manual_seed(1)
    means = torch.cat([torch.rand(63, 2, generator=g) * 2 - 1, torch.zeros(63, 1)], 1)
    ls = torch.cat([torch.full((60, 3), math.log(0.02)), torch.full((3, 3), math.log(1.5))])
    quats = torch.tensor([[1.0, 0, 0, 0]]).expand(63, 4)
    op = torch.full((63,), 0.1)
    before = float(screen_coverage(means, ls, quats, op, cam)[0])
    assert before > 10.0
    out = cap_to_coverage(means, ls, quats, op, cam, max_coverage=1.0)
    after = float(screen_coverage(means, out, quats, op, cam)[0])
    assert 0.95 <= after <= 1.0 + 1e-6
    assert torch.equal(out[:60], ls[:60]) and torch.all(out[60:] < ls[60:])
    big = splat_coverage(means, out, quats, op, cam)[60:]
    assert float(big.max() - big.min()) < 1e-3 * float(big.max())
    shrunk = shrink_to_coverage(means, ls, quats, op, cam, max_coverage=1.0)
    assert torch.all(shrunk[:60] < ls[:60] - 1.0)                             # the common factor: dots
    assert torch.equal(cap_to_coverage(means, ls, quats, op, cam, max_coverage=1e4), ls)


def test_uncovered_cells_get_splats_on_the_wall_with_their_colour():
    """Points on the left half of a wall at depth 4 (a 64 x 48 view, 16 cells of 4 px along the
    long side): each right-half cell gets one splat on the wall (every nearest point is at depth 4)
    through its centre, half a cell wide there, with the cell's mean colour; covered cells none."""
    cam = _camera()
    x = torch.linspace(-2.0, -0.2, 30)
    y = torch.linspace(-1.5, 1.5, 25)
    gx, gy = torch.meshgrid(x, y, indexing="ij")
    points = torch.stack([gx.reshape(-1), gy.reshape(-1), torch.zeros(gx.numel())], 1)   # wall at world z = 0
    quats = torch.tensor([[1.0, 0, 0, 0]]).expand(len(points), 4)
    ls = torch.full((len(points), 3), math.log(0.05))
    v, u = torch.meshgrid(torch.arange(H, dtype=torch.float32), torch.arange(W, dtype=torch.float32), indexing="ij")
    image = torch.stack([u / W, v / H, 0.5 + 0.0 * u], -1)[None]
    means, log_scales, colors = fill_splats(points, ls, quats, points, image, cam)
    cell = 4
    assert len(means) > 0
    uv, z = cam.project(means)
    torch.testing.assert_close(z[0], torch.full((len(means),), Z), atol=1e-5, rtol=0)      # on the wall
    # through cell centres, only right of where the points end (u of x = -0.2 is 32 - 3 = 29)
    frac = uv[0] / cell - 0.5
    torch.testing.assert_close(frac, frac.round(), atol=1e-4, rtol=0)
    assert float(uv[0, :, 0].min()) > 29.0
    # every cell right of the covered part (columns 8..15, u >= 32) is filled, in every row, once
    cells = {(int(r), int(c)) for r, c in zip((uv[0, :, 1] // cell).tolist(), (uv[0, :, 0] // cell).tolist())}
    assert cells == {(r, c) for r in range(H // cell) for c in range(8, W // cell)} and len(means) == len(cells)
    torch.testing.assert_close(log_scales, torch.full_like(log_scales, math.log(0.5 * cell * Z / F)))
    pooled = torch.nn.functional.avg_pool2d(image[0].permute(2, 0, 1)[None], cell)[0]     # (3, 12, 16)
    r, c = (uv[0, :, 1] // cell).long(), (uv[0, :, 0] // cell).long()
    torch.testing.assert_close(colors, pooled[:, r, c].T, atol=1e-6, rtol=0)


def test_cover_views_covers_a_wall_the_points_leave_bare():
    """The model a capture starts from: points on the left half of the wall, their splats capped,
    the right half filled; rendered opaque, nearly every pixel is covered, and the bound holds."""
    from l3d_app.render.gaussians.rasterize import rasterize_gaussians

    cam = _camera()
    x, y = torch.meshgrid(torch.linspace(-2.0, -0.2, 30), torch.linspace(-1.5, 1.5, 25), indexing="ij")
    points = torch.stack([x.reshape(-1), y.reshape(-1), torch.zeros(x.numel())], 1)
    model = init_from_points(points, None, opacity=0.1)
    image = torch.full((1, H, W, 3), 0.3)
    grown = cover_views(model, image, cam, max_coverage=16.0)
    assert grown.num > model.num
    assert float(screen_coverage(grown.means, grown.log_scales3, grown.quats, torch.sigmoid(grown.opacity_logits),
                                 cam)[0]) <= 16.0 + 1e-6

    def covered(m):
        out = rasterize_gaussians(m.means, m.log_scales3, m.quats, torch.full((m.num,), 4.6), m.sh, 0, cam)
        return float((out["alpha"] > 0.5).float().mean())
    assert covered(model) < 0.6 and covered(grown) > 0.95


@pytest.mark.parametrize("known, surfels", [(False, False), (True, False), (False, True)])
def test_initial_splats_start_a_photo_capture_by_covering_its_views(known, surfels):
    """``initial_splats`` (gs_train, surfels): points and an unknown background (a photo capture) give
    gs_train's 3D splats the covering start (more splats than points, the points' small splats kept);
    a known background, or surfels, keep the common shrink (one splat per point, all scaled alike)."""
    from l3d_app.data.nerf_views import MultiViewData
    from l3d_app.pipelines.splats import initial_splats

    cam = _camera()
    x, y = torch.meshgrid(torch.linspace(-2.0, -0.2, 30), torch.linspace(-1.5, 1.5, 25), indexing="ij")
    points = torch.stack([x.reshape(-1), y.reshape(-1), torch.zeros(x.numel())], 1)
    far = torch.tensor([[0.5, 0.0, -3.0]])                         # an isolated point 1 unit before the camera
    data = MultiViewData(torch.full((1, H, W, 3), 0.3), cam, torch.tensor([0]), torch.tensor([], dtype=torch.long),
                         torch.tensor([], dtype=torch.long), torch.full((3,), 0.3),
                         torch.tensor([[-3.0, -3.0, -1.0], [3.0, 3.0, 1.0]]), points=torch.cat([points, far]),
                         background_known=known)
    model = initial_splats(data, data, None, 10, "grey", 0.1, max_coverage=16.0, surfels=surfels)
    plain = init_from_points(data.points, None, opacity=0.1)
    if known or surfels:
        assert model.num == len(data.points)
        step = (model.log_scales[:, 0] - plain.log_scales[:, 0]).detach()
        assert float(step.max() - step.min()) < 1e-5 and float(step.max()) < -1.0      # one common factor
    else:
        assert model.num > len(data.points)
        kept = (model.log_scales[: len(points)] == plain.log_scales[: len(points)]).all(1).float().mean()
        assert kept > 0.9                                           # the isolated splat is capped, not the rest
