"""neural_sdf on the course's real bunny point cloud (../shared/data/bunny; skipped when absent)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from l3d_app.app import run_task
from conftest import course_data


def test_bunny_loader_keeps_every_second_point_centred():
    path = course_data("bunny", "bunny_pointcloud.npz")
    from l3d_app.data.bunny import bunny_points

    verts = np.load(path)["verts"].astype(np.float64)[::2]
    cloud = bunny_points(str(path))
    assert cloud.points.shape == (5000, 3)
    np.testing.assert_allclose(cloud.points.double().numpy(), verts - verts.mean(0), atol=1e-6)


def test_course_neural_sdf_on_the_bunny_beats_its_initial_sphere(compose, tmp_path):
    """The course's loss and network on the real cloud; a faster rate than the course's 1e-4 so that 25 steps
    show it: the untrained sphere reads F1@0.05 0.16, chamfer 0.34 against the cloud (measured, 32^3 mesh)."""
    path = course_data("bunny", "bunny_pointcloud.npz")
    cfg = compose("experiment=course_neural_sdf", f"data.path={path}", "iters=25", "lr=0.001", "batch_points=512",
                  "eval_every=1000", "gif_frames=0", "mesh_resolution=32", "eval_points=2000", "tensorboard=false")
    assert (cfg.model.n_layers, cfg.model.hidden, cfg.model.n_frequencies, cfg.w_eikonal, cfg.w_offsurface) == \
        (6, 128, 4, 0.02, 0.1)
    run_task(cfg, out_dir=tmp_path / "run")
    m = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert m["n_points"] == 5000 and m["mesh_faces"] > 500
    assert m["f1"] > 0.5 and m["chamfer"] < 0.15, m
    assert (tmp_path / "run" / "mesh.ply").stat().st_size > 0 and torch.isfinite(torch.tensor(m["val_surface_abs"]))
