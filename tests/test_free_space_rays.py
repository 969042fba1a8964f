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


def test_chunks_do_not_change_the_distances_of_a_rising_density():
    est = StratifiedEstimator(400, scene_box=BOX)
    o = torch.tensor([[-3.0, 0.0, 0.0], [-3.0, 0.2, 0.1], [0.5, -3.0, 0.0], [-3.0, 5.0, 0.0]])
    d = torch.tensor([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]])
    field = _field(lambda p: 2.0 + 3.0 * p[:, 0].clamp_min(0))     # density rising along +x
    chunked = free_distances(field, est, o, d, 0.3, chunk=3)       # chunks split the rays
    assert torch.equal(chunked, free_distances(field, est, o, d, 0.3))
    # constant density 2 on the ray along +y at x = 0.5 is 2 + 1.5: opacity 1 - exp(-3.5 s) reaches 0.3
    torch.testing.assert_close(chunked[2], torch.tensor(2.0 + math.log(1 / 0.7) / 3.5), atol=2.0 / 400, rtol=0)
    assert torch.isinf(chunked[3])


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


def test_carving_on_free_segments_shrinks_a_sphere_out_of_them():
    """A sphere of radius 0.8 about the origin, rays along +x free up to x = -0.5: the loss
    mean(relu(-f)) at points drawn uniformly on the free stretch leaves the radius at the stretch's end."""
    o = torch.tensor([[-3.0, 0.0, 0.0]])
    free = FreeRays.from_distances(o, torch.tensor([[1.0, 0.0, 0.0]]), torch.tensor([2.55]), BOX, margin=0.05)
    radius = torch.nn.Parameter(torch.tensor(0.8))
    opt = torch.optim.SGD([radius], lr=0.05)
    g = torch.Generator().manual_seed(0)
    for _ in range(300):
        opt.zero_grad()
        pts = free.sample(256, g)[0]
        torch.relu(radius - pts.norm(dim=-1)).mean().backward()
        opt.step()
    assert 0.49 < float(radius.detach()) <= 0.56                   # just out of the stretch [-1, -0.5], not beyond
