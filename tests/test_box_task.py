from pathlib import Path
"""The box task: recovery of the course's SDF box from its four images; input errors."""

import json

import numpy as np
import pytest
import torch

from l3d_app.app import run_task
from l3d_app.data.box_images import box_cameras, load_box_images
from l3d_app.errors import UserError
from l3d_app.runtime.paths import resolve_path
from l3d_app.models.sdf_box import SDFBox
from conftest import course_data

TRUE_CENTER, TRUE_SIZE = (0.25, 0.25, 0.0), (2.0, 1.5, 1.5)


def test_box_cameras_match_the_readme():
    cams = box_cameras(dtype=torch.float64)
    torch.testing.assert_close(cams.centers(), torch.tensor(
        [[-2.5, 0, 0], [-1.0, 0, -2.2], [0, 0, -2.5], [1.0, 0, -2.2]], dtype=torch.float64))
    uv, depth = cams.project(torch.zeros(1, 3, dtype=torch.float64))   # the origin is at the centre
    torch.testing.assert_close(uv[:, 0], torch.full((4, 2), 128.0, dtype=torch.float64))
    # world up (+Y) projects upwards (smaller v); NDC focal 1 = 128 px on a 256 image
    up_uv, _ = cams.project(torch.tensor([[0.0, 0.5, 0.0]], dtype=torch.float64))
    assert (up_uv[:, 0, 1] < 128).all() and float(cams.fx[0]) == 128.0


def test_ground_truth_box_reproduces_the_images():
    data = load_box_images(str(course_data("box")))
    from l3d_app.geometry.rays import camera_rays
    from l3d_app.render.volume.renderer import render_rays_chunked
    model = SDFBox(TRUE_CENTER, TRUE_SIZE)
    o, d = camera_rays(data.cameras)
    o, d = o[:, ::8, ::8], d[:, ::8, ::8]
    with torch.no_grad():
        img = render_rays_chunked(model.render_rays, o, d, 8192)["color"]
    assert float((img - data.images[:, ::8, ::8]).abs().max()) < 1e-4


def test_box_task_recovers_the_box(compose, tmp_path):
    course_data("box")
    cfg = compose("task=box", "iters=250", "batch_rays=256", "eval_every=0", "gif_frames=4",
                  "turntable_size=16", "tensorboard=false")
    run_task(cfg, out_dir=tmp_path)
    metrics = json.loads((tmp_path / "metrics.json").read_text())
    for got, want in zip(metrics["box_center"] + metrics["box_size"], TRUE_CENTER + TRUE_SIZE):
        assert abs(got - want) < 0.005, metrics
    assert metrics["center_error"] < 0.005 and metrics["size_error"] < 0.005
    assert metrics["psnr"] > 40 and metrics["iters"] == 250
    assert (tmp_path / "turntable.gif").exists() and (tmp_path / "fit_views.png").exists()
    import imageio.v2 as imageio

    ba = imageio.imread(tmp_path / "before_after.png").astype(np.float64) / 255     # before / after / images
    h = ba.shape[0] // 3
    before_err, after_err = np.abs(ba[:h] - ba[2 * h:]).mean(), np.abs(ba[h:2 * h] - ba[2 * h:]).mean()
    assert after_err < 0.25 * before_err, (before_err, after_err)


def test_render_mode_draws_the_true_box_without_training(compose, tmp_path):
    """mode=render with the true box reproduces the course's images (133 dB) and draws the
    depth picture the course shows; a wrong box does not."""
    import imageio.v2 as imageio

    course_data("box")
    common = ("task=box", "mode=render", "gif_frames=2", "turntable_size=16", "tensorboard=false", "threads=1")
    run_task(compose(*common), out_dir=tmp_path / "true")
    m = json.loads((tmp_path / "true" / "metrics.json").read_text())
    assert m["render_psnr"] > 100 and "iters" not in m
    depth = imageio.imread(tmp_path / "true" / "depth.png")
    assert depth.shape == (16, 16, 3) and (tmp_path / "true" / "turntable.gif").exists()
    run_task(compose(*common, "render_size=[1.5,1.5,1.5]"), out_dir=tmp_path / "wrong")
    assert json.loads((tmp_path / "wrong" / "metrics.json").read_text())["render_psnr"] < 30


def test_missing_root_is_a_user_error(compose, tmp_path):
    cfg = compose("task=box", f"data.root={tmp_path / 'nowhere'}", "iters=1")
    with pytest.raises(UserError, match="nowhere"):
        run_task(cfg, out_dir=tmp_path / "run")


def test_missing_file_and_wrong_size_are_user_errors(tmp_path):
    for i in range(3):
        np.save(tmp_path / f"box_{i}.npy", np.zeros((256, 256, 3), np.float32))
    with pytest.raises(UserError, match="box_3.npy"):
        load_box_images(str(tmp_path))
    np.save(tmp_path / "box_3.npy", np.zeros((128, 128, 3), np.float32))
    with pytest.raises(UserError, match="shape"):
        load_box_images(str(tmp_path))


def test_paths_resolve_against_cwd_then_repository():
    from conftest import REPO
    assert resolve_path("conf") == (REPO / "conf").resolve()
    assert str(resolve_path("/abs/path")) == "/abs/path"
    assert resolve_path("no/such/dir") == Path.cwd() / "no/such/dir"
