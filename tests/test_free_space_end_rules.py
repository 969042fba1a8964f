"""bench/free_space_end_rules.py's helpers against hand-built references: the plain-pixel measure
against a naive window loop, the multi-view cut against ray-plane distances in closed form."""

import torch

from bench_scripts import load_bench_script
from l3d_app.geometry.cameras import look_at_cameras
from l3d_app.geometry.rays import camera_rays


def _rules():
    return load_bench_script("free_space_end_rules")


def test_plain_texture_matches_a_naive_window_loop():
    g = torch.Generator().manual_seed(0)
    img = torch.rand(2, 7, 9, 3, generator=g, dtype=torch.float64)
    got = _rules().plain_texture(img, 5)
    want = torch.empty(2, 7, 9, dtype=torch.float64)
    for v in range(2):
        for y in range(7):
            for x in range(9):
                win = img[v, max(0, y - 2):y + 3, max(0, x - 2):x + 3].reshape(-1, 3)   # inside the image only
                want[v, y, x] = win.std(0, unbiased=False).mean()
    torch.testing.assert_close(got, want)
    assert float(_rules().plain_texture(torch.full((1, 6, 6, 3), 0.4), 5).abs().max()) < 1e-6


def test_multi_view_cut_finds_the_other_views_plane_in_front_of_ends_set_behind_it():
    """Two cameras over the plane y = 0. View 0's ends are put 0.5 behind the plane, view 1's on it: view 0
    gets view 1's plane points (its own ray-plane distance, to within a pixel's depth change), view 1 gets
    nothing (view 0's points lie behind the plane it sees)."""
    cams = look_at_cameras(4.0, [60.0, 45.0], [0.0, 25.0], 40.0, 32)
    o, d = camera_rays(cams)
    o, d = o.reshape(-1, 3).double(), d.reshape(-1, 3).double()
    t = torch.where(d[:, 1] < 0, -o[:, 1] / d[:, 1], torch.full_like(d[:, 1], float("inf")))   # ray-plane
    hw = 32 * 32
    ends = t.clone()
    ends[:hw] += 0.5
    cams = cams.to(dtype=torch.float64)
    cut = _rules().nearest_other_view_ends(cams, o, d, ends, ends, tol=0.02)
    zero, one = cut[:hw], cut[hw:]
    assert torch.isinf(one).all()
    fin = torch.isfinite(zero)
    assert float(fin.float().mean()) > 0.5     # measured 0.67: view 1 covers part of it, one point per pixel (holes)
    assert float((zero[fin] - t[:hw][fin]).abs().max()) < 0.1
