"""Known free space along rays (render/volume/free_space.py): the opacity distance against a naive
float64 loop and against analytic fields; the free segments' box and margin arithmetic; the
carving loss on them drives a sphere out of the free stretch."""

import math

import pytest
import torch

from l3d_app.render.volume.estimators.stratified import StratifiedEstimator
from l3d_app.render.volume.free_space import FreeRays, free_distances, opacity_distance

BOX = ((-1.0, -1.0, -1.0), (1.0, 1.0, 1.0))


def _naive_distance(t, alphas, level):
    opacity = 0.0
    for ti, a in zip(t, alphas):
        opacity = 1.0 - (1.0 - opacity) * (1.0 - a)
        if opacity >= level:
            return ti
    return math.inf


@pytest.mark.parametrize("level", [0.05, 0.3, 0.9])
def test_opacity_distance_matches_a_naive_loop(level):
    g = torch.Generator().manual_seed(0)
    counts = [0, 1, 3, 7, 12, 5]
    t_list, a_list, idx, trans = [], [], [], []
    for r, c in enumerate(counts):
        t = torch.sort(torch.rand(c, generator=g, dtype=torch.float64) * 4)[0]
        a = torch.rand(c, generator=g, dtype=torch.float64) ** 3
        trans.append(torch.cumprod(torch.cat([torch.ones(1, dtype=torch.float64), 1 - a[:-1]]), 0)[:c])
        t_list.append(t), a_list.append(a), idx.append(torch.full((c,), r))
    got = opacity_distance(torch.cat(t_list), torch.cat(trans), torch.cat(a_list), torch.cat(idx), len(counts), level)
    want = torch.tensor([_naive_distance(t.tolist(), a.tolist(), level) for t, a in zip(t_list, a_list)],
                        dtype=torch.float64)
    assert torch.equal(torch.isinf(got), torch.isinf(want)) and torch.isinf(got[0])
    fin = torch.isfinite(want)
    assert torch.equal(got[fin], want[fin])


def _field(sigma_fn):
    def field(points, dirs):
        return sigma_fn(points), torch.zeros(points.shape[0], 3, dtype=points.dtype)
    return field


def test_free_distance_of_a_constant_fog_and_of_a_wall():
    est = StratifiedEstimator(400, scene_box=BOX)
    o = torch.tensor([[-3.0, 0.0, 0.0], [-3.0, 0.2, 0.1], [0.5, -3.0, 0.0], [-3.0, 5.0, 0.0]])
    d = torch.tensor([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]])
    spacing = 2.0 / 400
    # constant density c: opacity 1 - exp(-c s) after s inside the box reaches 0.3 at s = ln(1 / 0.7) / c
    fog = free_distances(_field(lambda p: torch.full((p.shape[0],), 2.0)), est, o, d, 0.3)
    s = math.log(1 / 0.7) / 2.0
    torch.testing.assert_close(fog[:3], torch.full((3,), 2.0 + s), atol=spacing, rtol=0)
    assert math.isinf(float(fog[3]))                           # misses the box: never opaque
    # a wall at x = 0.2 (density 1e4 beyond it): rays along +x stop there, the ray along +y at x = 0.5
    # starts inside the wall, the ray beside the box never reaches it
    wall = free_distances(_field(lambda p: 1e4 * (p[:, 0] > 0.2).float()), est, o, d, 0.3)
    torch.testing.assert_close(wall[:2], torch.full((2,), 3.2), atol=spacing, rtol=0)
    torch.testing.assert_close(wall[2], torch.tensor(2.0), atol=spacing, rtol=0)
    assert math.isinf(float(wall[3]))


def test_several_levels_read_off_one_render_match_one_level_each():
    est = StratifiedEstimator(400, scene_box=BOX)
    o = torch.tensor([[-3.0, 0.0, 0.0], [-3.0, 0.2, 0.1], [0.5, -3.0, 0.0], [-3.0, 5.0, 0.0]])
    d = torch.tensor([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]])
    field = _field(lambda p: 2.0 + 3.0 * p[:, 0].clamp_min(0))     # density rising along +x
    levels = [0.05, 0.3, 0.9]
    both = free_distances(field, est, o, d, levels, chunk=3)       # chunks split the rays
    assert both.shape == (4, 3)
    for k, level in enumerate(levels):
        assert torch.equal(both[:, k], free_distances(field, est, o, d, level)), level
    # constant density 2 on the ray along +y at x = 0.5 is 2 + 1.5: opacity 1 - exp(-3.5 s) reaches each level
    want = torch.tensor([2.0 + math.log(1 / (1 - x)) / 3.5 for x in levels])
    torch.testing.assert_close(both[2], want, atol=2.0 / 400, rtol=0)
    assert torch.isinf(both[3]).all()


def test_free_segments_follow_the_box_and_the_margin():
    o = torch.tensor([[-3.0, 0.0, 0.0], [-3.0, 0.0, 0.0], [-3.0, 0.0, 0.0], [-3.0, 5.0, 0.0]])
    d = torch.tensor([[1.0, 0.0, 0.0]] * 4)
    dist = torch.tensor([3.2, 2.03, math.inf, 3.0])     # a wall at x = 0.2; one at 0.03 past the box entry;
    free = FreeRays.from_distances(o, d, dist, BOX, margin=0.05)   # never opaque; a ray beside the box
    assert len(free) == 2                                # the 0.03 stretch is under the margin, the miss has none
    torch.testing.assert_close(free.near, torch.tensor([2.0, 2.0]))
    torch.testing.assert_close(free.far, torch.tensor([3.15, 4.0]))     # margin; the box exit
    pts, length = free.sample(20000, torch.Generator().manual_seed(1))
    assert torch.all(torch.isclose(length, torch.tensor(1.15)) | torch.isclose(length, torch.tensor(2.0)))
    assert torch.all(pts[:, 1:] == 0) and pts[:, 0].min() >= -1.0 and pts[:, 0].max() <= 1.0
    # half the draws on each ray: uniform on [-1, 0.15] and on [-1, 1]: mean (-0.425 + 0) / 2
    assert abs(float(pts[:, 0].mean()) - (-0.2125)) < 0.01
    # shortened by 1.5: the first ray has nothing left (its near point, length 0), the second [-1, -0.5]
    pts, length = free.sample(20000, torch.Generator().manual_seed(2), shorten=1.5)
    first = length == 0
    assert 0.45 < float(first.float().mean()) < 0.55
    torch.testing.assert_close(pts[first], torch.tensor([-1.0, 0.0, 0.0]).expand(int(first.sum()), 3))
    torch.testing.assert_close(length[~first], torch.full((int((~first).sum()),), 0.5))
    assert pts[~first, 0].min() >= -1.0 and pts[~first, 0].max() <= -0.5
    assert abs(float(pts[~first, 0].mean()) - (-0.75)) < 0.01


def _uniform_draw(free, radius, g):
    pts = free.sample(256, g)[0]
    return pts, torch.ones(pts.shape[0])


def _resampled_draw(free, radius, g):
    from l3d_app.render.volume.free_space import near_surface_weight
    pts, _, w = free.sample_resampled(256, 8, lambda p: near_surface_weight(p.norm(dim=-1) - radius, 0.05), g)
    return pts, w


@pytest.mark.parametrize("draw", [_uniform_draw, _resampled_draw])
def test_carving_on_free_segments_shrinks_a_sphere_out_of_them(draw):
    """A sphere of radius 0.8 about the origin, rays along +x free up to x = -0.5: the loss
    mean(relu(-f)) at points drawn on the free stretch (uniformly, or resampled near the current
    surface with importance weights: the same expectation) leaves the radius at the stretch's end."""
    o = torch.tensor([[-3.0, 0.0, 0.0]])
    free = FreeRays.from_distances(o, torch.tensor([[1.0, 0.0, 0.0]]), torch.tensor([2.55]), BOX, margin=0.05)
    radius = torch.nn.Parameter(torch.tensor(0.8))
    opt = torch.optim.SGD([radius], lr=0.05)
    g = torch.Generator().manual_seed(0)
    for _ in range(300):
        opt.zero_grad()
        pts, w = draw(free, radius, g)
        (torch.relu(radius - pts.norm(dim=-1)) * w).mean().backward()
        opt.step()
    assert 0.49 < float(radius.detach()) <= 0.56                   # just out of the stretch [-1, -0.5], not beyond


def _three_rays():
    o = torch.tensor([[-3.0, 0.0, 0.0], [-3.0, 0.3, 0.0], [0.6, -3.0, 0.2]], dtype=torch.float64)
    d = torch.tensor([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]], dtype=torch.float64)
    return FreeRays.from_distances(o, d, torch.tensor([3.2, math.inf, 2.7], dtype=torch.float64), BOX, margin=0.05)


def _shell(points):      # a loss term living on a thin shell about x = 0.1 (as a free loss lives near surfaces)
    return torch.exp(-(points[:, 0] - 0.1).abs() / 0.02)


def test_resampled_free_points_keep_the_expectation_and_cut_its_variance():
    """E[mean(g(x) w)] under importance resampling equals the uniform draw's E[g] (a float64 quadrature
    along each free segment), for a g on a thin shell; the resampled estimate's spread is far smaller."""
    free = _three_rays()
    t = torch.linspace(0, 1, 200001, dtype=torch.float64)
    want = 0.0
    for i in range(len(free)):           # E over the uniform draw: mean over rays of the segment-average of g x length
        pts = free.origins[i] + (free.near[i] + t * (free.far[i] - free.near[i]))[:, None] * free.dirs[i]
        length = free.far[i] - free.near[i]
        want += float(torch.trapezoid(_shell(pts) * length, t)) / len(free)
    g = torch.Generator().manual_seed(3)
    uniform, resampled = [], []
    for _ in range(400):
        pts, length = free.sample(256, g)
        uniform.append(float((_shell(pts) * length).mean()))
        pts, length, w = free.sample_resampled(256, 16, _shell, g)
        assert float(w.max()) <= 2.0 + 1e-12
        resampled.append(float((_shell(pts) * length * w).mean()))
    uniform, resampled = torch.tensor(uniform, dtype=torch.float64), torch.tensor(resampled, dtype=torch.float64)
    for est in (uniform, resampled):     # within 4 standard errors of the quadrature
        assert abs(float(est.mean()) - want) < 4 * float(est.std()) / math.sqrt(len(est)) + 1e-9
    assert float(resampled.std()) < 0.5 * float(uniform.std())


def test_resampling_without_the_proposal_is_the_uniform_draw():
    """mix 0: every weight is 1 and the points are uniform candidates (the x-mean of the draw as
    :meth:`sample`'s: rays 1 and 2 along x, ray 3 at x = 0.1)."""
    free = _three_rays()
    pts, length, w = free.sample_resampled(30000, 4, _shell, torch.Generator().manual_seed(4), mix=0.0)
    assert torch.all(w == 1.0)
    want = (float(free.near[0] + free.far[0]) / 2 - 3.0 + float(free.near[1] + free.far[1]) / 2 - 3.0 + 0.6) / 3
    assert abs(float(pts[:, 0].mean()) - want) < 0.01
    with pytest.raises(ValueError, match="mix"):
        free.sample_resampled(8, 2, _shell, None, mix=1.0)


def test_near_surface_weight_is_the_laplace_shape():
    from l3d_app.render.volume.free_space import near_surface_weight
    torch.testing.assert_close(near_surface_weight(torch.tensor([0.0, 0.1, -0.1]), 0.1),
                               torch.tensor([1.0, math.exp(-1), math.exp(-1)]))
    with pytest.raises(ValueError, match="width"):
        near_surface_weight(torch.zeros(1), 0.0)
