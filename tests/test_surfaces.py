"""Parametric point clouds, implicit meshes from configs, and the surface_tradeoff task."""

import json
import math

import pytest
import torch

import l3d_app.data  # noqa: F401  (registers the data sources)
from l3d_app.app import run_task
from l3d_app.errors import UserError
from l3d_app.geometry.mesh import Mesh
from l3d_app.geometry.parametric import superquadric_points, torus_points
from l3d_app.geometry.pointcloud import PointCloud
from l3d_app.geometry.sdf import Superquadric, Torus
from l3d_app.registry import DATASETS


def gen(seed=0):
    return torch.Generator().manual_seed(seed)


@pytest.mark.parametrize("area_uniform", [False, True])
def test_torus_points_on_surface(area_uniform):
    cloud = torus_points(5000, 0.7, 0.3, gen(), area_uniform=area_uniform, dtype=torch.float64)
    assert cloud.points.shape == (5000, 3)
    assert Torus(0.7, 0.3)(cloud.points).abs().max() < 1e-12
    # normals point outward: a small step along them increases the SDF by the step
    stepped = Torus(0.7, 0.3)(cloud.points + 1e-3 * cloud.normals)
    assert torch.allclose(stepped, torch.full_like(stepped, 1e-3), atol=1e-9)
    assert cloud.colors.min() >= 0 and cloud.colors.max() <= 1


def test_torus_area_uniform_vs_parameter_uniform():
    # area element ~ (R + r cos v): the outer half (x^2+z^2 > R^2) holds (pi R + 2r)/(2 pi R)
    R, r = 0.7, 0.3
    outer = lambda c: (c.points[:, [0, 2]].norm(dim=-1) > R).double().mean().item()
    exact = (math.pi * R + 2 * r) / (2 * math.pi * R)
    assert outer(torus_points(40000, R, r, gen(1), area_uniform=True)) == pytest.approx(exact, abs=0.01)
    assert outer(torus_points(40000, R, r, gen(1))) == pytest.approx(0.5, abs=0.01)


@pytest.mark.parametrize("exponents", [(0.5, 0.5), (1.0, 1.0), (0.2, 1.5), (2.0, 0.3)])
def test_superquadric_points_satisfy_inside_outside(exponents):
    q = Superquadric((0.8, 0.6, 0.4), exponents)
    cloud = superquadric_points(3000, (0.8, 0.6, 0.4), exponents, gen(), dtype=torch.float64)
    F = q.inside_outside(cloud.points)
    assert torch.allclose(F, torch.ones_like(F), atol=1e-9)
    assert q(cloud.points).abs().max() < 1e-9
    assert torch.isfinite(cloud.normals).all()
    assert torch.allclose(cloud.normals.norm(dim=-1), torch.ones(3000, dtype=torch.float64))


def test_bad_sampling_arguments():
    with pytest.raises(UserError):
        torus_points(0)
    with pytest.raises(UserError):
        superquadric_points(10, exponents=(0.0, 1.0))


@pytest.mark.parametrize("name,kind", [
    ("torus_parametric", PointCloud), ("superquadric_parametric", PointCloud),
    ("torus_implicit", Mesh), ("superquadric_implicit", Mesh), ("sphere_implicit", Mesh),
    ("box_implicit", Mesh), ("union_implicit", Mesh)])
def test_data_configs_build(compose, name, kind):

    cfg = compose(f"data={name}")
    overrides = {"num_samples": 500} if kind is PointCloud else {"resolution": 24}
    data = DATASETS.build({**cfg.data, **overrides}, device=torch.device("cpu"))
    assert isinstance(data, kind)
    if kind is Mesh:
        fv = data.verts.double()[data.faces]
        volume = float((fv[:, 0] * torch.cross(fv[:, 1], fv[:, 2], dim=-1)).sum() / 6)
        assert volume > 0 and data.vert_colors is not None
    else:
        assert data.num_points == 500 and data.colors is not None


def test_parametric_source_is_seeded_and_checks_shape():
    a = DATASETS.build({"name": "parametric", "num_samples": 100, "seed": 3})
    b = DATASETS.build({"name": "parametric", "num_samples": 100, "seed": 3})
    assert torch.equal(a.points, b.points)
    with pytest.raises(UserError):
        DATASETS.build({"name": "parametric", "shape": "klein"})
    with pytest.raises(UserError):
        DATASETS.build({"name": "implicit", "shape": "klein"})


def test_surface_tradeoff_small_run(compose, tmp_path):
    cfg = compose("task=surface_tradeoff", "num_samples_list=[200,3000]", "resolutions=[8,24]",
                  "reference_samples=20000", "mesh_samples=3000", "tensorboard=false")
    run_task(cfg, out_dir=tmp_path)
    metrics = json.loads((tmp_path / "metrics.json").read_text())
    assert metrics["points_3000_chamfer"] < metrics["points_200_chamfer"]
    assert metrics["mc_24_chamfer"] < metrics["mc_8_chamfer"]
    assert metrics["mc_24_surface_error"] < metrics["mc_8_surface_error"]
    for key in ("points_200_seconds", "mc_8_seconds", "mc_24_seconds"):
        assert metrics[key] >= 0
    # best_setting: the lowest chamfer on a second reference (val); chamfer: its figure on the first
    assert metrics["selected_on"] == "val" and metrics["best_setting"] in ("points_3000", "mc_24")
    assert metrics["chamfer"] == metrics[f"{metrics['best_setting']}_chamfer"]
    assert metrics["val_chamfer"] != metrics["chamfer"] and metrics["val_chamfer"] > 0
    csv_lines = (tmp_path / "tradeoff.csv").read_text().strip().splitlines()
    assert len(csv_lines) == 1 + 4 and csv_lines[0].startswith("method,setting,seconds,chamfer")
    assert "| marching_cubes | 24 |" in (tmp_path / "tradeoff.md").read_text()


def test_surface_tradeoff_rejects_bad_lists(compose, tmp_path):
    cfg = compose("task=surface_tradeoff", "resolutions=[2]", "tensorboard=false")
    with pytest.raises(UserError):
        run_task(cfg, out_dir=tmp_path)
