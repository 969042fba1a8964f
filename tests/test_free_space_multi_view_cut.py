"""The multi-view cut of known free stretches (``free_space.ray_cut=multi_view``): other views' end
points against ray-plane distances in closed form (float64), and :meth:`FreeRays.multi_view_cut`
moving only the ends that lie behind another view's surface."""

import torch

from l3d_app.geometry.cameras import look_at_cameras
from l3d_app.geometry.rays import camera_rays
from l3d_app.render.volume.free_space import FreeRays, nearest_other_view_ends

HW = 32 * 32


def _two_views_over_a_plane():
    """Two cameras over the plane y = 0: view-major rays (float64) and each ray's distance to the
    plane (+inf: the ray points away from it)."""
    cams = look_at_cameras(4.0, [60.0, 45.0], [0.0, 25.0], 40.0, 32).to(dtype=torch.float64)
    o, d = camera_rays(cams)
    o, d = o.reshape(-1, 3).double(), d.reshape(-1, 3).double()
    t = torch.where(d[:, 1] < 0, -o[:, 1] / d[:, 1], torch.full_like(d[:, 1], float("inf")))
    return cams, o, d, t


def test_nearest_other_view_ends_finds_the_other_views_plane_in_front_of_ends_set_behind_it():
    """View 0's ends are put 0.5 behind the plane, view 1's on it: view 0 gets view 1's plane points
    (its own ray-plane distance, to within a pixel's depth change), view 1 gets nothing (view 0's
    points lie behind the plane it sees)."""
    cams, o, d, t = _two_views_over_a_plane()
    ends = t.clone()
    ends[:HW] += 0.5
    cut = nearest_other_view_ends(cams, o, d, ends, ends, tol=0.02)
    zero, one = cut[:HW], cut[HW:]
    assert torch.isinf(one).all()
    fin = torch.isfinite(zero)
    assert float(fin.float().mean()) > 0.5     # measured 0.67: view 1 covers part of it, one point per pixel (holes)
    assert float((zero[fin] - t[:HW][fin]).abs().max()) < 0.1


def test_free_rays_cut_moves_only_the_ends_behind_another_views_surface():
    """The stage's distances: view 0's 0.5 behind the plane, view 1's on it (margin 0.05, tol 0.02).
    View 0's ends that view 1 covers become the plane distance + tol - margin (to within a pixel's
    depth change); its others, view 1's, the rays that never became opaque and the -inf ones keep theirs."""
    cams, o, d, t = _two_views_over_a_plane()
    margin, tol, box = 0.05, 0.02, ((-3.0, -1.0, -3.0), (3.0, 3.0, 3.0))
    dist = t.clone()
    dist[:HW] += 0.5
    free = FreeRays.from_distances(o, d, dist, box, margin)
    ends = free.ends_per_ray(2 * HW)
    got = free.multi_view_cut(ends, cams, o, d, margin, tol)
    moved = got < ends
    assert not bool(moved[HW:].any())
    assert torch.equal(got[~moved], ends[~moved])          # untouched ends bit for bit (inf, -inf, box exits)
    zero = moved[:HW]
    assert float(zero.float().mean()) > 0.5
    assert float((got[:HW][zero] - (t[:HW][zero] + tol - margin)).abs().max()) < 0.1
    assert float((got[:HW][zero] - ends[:HW][zero]).min()) < -0.4     # the 0.5 behind is cut back
    opaque_never = torch.isinf(dist)
    assert torch.equal(got[opaque_never], ends[opaque_never])
