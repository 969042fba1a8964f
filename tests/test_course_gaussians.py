"""The course's Gaussian pictures: the four-view progress grid with its ground-truth row, the 32-view
render path (against the closed-form camera placement), init_points subsampling."""

from __future__ import annotations

import json
import math

import numpy as np
import torch
from omegaconf import OmegaConf

from l3d_app.app import run_task
from l3d_app.geometry.course_orbit import course_orbit
from l3d_app.geometry.gaussian_ply import save_gaussian_ply
from l3d_app.models.gaussians import init_from_points
from l3d_app.render.gaussians.progress_grid import progress_grid


def test_progress_grid_puts_four_views_over_their_truth():
    pred = torch.rand(5, 4, 6, 3, generator=torch.Generator().manual_seed(0))
    truth = torch.rand(5, 4, 6, 3, generator=torch.Generator().manual_seed(1))
    grid = progress_grid(pred, truth)
    assert grid.shape == (8, 24, 3)
    for k in range(4):
        torch.testing.assert_close(grid[:4, 6 * k:6 * (k + 1)], pred[k])
        torch.testing.assert_close(grid[4:, 6 * k:6 * (k + 1)], truth[k])
    assert progress_grid(pred[:2], truth[:2]).shape == (8, 12, 3)          # fewer views: all of them


def test_course_orbit_matches_the_closed_form_placement():
    at = torch.tensor([0.5, -0.2, 1.0])
    cams = course_orbit(256, at.tolist())
    assert len(cams) == 32 and float(cams.fx[0]) == 5 * 128 and float(cams.cx[0]) == 128
    a = torch.deg2rad(torch.linspace(-180.0, 180.0, 32, dtype=torch.float64))
    e = math.radians(30.0)
    eyes = at.double() + 6.0 * torch.stack([math.cos(e) * torch.sin(a), math.sin(e) + 0 * a,
                                             math.cos(e) * torch.cos(a)], -1)
    torch.testing.assert_close(cams.centers().double(), eyes, atol=1e-5, rtol=0)
    # the centre projects to the principal point; a point 0.1 along -y (the course's up) lies above it
    for p, above in ((at, None), (at + torch.tensor([0.0, -0.1, 0.0]), True)):
        x = (cams.R @ p + cams.t)                                           # (32, 3) camera coordinates
        u, v = cams.fx * x[:, 0] / x[:, 2] + cams.cx, cams.fy * x[:, 1] / x[:, 2] + cams.cy
        if above is None:
            torch.testing.assert_close(torch.stack([u, v], -1), torch.full((32, 2), 128.0), atol=1e-3, rtol=0)
        else:
            assert bool((v < 128 - 5).all())


def test_gs_render_course_path_writes_32_frames(compose, tmp_path):
    g = torch.Generator().manual_seed(1)
    m = init_from_points(0.3 * torch.rand(150, 3, generator=g) + torch.tensor([2.0, 0.0, 0.0]), opacity=0.9)
    save_gaussian_ply(tmp_path / "g.ply", **m.tensors())
    run_task(compose("task=gs_render", f"ply={tmp_path / 'g.ply'}", "path=course", "image_size=24",
                     "tensorboard=false"), out_dir=tmp_path / "run")
    import imageio.v2 as imageio

    frames = imageio.mimread(tmp_path / "run" / "turntable.gif")
    out = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert len(frames) == 32 and frames[0].shape[:2] == (24, 72) and out["depth_range"] == [5.0, 7.0]
    mask = torch.from_numpy(np.stack([f[:, 48:, 0] > 127 for f in frames])).float()       # the cloud, centred on its mean
    ys, xs = torch.meshgrid(torch.arange(24.0), torch.arange(24.0), indexing="ij")
    for k in (0, 8, 16):
        w = mask[k]
        assert w.sum() > 4 and abs(float((w * xs).sum() / w.sum()) - 11.5) < 3 and abs(
            float((w * ys).sum() / w.sum()) - 11.5) < 3


def test_init_points_keeps_a_seeded_subset_of_the_data_points():
    from l3d_app.pipelines.splats import initial_splats

    def _initial_model(cfg, raw, data, generator):
        return initial_splats(raw, data, generator, cfg.n_init, cfg.init_colors, cfg.init_opacity, cfg.isotropic,
                              cfg.init_scale, cfg.init_max_coverage, init_points=cfg.init_points)

    pts = torch.rand(500, 3, generator=torch.Generator().manual_seed(3))
    raw = type("Raw", (), {"points": pts, "point_colors": pts.flip(-1)})()
    cfg = OmegaConf.create({"init_points": 100, "n_init": 10, "init_colors": "points", "init_opacity": 0.1,
                            "isotropic": True, "init_scale": 1.0, "init_max_coverage": 0.0, "data": {"name": "x"}})
    data = type("Data", (), {"images": torch.zeros(1, 2, 2, 3)})()
    model = _initial_model(cfg, raw, data, torch.Generator().manual_seed(0))
    means = model.means.detach()
    assert model.num == 100 and len(set(map(tuple, means.tolist()))) == 100
    match = (means[:, None] - pts[None]).abs().sum(-1).argmin(-1)          # each kept point is one of the data's
    torch.testing.assert_close(pts[match], means)
    again = _initial_model(cfg, raw, data, torch.Generator().manual_seed(0)).means.detach()
    torch.testing.assert_close(again, means)                                # seeded
    cfg.init_points = 0
    assert _initial_model(cfg, raw, data, torch.Generator().manual_seed(0)).num == 500
