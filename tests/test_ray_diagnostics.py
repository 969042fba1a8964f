"""task=ray_diagnostics and task=sphere_trace against closed forms."""

import json
import math

import imageio.v2 as imageio
import numpy as np
import pytest
import torch

from l3d_app.app import run_task
from l3d_app.errors import UserError
from l3d_app.geometry.cameras import look_at_cameras
from l3d_app.render.volume.diagnostics import pixel_grid_image, ray_direction_image, ray_sample_points


def test_pixel_grid_matches_the_course_formula():
    img = pixel_grid_image(4, 6)
    # pixel (row 1, col 4): centre (4.5, 1.5) -> x = 4.5/6*2-1 = 0.5, y = 1.5/4*2-1 = -0.25
    assert img[1, 4].tolist() == pytest.approx([(0.5 + 1) / 2.001, (-0.25 + 1) / 2.001, 0.0], abs=1e-6)
    assert float(img.min()) >= 0 and float(img.max()) < 1


def test_ray_directions_and_samples_lie_on_the_pixel_rays():
    cams = look_at_cameras(3.0, 0.0, 0.0, 90.0, 4)                 # camera on +Z looking at the origin
    dirs = ray_direction_image(cams)[0]
    # fov 90 on 4 px: f = 2; pixel (0, 0) centre (0.5, 0.5) -> camera dir (-0.75, -0.75, 1) normalised
    n = math.sqrt(0.75 ** 2 * 2 + 1)
    assert dirs[0, 0].tolist() == pytest.approx([0.75 / n, 0.75 / n, 1 / n], abs=1e-6)
    pts, t = ray_sample_points(cams, 1.0, 5.0, 3, stride=1)
    assert t[:3].tolist() == pytest.approx([1.0, 3.0, 5.0])
    centre = torch.tensor([0.0, 0.0, 3.0])
    assert (pts - centre).norm(dim=-1).tolist() == pytest.approx(t.tolist(), abs=1e-5)  # |p - C| = t
    uv, _ = cams.project(pts)
    expected = torch.tensor([[j + 0.5, i + 0.5] for i in range(4) for j in range(4)]).repeat_interleave(3, 0)
    assert torch.allclose(uv[0], expected, atol=1e-4)               # every sample projects to its pixel


def test_ray_diagnostics_task_writes_pictures_and_closed_form_checks(compose, tmp_path):
    cfg = compose("task=ray_diagnostics", "image_size=48", "n_samples=8", "stride=4", "fov=70")
    run_task(cfg, out_dir=tmp_path)
    m = json.loads((tmp_path / "metrics.json").read_text())
    f = 24 / math.tan(math.radians(35))
    assert m["corner_ray_angle_deg"] == pytest.approx(math.degrees(math.atan(math.hypot(23.5, 23.5) / f)), abs=1e-3)
    assert m["max_dir_norm_error"] < 1e-5 and m["n_sample_points"] == 12 * 12 * 8
    for name in ("pixel_grid", "ray_directions", "sample_points", "sample_points_camera"):
        img = imageio.imread(tmp_path / f"{name}.png")
        assert img.shape[:2] == (48, 48)
    side = imageio.imread(tmp_path / "sample_points.png").astype(float)
    assert 0.01 < (side.sum(-1) < 700).mean() < 0.6                  # the frustum is visible, not everything


def _analytic_sphere_coverage(size, dist, elev, fov, radius, frames):
    """Fraction of pixel-centre rays whose line passes within ``radius`` of the origin (camera outside)."""
    f = size / 2 / math.tan(math.radians(fov) / 2)
    c = np.arange(size) + 0.5 - size / 2
    x, y = np.meshgrid(c / f, c / f)
    # the camera looks at the origin from distance dist: the ray's closest distance to the origin is
    # dist * sin(angle to the optical axis), the same for every azimuth and elevation
    sin_angle = np.sqrt((x ** 2 + y ** 2) / (1 + x ** 2 + y ** 2))
    return float((dist * sin_angle < radius).mean())


def test_sphere_trace_coverage_matches_the_analytic_sphere(compose, tmp_path):
    cfg = compose("task=sphere_trace", "data=sphere_implicit", "image_size=48", "num_frames=2", "fov=40")
    run_task(cfg, out_dir=tmp_path)
    m = json.loads((tmp_path / "metrics.json").read_text())
    assert m["hit_fraction"] == pytest.approx(_analytic_sphere_coverage(48, 3.0, 30.0, 40.0, 0.8, 2), abs=0.004)
    assert m["max_abs_sdf_at_hits"] <= 1e-3
    assert len(imageio.mimread(tmp_path / "turntable.gif")) == 2


def test_sphere_trace_torus_and_bad_data(compose, tmp_path):
    run_task(compose("task=sphere_trace", "image_size=32", "num_frames=2"), out_dir=tmp_path)
    m = json.loads((tmp_path / "metrics.json").read_text())
    assert m["shape"] == "torus" and 0.1 < m["hit_fraction"] < 0.6 and m["max_abs_sdf_at_hits"] <= 1e-3
    with pytest.raises(UserError, match="implicit"):
        run_task(compose("task=sphere_trace", "data=builtin", "image_size=16", "num_frames=1"),
                 out_dir=tmp_path / "bad")
    assert not (tmp_path / "bad" / "metrics.json").exists()
