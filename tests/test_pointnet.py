"""Point-cloud learning: data, loaders, models, the pointnet tasks, resume, robustness."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest
import torch

from l3d_app.app import RunInterrupted, run_task
from l3d_app.data.point_sets import course_pointcloud, modelnet40
from l3d_app.data.shape_parts import CLASS_NAMES, PART_NAMES, lathe, shape_parts
from l3d_app.errors import UserError
from l3d_app.models.dgcnn import dgcnn
from l3d_app.models.pointnet import pointnet
from l3d_app.pipelines.point_nets import rotate, rotations

CHAIR_PARTS = {PART_NAMES.index(p) for p in ("chair/seat", "chair/back", "chair/legs", "chair/arms")}


@pytest.fixture(autouse=True, scope="module")
def one_thread():
    """Tiny tensors: one intra-op thread is faster and kinder to a shared machine."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture(scope="session")
def cache_dir(tmp_path_factory):
    return tmp_path_factory.mktemp("shape_cache")


def tiny(cache_dir, *extra):
    """Overrides for a seconds-long run on a tiny built-in dataset (the complete three-class shapes) and a
    small PointNet."""
    return ["data=shape_parts", "data.train_per_class=10", "data.test_per_class=6", "data.num_points=400",
            f"data.cache_dir={cache_dir}", "model.widths=[32,64,128]", "model.cls_head=[64]",
            "model.seg_head=[64]", "train_points=128", "eval_points=128", "batch_size=10",
            "lr=0.005", "num_vis=1", "num_frames=2", "image_size=32", "vis_points=100",
            "tensorboard=false", "threads=1", *extra]


# ----------------------------------------------------------------------------- data

def test_shape_parts_shapes_labels_and_cache(cache_dir):
    data = shape_parts(train_per_class=3, test_per_class=2, num_points=500, cache_dir=str(cache_dir),
                       val_fraction=0.0)
    assert data.train.points.shape == (9, 500, 3) and data.test.points.shape == (6, 500, 3)
    assert data.train.parts.shape == (9, 500) and data.train.labels.tolist() == [0, 0, 0, 1, 1, 1, 2, 2, 2]
    assert len(data.val) == 0
    assert data.class_names == list(CLASS_NAMES) and len(data.part_names) == 10
    radius = data.train.points.norm(dim=-1).max(dim=1).values
    assert torch.allclose(radius, torch.ones(9), atol=1e-5)
    for split in (data.train, data.test):
        for c, name in enumerate(CLASS_NAMES):
            parts = set(split.parts[split.labels == c].unique().tolist())
            allowed = {i for i, p in enumerate(PART_NAMES) if p.startswith(name + "/")}
            assert parts <= allowed and len(parts) >= 3
    chairs = data.train.parts[data.train.labels == 0]
    for chair in chairs:  # every chair has a seat, a back and legs
        assert {0, 1, 2} <= set(chair.unique().tolist()) <= CHAIR_PARTS
    files = list(cache_dir.glob("shape_parts_*.npz"))
    assert files
    again = shape_parts(train_per_class=3, test_per_class=2, num_points=500, cache_dir=str(cache_dir))
    assert torch.equal(again.test.points, data.test.points)
    other = shape_parts(train_per_class=3, test_per_class=2, num_points=500, seed=1, cache_dir=str(cache_dir))
    assert not torch.allclose(other.test.points, data.test.points)
    # objects vary: two chairs differ in extent
    ext = data.train.points[:3].amax(1) - data.train.points[:3].amin(1)
    assert (ext[0] - ext[1]).abs().max() > 1e-3


def test_val_split_is_seeded_stratified_and_leaves_test_alone(cache_dir):
    from l3d_app.data.val_split import carve_val

    full = shape_parts(train_per_class=10, test_per_class=2, num_points=100, cache_dir=str(cache_dir),
                       val_fraction=0.0)
    data = shape_parts(train_per_class=10, test_per_class=2, num_points=100, cache_dir=str(cache_dir),
                       val_fraction=0.2, val_seed=3)
    assert torch.equal(data.test.points, full.test.points)  # test untouched
    assert len(data.train) == 24 and len(data.val) == 6
    assert torch.bincount(data.val.labels).tolist() == [2, 2, 2]  # 20% of 10 per class
    # train + val is exactly the original training set: every val cloud is one of them, none in train
    def keys(split):
        return {tuple(p[0].tolist()) for p in split.points}
    assert keys(data.train) | keys(data.val) == keys(full.train) and not keys(data.train) & keys(data.val)
    again = shape_parts(train_per_class=10, test_per_class=2, num_points=100, cache_dir=str(cache_dir),
                        val_fraction=0.2, val_seed=3)
    assert torch.equal(again.val.points, data.val.points)
    other = shape_parts(train_per_class=10, test_per_class=2, num_points=100, cache_dir=str(cache_dir),
                        val_fraction=0.2, val_seed=4)
    assert keys(other.val) != keys(data.val)
    # the rule itself: per class round(f * count), at least one, never the class's last item
    labels = torch.tensor([0] * 7 + [1] * 2 + [2])
    tr, va = carve_val(10, 0.3, seed=0, labels=labels)
    assert sorted(torch.bincount(labels[va], minlength=3).tolist()) == [0, 1, 2]
    assert torch.bincount(labels[va], minlength=3).tolist() == [2, 1, 0]
    assert sorted(tr.tolist() + va.tolist()) == list(range(10))
    for bad in (-0.1, 1.0):
        with pytest.raises(ValueError, match="val_fraction"):
            carve_val(10, bad)


def test_shape_parts_bad_knobs(cache_dir):
    with pytest.raises(UserError, match="unknown shape_parts class"):
        shape_parts(classes=["sofa"], cache_dir=str(cache_dir))
    with pytest.raises(UserError, match="num_points"):
        shape_parts(num_points=0, cache_dir=str(cache_dir))


def test_lathe_counts_and_radius():
    mesh = lathe([1.0, 0.5, 0.25], [0.0, 1.0, 2.0], n=8, cap_bottom=True)
    assert mesh.num_verts == 3 * 8 + 1 and mesh.num_faces == 2 * 8 * 2 + 8
    r = mesh.verts[:8, [0, 2]].norm(dim=-1)
    assert torch.allclose(r, torch.ones(8), atol=1e-6)


def test_course_loader_cls_and_seg(tmp_path):
    rng = np.random.default_rng(0)
    for split, n in (("train", 5), ("test", 3)):
        np.save(tmp_path / f"{split}_data.npy", rng.normal(size=(n, 50, 3)).astype(np.float32))
        np.save(tmp_path / f"{split}_labels.npy", np.arange(n) % 3)
        (tmp_path / "seg").mkdir(exist_ok=True)
        np.save(tmp_path / "seg" / f"data_{split}.npy", rng.normal(size=(n, 50, 3)))
        np.save(tmp_path / "seg" / f"label_{split}.npy", rng.integers(0, 6, size=(n, 50)))
    data = course_pointcloud(str(tmp_path), kind="cls", class_names=["chair", "vase", "lamp"], val_fraction=0)
    assert data.train.points.shape == (5, 50, 3) and data.test.labels.tolist() == [0, 1, 2]
    assert data.class_names == ["chair", "vase", "lamp"] and data.train.parts is None
    seg = course_pointcloud(str(tmp_path), kind="seg", val_fraction=0)
    assert seg.train.parts.shape == (5, 50) and seg.train.labels is None
    assert seg.part_names == [f"part{i}" for i in range(int(seg.train.parts.max().clamp_min(seg.test.parts.max())) + 1)]
    with pytest.raises(UserError, match="no class labels"):
        seg.test.targets("cls")
    (tmp_path / "test_labels.npy").unlink()
    with pytest.raises(UserError, match="missing test_data.npy / test_labels.npy"):
        course_pointcloud(str(tmp_path), kind="cls")
    with pytest.raises(UserError, match="not a folder"):
        course_pointcloud(str(tmp_path / "nope"))


def test_modelnet40_loader(tmp_path):
    try:
        import h5py
    except ImportError:
        (tmp_path / "ply_data_train0.h5").write_bytes(b"")
        with pytest.raises(UserError, match="pip install h5py"):
            modelnet40(str(tmp_path))
        pytest.skip("h5py not installed: only the error message is tested")
    rng = np.random.default_rng(0)
    for split, n in (("train", 4), ("test", 2)):
        with h5py.File(tmp_path / f"ply_data_{split}0.h5", "w") as f:
            f["data"] = rng.normal(size=(n, 64, 3)).astype(np.float32)
            f["label"] = (np.arange(n) % 2)[:, None].astype(np.uint8)
    (tmp_path / "shape_names.txt").write_text("airplane\nbathtub\n")
    data = modelnet40(str(tmp_path), val_fraction=0)
    assert data.train.points.shape == (4, 64, 3) and data.test.labels.tolist() == [0, 1]
    assert data.class_names == ["airplane", "bathtub"]


def test_modelnet40_missing_files(tmp_path):
    with pytest.raises(UserError):
        modelnet40(str(tmp_path))


# ----------------------------------------------------------------------------- models

MODELS = [
    ("pointnet", lambda kind, k: pointnet(kind, k, widths=[32, 64, 128], input_transform=True,
                                          feature_transform=True)),
    ("dgcnn", lambda kind, k: dgcnn(kind, k, widths=[16, 16, 32], k=8, emb=64)),
]


@pytest.mark.parametrize("name,build", MODELS, ids=[m[0] for m in MODELS])
@pytest.mark.parametrize("kind", ["cls", "seg"])
def test_permutation_invariance(name, build, kind):
    torch.manual_seed(0)
    model = build(kind, 4)
    model.train()
    for _ in range(3):  # move BatchNorm statistics away from their initial values
        model(torch.randn(4, 128, 3))
    model.eval()
    x = torch.randn(3, 128, 3)
    perm = torch.randperm(128)
    with torch.no_grad():
        out, out_perm = model(x)["logits"], model(x[:, perm])["logits"]
    if kind == "cls":
        assert out.shape == (3, 4)
        torch.testing.assert_close(out_perm, out, rtol=1e-4, atol=1e-5)
    else:
        assert out.shape == (3, 128, 4)
        torch.testing.assert_close(out_perm, out[:, perm], rtol=1e-4, atol=1e-5)
    assert (out[0] - out[1]).abs().max() > 1e-4  # the output does depend on the cloud


def test_rotation_helper():
    x = torch.tensor([[[1.0, 0.0, 0.0]]])
    torch.testing.assert_close(rotate(x, rotations("z", [90.0]))[0, 0], torch.tensor([0.0, 1.0, 0.0]),
                               atol=1e-6, rtol=0)
    with pytest.raises(UserError):
        rotations("w", [10.0])


# ----------------------------------------------------------------------------- tasks

@pytest.mark.parametrize("task", ["pointnet_cls", "pointnet_seg"])
def test_task_trains_and_beats_chance(compose, cache_dir, tmp_path, task):
    cfg = compose(f"task={task}", *tiny(cache_dir, "epochs=8"))
    run_task(cfg, out_dir=tmp_path)
    m = json.loads((tmp_path / "metrics.json").read_text())
    test = shape_parts(train_per_class=10, test_per_class=6, num_points=400, cache_dir=str(cache_dir)).test
    target = test.labels if task == "pointnet_cls" else test.parts
    majority = float(torch.bincount(target.reshape(-1)).max()) / target.numel()  # predict-one-label
    assert m["accuracy"] > majority + 0.25, (m, majority)
    assert m["test_points"] == 400 and m["n_params"] > 0 and m["seconds"] > 0
    assert m["iters"] == 8 * 3 and m["best_epoch"] >= 1
    # chosen on validation (27 train / 3 val clouds carved from the 30), test read once
    assert m["selected_on"] == "val" and m["n_train"] == 27 and m["n_val"] == 3 and m["n_test"] == 18
    assert 0 <= m["val_accuracy"] <= 1
    assert max(row["accuracy"] for row in m["history"]) == pytest.approx(m["val_accuracy"], abs=1e-4)
    best = torch.load(tmp_path / "best.pt", weights_only=False)
    assert best["epoch"] == m["best_epoch"] and best["accuracy"] == pytest.approx(m["val_accuracy"], abs=1e-4)
    for name in ("best.pt", "checkpoint.pt", "confusion_matrix.png"):
        assert (tmp_path / name).is_file()
    gifs = list((tmp_path / "vis").glob("*.gif"))
    assert any(g.name.startswith("sample0_") for g in gifs)
    if task == "pointnet_seg":
        assert 0 < m["miou"] <= 1 and any(g.name.startswith("failure_") for g in gifs)


def test_resume_matches_uninterrupted(compose, cache_dir, tmp_path, monkeypatch):
    overrides = tiny(cache_dir, "epochs=3", "num_vis=0", "vis_failures=false")
    run_task(compose("task=pointnet_cls", *overrides), out_dir=tmp_path / "full")
    full = torch.load(tmp_path / "full" / "checkpoint.pt", weights_only=False)

    monkeypatch.setenv("L3D_STOP_AT_STEP", "3")  # the loop's hook: a SIGINT after step 3
    with pytest.raises(RunInterrupted):
        run_task(compose("task=pointnet_cls", *overrides), out_dir=tmp_path / "cut")
    cut = torch.load(tmp_path / "cut" / "checkpoint.pt", weights_only=False)
    assert cut["step"] == 3  # stopped after epoch 1 of 3 (3 steps per epoch)
    assert json.loads((tmp_path / "cut" / "metrics.json").read_text())["interrupted"] is True
    monkeypatch.delenv("L3D_STOP_AT_STEP")
    run_task(compose("task=pointnet_cls", *overrides, "resume=true"), out_dir=tmp_path / "cut")
    resumed = torch.load(tmp_path / "cut" / "checkpoint.pt", weights_only=False)
    assert resumed["step"] == full["step"] == 9
    a, b = full["trainable"]["modules"]["model"], resumed["trainable"]["modules"]["model"]
    assert all(torch.equal(a[k], b[k]) for k in a)
    best_full = torch.load(tmp_path / "full" / "best.pt", weights_only=False)
    best_cut = torch.load(tmp_path / "cut" / "best.pt", weights_only=False)
    assert best_full["epoch"] == best_cut["epoch"]


def test_robustness_command(compose, cache_dir, tmp_path, capsys):
    overrides = tiny(cache_dir, "epochs=8", "rotation_degrees=[0,90]",
                     "num_points_list=[400,100,100000]", "num_vis=0", "vis_failures=false")
    run_task(compose("task=pointnet_robustness", *overrides), out_dir=tmp_path / "a")
    m = json.loads((tmp_path / "a" / "metrics.json").read_text())
    # trained upright (no rotation augmentation), then shown the test clouds tipped 90 degrees
    # about z: a model that learnt anything about upright shapes must lose accuracy. If the
    # table applied no rotation, rot90 would equal rot0 and this would fail.
    assert m["cls_rot0"] > 0.6 and m["cls_rot90"] < m["cls_rot0"] - 0.15, m
    assert m["seg_rot90"] < m["seg_rot0"] - 0.15, m
    assert m["selected_on"] == "val" and 0 <= m["cls_val_accuracy"] <= 1
    assert m["cls_ms_per_cloud"] > 0 and m["seg_n_params"] > 0
    for kind in ("cls", "seg"):
        for key in ("rot0", "rot90", "pts400", "pts100"):
            assert 0.0 <= m[f"{kind}_{key}"] <= 1.0
        assert m[f"{kind}_pts100000"] is None  # more points than the clouds have: no figure (JSON null)
        assert set(m["tables"][kind]) == {"rotation", "num_points"}
    assert m["cls_rot0"] == pytest.approx(m["cls_pts400"])  # both: every point, unrotated
    assert "| 90 |" in (tmp_path / "a" / "robustness.md").read_text()
    import imageio.v2 as imageio
    for kind in ("cls", "seg"):            # a row per angle, the first test cloud of each of the 3 classes
        assert imageio.imread(tmp_path / "a" / f"rotation_{kind}.png").shape[:2] == (2 * 32, 3 * 32)
    for name in ("robustness_rotation.png", "robustness_points.png"):
        assert (tmp_path / "a" / name).stat().st_size > 0
    # from a saved checkpoint: same figures without training
    run_task(compose("task=pointnet_robustness", *overrides, "robust_kinds=[cls]",
                     f"cls_checkpoint={tmp_path / 'a' / 'cls' / 'best.pt'}"), out_dir=tmp_path / "b")
    m2 = json.loads((tmp_path / "b" / "metrics.json").read_text())
    assert m2["cls_rot90"] == pytest.approx(m["cls_rot90"]) and "seg_rot0" not in m2
    assert m2["cls_selected_on"] == "val"                     # best.pt says where it was chosen
    # a best.pt that does not say (written before it was recorded; older ones were chosen on test)
    old = torch.load(tmp_path / "a" / "cls" / "best.pt", weights_only=False)
    old.pop("selected_on")
    torch.save(old, tmp_path / "old.pt")
    run_task(compose("task=pointnet_robustness", *overrides, "robust_kinds=[cls]",
                     f"cls_checkpoint={tmp_path / 'old.pt'}"), out_dir=tmp_path / "c")
    m3 = json.loads((tmp_path / "c" / "metrics.json").read_text())
    assert m3["cls_selected_on"] == "unknown" and "chosen on the validation split" in capsys.readouterr().err


def test_missing_course_files_is_user_error(compose, tmp_path):
    with pytest.raises(UserError, match="missing train_data.npy"):
        run_task(compose("task=pointnet_cls", "data=course_pointcloud", f"data.root={tmp_path}",
                         "tensorboard=false"), out_dir=tmp_path / "x")
    with pytest.raises(UserError, match="data.root"):  # not given at all
        run_task(compose("task=pointnet_cls", "data=course_pointcloud", "tensorboard=false"),
                 out_dir=tmp_path / "y")


# ----------------------------------------------------------------------------- DDP

def _ddp_worker(rank, world, port, out_dir, cache_dir):
    """One torchrun-like process: the env variables torchrun sets, then the app."""
    os.environ.update(RANK=str(rank), WORLD_SIZE=str(world), LOCAL_RANK=str(rank),
                      MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port), L3D_NO_PROGRESS="1")
    from pathlib import Path

    from hydra import compose, initialize_config_dir

    torch.set_num_threads(1)
    conf = Path(__file__).resolve().parents[1] / "conf"
    with initialize_config_dir(version_base="1.3", config_dir=str(conf)):
        cfg = compose(config_name="config", overrides=["task=pointnet_cls", "device=cpu", *tiny(
            cache_dir, "epochs=2", "num_vis=0", "vis_failures=false")])
    run_task(cfg, out_dir=Path(out_dir))


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_ddp_two_processes_end_with_identical_weights(cache_dir, tmp_path):
    import torch.multiprocessing as mp

    mp.spawn(_ddp_worker, args=(2, _free_port(), str(tmp_path), str(cache_dir)), nprocs=2, join=True)
    rank0 = torch.load(tmp_path / "checkpoint.pt", weights_only=False)
    rank1 = torch.load(tmp_path / "rank1" / "checkpoint.pt", weights_only=False)
    assert rank0["step"] == rank1["step"] == 2 * 3  # 2 epochs of ceil(30 / 10) global batches
    a, b = rank0["trainable"]["modules"]["model"], rank1["trainable"]["modules"]["model"]
    params = [k for k in a if "running_" not in k and "num_batches" not in k]
    assert all(torch.equal(a[k], b[k]) for k in params)  # BatchNorm statistics stay rank-local
    torch.manual_seed(0)
    init = pointnet("cls", 3, widths=[32, 64, 128], cls_head=[64]).state_dict()
    assert any(not torch.equal(init[k], a[k]) for k in params)  # and training moved them
    m = json.loads((tmp_path / "metrics.json").read_text())
    assert m["world_size"] == 2 and (tmp_path / "best.pt").is_file()
    assert not (tmp_path / "rank1" / "best.pt").exists()


def test_batched_knn_matches_brute_force():
    from l3d_app.models.dgcnn import batched_knn

    x = torch.randn(2, 50, 5, dtype=torch.float64)
    idx = batched_knn(x, 4, chunk=7)
    ref = torch.cdist(x, x).topk(4, dim=-1, largest=False).indices
    assert torch.equal(idx, ref)


def test_dgcnn_task_runs(compose, cache_dir, tmp_path):
    cfg = compose("task=pointnet_seg", "model=dgcnn", "model.widths=[16,16,32]", "model.k=8",
                  "model.emb=64", "model.seg_head=[32]",
                  *tiny(cache_dir, "epochs=1", "num_vis=0", "vis_failures=false"))
    run_task(cfg, out_dir=tmp_path)
    m = json.loads((tmp_path / "metrics.json").read_text())
    assert 0 <= m["accuracy"] <= 1 and m["n_params"] > 0
    assert torch.load(tmp_path / "best.pt", weights_only=False)["model_cfg"]["name"] == "dgcnn"


# ----------------------------------------------------------------------------- PointNet++

def _naive_fps(xyz, m):
    """Farthest-point sampling, one cloud, plain Python over points (float64)."""
    pts = xyz.double().tolist()
    chosen = [0]
    best = [float("inf")] * len(pts)
    for _ in range(1, m):
        c = pts[chosen[-1]]
        for j, p in enumerate(pts):
            best[j] = min(best[j], sum((a - b) ** 2 for a, b in zip(p, c)))
        far = max(range(len(pts)), key=lambda j: (best[j], -j))  # ties: the lowest index
        chosen.append(far)
    return chosen


def _naive_ball(xyz, centers, radius, k):
    pts = xyz.double().tolist()
    out = []
    for c in centers.double().tolist():
        d2 = [sum((a - b) ** 2 for a, b in zip(p, c)) for p in pts]
        inside = [j for j, d in enumerate(d2) if d <= radius ** 2][:k]
        if not inside:
            inside = [min(range(len(pts)), key=lambda j: d2[j])]
        out.append(inside + [inside[0]] * (k - len(inside)))
    return out


def test_farthest_point_sample_matches_naive_reference():
    from l3d_app.models.pointnet2 import farthest_point_sample

    g = torch.Generator().manual_seed(0)
    xyz = torch.rand(3, 70, 3, generator=g, dtype=torch.float64)
    idx = farthest_point_sample(xyz, 12)
    assert idx.tolist() == [_naive_fps(xyz[b], 12) for b in range(3)]
    # hard case: duplicated points never get picked twice while distinct ones remain
    dup = torch.cat([xyz[:1, :5], xyz[:1, :5]], dim=1)
    assert len(set(farthest_point_sample(dup, 5)[0].tolist())) == 5
    with pytest.raises(ValueError):
        farthest_point_sample(xyz, 71)


def test_ball_query_matches_naive_reference():
    from l3d_app.models.pointnet2 import ball_query

    g = torch.Generator().manual_seed(1)
    xyz = torch.rand(2, 60, 3, generator=g, dtype=torch.float64)
    centers = torch.cat([xyz[:, :4], torch.full((2, 1, 3), 5.0, dtype=torch.float64)], dim=1)  # last: far away
    for radius, k in ((0.3, 8), (0.05, 4), (2.0, 16)):
        idx = ball_query(xyz, centers, radius, k)
        assert idx.shape == (2, 5, k)
        assert idx.tolist() == [_naive_ball(xyz[b], centers[b], radius, k) for b in range(2)]


def test_three_nn_interpolation_is_exact_at_coarse_points_and_a_partition_of_unity():
    from l3d_app.models.pointnet2 import three_nn_interpolate

    g = torch.Generator().manual_seed(2)
    coarse = torch.rand(1, 10, 3, generator=g, dtype=torch.float64)
    feat = torch.rand(1, 10, 4, generator=g, dtype=torch.float64)
    at = three_nn_interpolate(coarse, coarse, feat)
    assert torch.allclose(at, feat, atol=1e-6)
    ones = three_nn_interpolate(torch.rand(1, 30, 3, generator=g, dtype=torch.float64), coarse,
                                torch.ones(1, 10, 1, dtype=torch.float64))
    assert torch.allclose(ones, torch.ones_like(ones))


@pytest.mark.parametrize("kind", ["cls", "seg"])
def test_pointnet2_shapes_and_gradients(kind):
    from l3d_app.models.pointnet2 import pointnet2

    torch.manual_seed(0)
    model = pointnet2(kind, 5, sa_points=[16, 4], sa_neighbors=[8, 4], sa_widths=[[8, 16], [16, 32]],
                      global_widths=[32, 64], cls_head=[32], seg_head=[16], fp_widths=[16])
    out = model(torch.rand(2, 50, 3) * 2 - 1)["logits"]
    assert out.shape == ((2, 5) if kind == "cls" else (2, 50, 5))
    out.square().sum().backward()
    grads = [p.grad for p in model.parameters()]
    assert all(gr is not None and torch.isfinite(gr).all() for gr in grads)
    with pytest.raises(UserError):
        pointnet2(kind, 5, sa_points=[16], sa_radii=[0.2, 0.4])


def test_pointnet2_task_beats_chance(compose, cache_dir, tmp_path):
    cfg = compose("task=pointnet_cls", "model=pointnet2", "model.sa_points=[32,8]", "model.sa_neighbors=[16,8]",
                  "model.sa_widths=[[16,32],[32,64]]", "model.global_widths=[64,128]", "model.cls_head=[64]",
                  *[o for o in tiny(cache_dir, "epochs=8", "num_vis=0", "vis_failures=false",
                                    "data.train_per_class=20")
                    if not o.startswith("model.")])
    run_task(cfg, out_dir=tmp_path)
    m = json.loads((tmp_path / "metrics.json").read_text())
    assert m["accuracy"] > 1 / 3 + 0.25 and m["selected_on"] == "val", m
    assert torch.load(tmp_path / "best.pt", weights_only=False)["model_cfg"]["name"] == "pointnet2"


def test_preview_gifs_stop_when_the_last_ones_cost_no_longer_fits(compose, tmp_path):
    """Under a time budget the gifs (previews) are written while the last gif's cost still fits the
    seconds left: 5 s left at the start, then a fake clock on which the first gif takes 0.5 s with
    1 ms left: only the first is written; without a budget all of them."""
    from l3d_app.pipelines.point_nets import Evaluation
    from l3d_app.pipelines.point_visuals import write_visuals
    from l3d_app.runtime.budget import TimeBudget
    from l3d_app.runtime.context import RunContext
    from l3d_app.runtime.logger import RunLogger
    from l3d_app.runtime.seed import seed_everything
    from l3d_app.tasks.point_common import turntable

    cfg = compose("task=pointnet_seg", "num_vis=3", "vis_failures=true", "num_frames=2", "image_size=32")
    g = torch.Generator().manual_seed(0)
    pts = torch.rand(6, 64, 3, generator=g)
    target = torch.randint(0, 3, (6, 64), generator=g)
    ev = Evaluation(pts, target.flip(1), target, 0.3)
    class_of = torch.tensor([0, 0, 1, 1, 2, 2])
    for seconds, readings, expect in ((0.0, [], (3, 3)), (60.0, [55.0, 59.999, 59.999, 60.5], (1, 0))):
        ctx = RunContext(out_dir=tmp_path / f"b{seconds:g}", device=torch.device("cpu"), generator=seed_everything(0),
                         logger=RunLogger(tmp_path / f"b{seconds:g}", enabled=False))
        clock = iter(readings)
        budget = TimeBudget(seconds, clock=lambda: next(clock, 60.5))
        out = write_visuals(ctx, ev, "seg", ["a", "b", "c"], class_of, ["x", "y", "z"], turntable(cfg, ctx), 3, True,
                            12.0, 0, budget)
        assert (out["n_vis"], out["n_failure_gifs"]) == expect
        assert len(list((ctx.out_dir / "vis").glob("*.gif"))) == sum(expect)
