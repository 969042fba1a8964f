"""render360 points_beside=true: the sampled points sit on the mesh's silhouette, frame by frame."""

import json

import imageio.v2 as imageio
import numpy as np
import pytest
import torch

from l3d_app.app import run_task
from l3d_app.errors import UserError


def _dilate(mask, r=1):
    t = torch.from_numpy(mask.astype(np.float32))[None, None]
    return (torch.nn.functional.max_pool2d(t, 2 * r + 1, stride=1, padding=r)[0, 0] > 0).numpy()


def test_points_beside_the_mesh(compose, tmp_path):
    cfg = compose("task=render360", "data.scene=torus", "image_size=48", "num_frames=3", "points_beside=true",
                  "points_beside_samples=4000", "point_renderer.radius=1.0")
    run_task(cfg, out_dir=tmp_path)
    m = json.loads((tmp_path / "metrics.json").read_text())
    assert m["points_beside_samples"] == 4000
    frames = imageio.mimread(tmp_path / "turntable.gif")
    assert len(frames) == 3
    for frame in frames:
        frame = np.asarray(frame)[..., :3].astype(int)
        assert frame.shape[:2] == (48, 96)
        mesh, points = frame[:, :48].sum(-1) < 740, frame[:, 48:].sum(-1) < 740   # not white background
        assert points.sum() > 0.4 * mesh.sum()                          # the points show the shape
        assert (points & ~_dilate(mesh)).sum() <= 0.03 * points.sum()   # and only where the mesh is


def test_points_beside_needs_a_mesh(compose, tmp_path):
    with pytest.raises(UserError, match="points_beside"):
        run_task(compose("task=render360", "data=torus_parametric", "image_size=16", "num_frames=1",
                         "points_beside=true"), out_dir=tmp_path)
