"""Fitting tasks (fit_vox, fit_point, fit_mesh) and their losses / metrics / voxel pieces."""

import json
import math

import pytest
import torch

from l3d_app.app import run_task
from l3d_app.geometry import primitives as P
from l3d_app.geometry.voxels import occupancy_to_mesh, voxel_centers, voxelize_mesh, winding_number
from l3d_app.losses.mesh_regularizers import (edge_length, laplacian_smoothing, normal_consistency,
                                              uniform_laplacian)
from l3d_app.losses.occupancy import bce_with_logits
from l3d_app.metrics.fscore import fscore
from l3d_app.metrics.iou import iou

SMALL = ("image_size=24", "num_frames=2", "batch_frames=2", "tensorboard=false")


# ----------------------------------------------------------------------------- losses / metrics
def test_bce_on_saturated_logits_matches_float64():
    z = torch.tensor([1e4, -1e4, 1e4, -1e4, 30.0, -30.0, 0.0], requires_grad=True)
    t = torch.tensor([1.0, 0.0, 0.0, 1.0, 0.0, 1.0, 1.0])
    loss = bce_with_logits(z, t)
    loss.backward()
    z64 = z.detach().double()
    # float64 reference: softplus form of the loss and its gradient (sigmoid(z) - t) / N
    ref = (torch.clamp(z64, min=0) - z64 * t.double() + torch.log1p(torch.exp(-z64.abs()))).mean()
    ref_grad = (torch.sigmoid(z64) - t.double()) / z.numel()
    assert torch.isfinite(loss) and torch.isfinite(z.grad).all()
    assert loss.item() == pytest.approx(ref.item(), rel=1e-6)
    assert loss.item() == pytest.approx((2e4 + 2 * 30 + math.log(2)) / 7, rel=1e-4)
    assert torch.allclose(z.grad.double(), ref_grad, atol=1e-8)


def test_iou_hand_computed():
    a = torch.zeros(4, 4, 4, dtype=torch.bool)
    b = torch.zeros_like(a)
    a[:2] = True   # 32 cells
    b[1:3] = True  # 32 cells, 16 shared
    assert iou(a, b) == pytest.approx(16 / 48)
    assert iou(a, a) == 1.0 and iou(torch.zeros_like(a), torch.zeros_like(a)) == 1.0
    assert iou(a.float() * 0.9, b.float()) == pytest.approx(16 / 48)  # probabilities threshold at 0.5


def test_fscore_hand_computed():
    pred = torch.tensor([[0.0, 0, 0], [1.0, 0, 0]])
    target = torch.tensor([[0.0, 0, 0.01], [5.0, 0, 0], [0.0, 0, 0.04]])
    out = fscore(pred, target, threshold=0.05)
    p, r = 1 / 2, 2 / 3
    assert out["precision"] == pytest.approx(p) and out["recall"] == pytest.approx(r)
    assert out["f1"] == pytest.approx(2 * p * r / (p + r))
    assert fscore(pred, pred + 10.0, 0.05)["f1"] == 0.0


def test_laplacian_zero_on_flat_grid_interior():
    grid = P.plane(2.0, n=5)
    lap = uniform_laplacian(grid.verts, grid.faces)
    v = grid.verts
    interior = (v[:, 0].abs() < 0.99) & (v[:, 2].abs() < 0.99)
    assert interior.sum() == 16
    assert lap[interior].abs().max() < 1e-6
    assert lap[~interior].abs().max() > 0.1  # boundary vertices are pulled inward


def test_normal_consistency_zero_on_flat_and_positive_when_folded():
    grid = P.plane(2.0, n=4)
    assert normal_consistency(grid.verts, grid.faces).item() == pytest.approx(0.0, abs=1e-6)
    cube = P.cube()
    assert normal_consistency(cube.verts, cube.faces).item() > 0.1


def test_regularizers_finite_on_degenerate_faces():
    verts = torch.tensor([[0.0, 0, 0], [1, 0, 0], [2, 0, 0], [0, 1, 0], [1, 1, 0]], requires_grad=True)
    faces = torch.tensor([[0, 1, 2],   # collinear: zero area
                          [0, 1, 3],
                          [1, 1, 4],   # repeated vertex
                          [1, 4, 3],
                          [3, 3, 3]])  # a point
    for fn in (laplacian_smoothing, normal_consistency, edge_length):
        verts.grad = None
        value = fn(verts, faces)
        value.backward()
        assert torch.isfinite(value) and torch.isfinite(verts.grad).all(), fn.__name__


# ----------------------------------------------------------------------------- voxels
def test_winding_number_inside_outside_and_voxelized_volume():
    sphere = P.icosphere(3, 1.0)
    pts = torch.tensor([[0.0, 0, 0], [0.5, 0.3, -0.2], [1.5, 0, 0], [0, -3, 0]])
    w = winding_number(sphere, pts)
    assert torch.allclose(w, torch.tensor([1.0, 1.0, 0.0, 0.0]), atol=1e-4)
    occ = voxelize_mesh(P.cube(1.0), 20, ((-1.0,) * 3, (1.0,) * 3))
    assert int(occ.sum()) == 10 ** 3  # cells with centres inside the unit cube
    # a tilted (non axis-aligned) box: volume close to its exact volume
    box = P.transformed(P.box((0, 0, 0), (1.2, 0.6, 0.8)), rotation=torch.tensor(
        [[0.8, -0.6, 0.0], [0.6, 0.8, 0.0], [0.0, 0.0, 1.0]]))
    occ = voxelize_mesh(box, 40, ((-1.0,) * 3, (1.0,) * 3))
    assert float(occ.sum()) * (2 / 40) ** 3 == pytest.approx(1.2 * 0.6 * 0.8, rel=0.05)


def test_occupancy_to_mesh_is_closed_and_in_place():
    bounds = ((-1.0,) * 3, (1.0,) * 3)
    centers = voxel_centers(16, bounds)
    occ = (centers.norm(dim=-1) < 0.7).float()
    mesh = occupancy_to_mesh(occ, bounds)
    r = mesh.verts.norm(dim=-1)
    assert 0.55 < float(r.min()) and float(r.max()) < 0.85
    fv = mesh.face_verts().double()
    volume = (fv[:, 0] * torch.cross(fv[:, 1], fv[:, 2], dim=-1)).sum() / 6
    assert volume.item() == pytest.approx(4 / 3 * math.pi * 0.7 ** 3, rel=0.15)


# ----------------------------------------------------------------------------- tasks
def _run(compose, tmp_path, *overrides):
    cfg = compose(*overrides, *SMALL)
    run_task(cfg, out_dir=tmp_path)
    return json.loads((tmp_path / "metrics.json").read_text())


def test_fit_vox_converges(compose, tmp_path):
    m = _run(compose, tmp_path, "task=fit_vox", "data=cube", "voxel_size=12", "iters=60", "eval_every=20")
    for key in ("iou", "seconds", "iters", "n_params", "occupied_cells"):
        assert key in m
    assert m["iou"] >= 0.95 and m["iters"] == 60 and m["n_params"] == 12 ** 3
    assert (tmp_path / "fit_vox.gif").exists() and (tmp_path / "checkpoint.pt").exists()


def test_fit_vox_resumes(compose, tmp_path):
    _run(compose, tmp_path, "task=fit_vox", "data=cube", "voxel_size=8", "iters=10")
    m = _run(compose, tmp_path, "task=fit_vox", "data=cube", "voxel_size=8", "iters=80", "resume=true")
    assert m["iters"] == 80 and m["iou"] >= 0.95


def test_fit_point_reaches_sampling_floor(compose, tmp_path):
    m = _run(compose, tmp_path, "task=fit_point", "data=cube", "num_points=600", "iters=200",
             "lr=0.03", "eval_every=100")
    for key in ("chamfer", "chamfer_baseline", "f1", "seconds", "iters"):
        assert key in m
    assert m["chamfer"] <= 2.0 * m["chamfer_baseline"]
    assert m["f1"] >= 0.9 * m["f1_baseline"]  # 600 points are sparse: F1@0.05 is capped by sampling
    assert (tmp_path / "fit_point.gif").exists()
    # the periodic evaluation read the VAL sample, the final figures the TEST sample: history's
    # last entry is the val figure, a different number from the test one (independent samples)
    assert [h["step"] for h in m["history"]] == [100, 200]
    assert m["history"][-1]["chamfer"] == pytest.approx(m["val_chamfer"], abs=1e-5)  # history keeps 5 digits
    assert m["val_chamfer"] != pytest.approx(m["chamfer"], rel=1e-6)
    assert m["val_chamfer"] <= 2.0 * m["chamfer_baseline"]


def test_held_out_surface_streams_are_seeded_and_independent():
    from omegaconf import OmegaConf
    from l3d_app.geometry.primitives import icosphere
    from l3d_app.tasks.fit_common import eval_generator, held_out_surface
    mesh = icosphere(2, 1.0)
    cfg = OmegaConf.create({"seed": 3, "eval_seed_offset": 7919})
    a, b = held_out_surface(mesh, 500, cfg, "cpu"), held_out_surface(mesh, 500, cfg, "cpu")
    for k in ("val", "test", "test_other"):
        assert a[k].shape == (500, 3) and torch.equal(a[k], b[k])   # the same for every run with that seed
    assert not torch.allclose(a["val"], a["test"]) and not torch.allclose(a["test"], a["test_other"])
    # the streams are seeded apart: val = test + 1, a task's stream 1 = test + 2, seeds 1000 apart
    draw = lambda g: torch.rand(4, generator=g)
    assert not torch.equal(draw(eval_generator(cfg, "cpu", "val")), draw(eval_generator(cfg, "cpu", "test")))
    assert torch.equal(draw(eval_generator(cfg, "cpu", "test", stream=1)),
                       draw(torch.Generator().manual_seed(3000 + 7919 + 2)))
    # no seed's test samples are another seed's val samples (seed + offset + 1 was seed + 1's test)
    from l3d_app.runtime.random import held_out_seed
    seeds = {(s, split, k): held_out_seed(s, 7919, split, k) for s in range(50) for split in ("val", "test")
             for k in range(3)}
    assert len(set(seeds.values())) == len(seeds)
    with pytest.raises(ValueError):
        eval_generator(cfg, "cpu", "train")


def test_fit_mesh_fits_cube(compose, tmp_path):
    m = _run(compose, tmp_path, "task=fit_mesh", "ico_level=2", "num_samples=1000",
             "eval_samples=2000", "iters=150", "lr=0.02", "eval_every=75")
    for key in ("chamfer", "chamfer_baseline", "f1", "seconds", "iters", "n_params"):
        assert key in m
    assert m["f1"] >= 0.85
    assert (tmp_path / "fit_mesh.gif").exists() and (tmp_path / "fit_mesh.obj").exists()
    assert [h["step"] for h in m["history"]] == [75, 150] and m["val_f1"] >= 0.85
