"""task=pca_normals on the built-in room: statistics against the mesh's closed forms, normals and classes."""

import json
import math

import pytest
import torch

from l3d_app.app import run_task
from l3d_app.data.room_scene import room_mesh, room_points
from l3d_app.geometry.surface_orientation import (HORIZONTAL, OTHER, VERTICAL, classify_orientation,
                                                  unsigned_angle_deg)


def test_classify_and_angles_on_known_vectors():
    t = math.radians(10)
    n = torch.tensor([[0, 1, 0], [0, -1, 0], [1, 0, 0], [0, math.sin(t), math.cos(t)],
                      [0, math.cos(t), math.sin(t)], [1, 1, 0]], dtype=torch.float64)
    assert classify_orientation(n, tolerance_deg=15).tolist() == [HORIZONTAL, HORIZONTAL, VERTICAL, VERTICAL,
                                                                  HORIZONTAL, OTHER]
    assert classify_orientation(n, tolerance_deg=5).tolist()[3:5] == [OTHER, OTHER]
    a = unsigned_angle_deg(torch.tensor([[0.0, 1, 0], [1, 0, 0]]), torch.tensor([[0.0, -1, 0], [1, 1, 0]]))
    assert a.tolist() == pytest.approx([0.0, 45.0], abs=1e-4)


def _area_centroid(mesh):
    fv = mesh.verts[mesh.faces].double()                              # (F, 3, 3)
    area = 0.5 * torch.cross(fv[:, 1] - fv[:, 0], fv[:, 2] - fv[:, 0], dim=-1).norm(dim=-1)
    return (area[:, None] * fv.mean(1)).sum(0) / area.sum()


def test_room_points_lie_on_the_room():
    cloud = room_points(5000, noise=0.0, seed=1)
    assert cloud.points.shape == (5000, 3) and cloud.normals is not None and cloud.colors is not None
    lo, hi = cloud.points.min(0).values, cloud.points.max(0).values
    assert lo.tolist() == pytest.approx([-2, 0, -2], abs=0.06) and hi.tolist() == pytest.approx([2, 2.5, 2], abs=0.06)
    assert torch.allclose(cloud.normals.norm(dim=-1), torch.ones(5000))


def test_pca_normals_task_on_the_clean_room(compose, tmp_path):
    run_task(compose("task=pca_normals", "data.num_samples=8000", "data.noise=0", "image_size=64"), out_dir=tmp_path)
    m = json.loads((tmp_path / "metrics.json").read_text())
    assert m["count"] == 8000
    centroid = _area_centroid(room_mesh())
    # sample mean of 8000 area-uniform points: std per axis < 1.5 / sqrt(8000) = 0.017
    assert m["centroid"] == pytest.approx(centroid.tolist(), abs=0.06)
    assert m["bounds_min"] == pytest.approx([-2, 0, -2], abs=0.06)
    assert m["bounds_max"] == pytest.approx([2, 2.5, 2], abs=0.06)
    assert m["angle_error_median_deg"] < 0.5        # planes are exact away from edges
    assert m["class_accuracy"] > 0.9
    assert m["fraction_vertical"] > m["fraction_horizontal"] > m["fraction_other"]
    assert (tmp_path / "normals.png").stat().st_size > 0
