"""The ModelNet40 HDF5 loader (data/point_sets.py ``modelnet40``) on small files written here.
h5py is a declared test dependency: if it is missing this file fails, it does not skip."""

from __future__ import annotations

import h5py
import numpy as np
import pytest
import torch

import l3d_app.data.point_sets  # noqa: F401  (registers the "modelnet40" data source)
from l3d_app.errors import UserError
from l3d_app.registry import DATASETS


def _write(path, data, label, pid=None):
    with h5py.File(path, "w") as f:
        f["data"] = data
        f["label"] = label
        if pid is not None:
            f["pid"] = pid


@pytest.fixture
def files(tmp_path):
    rng = np.random.default_rng(0)
    P = 32
    train = [rng.normal(size=(3, P, 3)).astype(np.float32), rng.normal(size=(2, P, 3)).astype(np.float32)]
    test = rng.normal(size=(4, P, 3)).astype(np.float32)
    tl = [np.array([[2], [0], [1]], np.uint8), np.array([[1], [2]], np.uint8)]
    tp = [rng.integers(0, 4, (3, P)).astype(np.uint8), rng.integers(0, 4, (2, P)).astype(np.uint8)]
    # written out of order: the loader reads the shards sorted by name
    _write(tmp_path / "ply_data_train1.h5", train[1], tl[1], tp[1])
    _write(tmp_path / "ply_data_train0.h5", train[0], tl[0], tp[0])
    _write(tmp_path / "ply_data_test0.h5", test, np.array([[0], [1], [2], [2]], np.uint8),
           rng.integers(0, 4, (4, P)).astype(np.uint8))
    (tmp_path / "shape_names.txt").write_text("airplane\nbathtub\nbed\n")
    return tmp_path, np.concatenate(train), np.concatenate(tl).reshape(-1), np.concatenate(tp), test


def test_loader_reads_shards_labels_parts_and_names(files):
    root, train_pts, train_lab, train_pid, test_pts = files
    data = DATASETS.build({"name": "modelnet40", "root": str(root)})
    # test: read as written, untouched
    assert data.test.points.dtype == torch.float32 and data.test.labels.dtype == torch.int64
    np.testing.assert_array_equal(data.test.points.numpy(), test_pts)
    assert data.test.labels.tolist() == [0, 1, 2, 2]
    # train (+ a validation split carved from it, if the loader makes one): exactly the
    # train shards' clouds, in shard order, with their labels and part ids
    parts = [data.train] + ([data.val] if getattr(data, "val", None) is not None else [])
    pts = np.concatenate([s.points.numpy() for s in parts])
    lab = np.concatenate([s.labels.numpy() for s in parts])
    pid = np.concatenate([s.parts.numpy() for s in parts])
    order = [int(np.flatnonzero((train_pts == p).all(axis=(1, 2)))[0]) for p in pts]
    assert sorted(order) == list(range(5))
    np.testing.assert_array_equal(lab, train_lab[order])
    np.testing.assert_array_equal(pid, train_pid[order])
    if len(parts) == 1:
        np.testing.assert_array_equal(pts, train_pts)              # shard 0 before shard 1
    assert data.class_names == ["airplane", "bathtub", "bed"]


def test_unreadable_or_incomplete_files_are_user_errors(tmp_path):
    with pytest.raises(UserError, match="no ply_data_train"):
        DATASETS.build({"name": "modelnet40", "root": str(tmp_path)})
    (tmp_path / "ply_data_train0.h5").write_bytes(b"not hdf5")
    _write(tmp_path / "ply_data_test0.h5", np.zeros((1, 4, 3), np.float32), np.zeros((1, 1), np.uint8))
    with pytest.raises(UserError, match="cannot read ModelNet40"):
        DATASETS.build({"name": "modelnet40", "root": str(tmp_path)})
    with h5py.File(tmp_path / "ply_data_train0.h5", "w") as f:
        f["data"] = np.zeros((1, 4, 3), np.float32)                  # no "label"
    with pytest.raises(UserError, match="cannot read ModelNet40"):
        DATASETS.build({"name": "modelnet40", "root": str(tmp_path)})
