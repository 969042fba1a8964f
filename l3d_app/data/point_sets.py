"""Labelled point-cloud datasets: one container and the loaders for real formats.

A dataset is three :class:`PointSplit` (train, val, test) of equal-size clouds with class
labels (classification) and/or per-point part labels (segmentation), plus the label names.
Every source ships train and test only; the validation split is carved from train by
:meth:`PointCloudData.with_val` (``data.val_fraction`` of it, stratified by class, fixed by
``data.val_seed``), so the test split stays untouched and is read once by the tasks.

Sources (``data=...``):

* ``shape_parts`` -- the built-in procedural chairs / vases / lamps
  (:mod:`l3d_app.data.shape_parts`);
* ``course_pointcloud data.root=DIR`` -- the course's ``.npy`` layout:
  ``{train,test}_data.npy`` float (N, P, 3) and ``{train,test}_labels.npy``, int (N,) for
  classification or (N, P) for segmentation. The course's own names
  ``data_{train,test}.npy`` / ``label_{train,test}.npy`` are accepted too, and so are
  ``cls/`` and ``seg/`` sub-folders (the one matching the task is used);
* ``modelnet40 data.root=DIR`` -- ModelNet40 in its common HDF5 form
  (``ply_data_{train,test}*.h5`` with ``data`` (N, 2048, 3), ``label`` (N, 1), optional
  ``pid`` (N, 2048) part ids; ``shape_names.txt`` for the class names). Needs ``h5py``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import List, Optional, Sequence

import numpy as np
import torch

from l3d_app.data.array_files import load_array_file, numeric_array
from l3d_app.data.val_split import carve_val
from l3d_app.errors import UserError
from l3d_app.registry import DATASETS

KINDS = ("cls", "seg")


@dataclass
class PointSplit:
    """One split of a labelled point-cloud dataset (CPU tensors).

    Attributes:
        points: (N, P, 3) float32 positions (world units; built-in clouds lie in the unit ball).
        labels: optional (N,) int64 class index per cloud.
        parts: optional (N, P) int64 part index per point.
    """

    points: torch.Tensor
    labels: Optional[torch.Tensor] = None
    parts: Optional[torch.Tensor] = None

    def __post_init__(self):
        p = self.points
        if p.dim() != 3 or p.shape[-1] != 3 or p.shape[1] == 0:
            raise UserError(f"point clouds must be (N, P, 3) with P >= 1, got {tuple(p.shape)}")
        if self.labels is not None and tuple(self.labels.shape) != (p.shape[0],):
            raise UserError(f"class labels must be ({p.shape[0]},), got {tuple(self.labels.shape)}")
        if self.parts is not None and tuple(self.parts.shape) != tuple(p.shape[:2]):
            raise UserError(f"part labels must be {tuple(p.shape[:2])}, got {tuple(self.parts.shape)}")

    def __len__(self) -> int:
        return self.points.shape[0]

    @property
    def num_points(self) -> int:
        return self.points.shape[1]

    def targets(self, kind: str) -> torch.Tensor:
        """The labels a task of ``kind`` ('cls' or 'seg') learns: (N,) or (N, P)."""
        out = self.labels if kind == "cls" else self.parts
        if out is None:
            what = "class labels" if kind == "cls" else "per-point part labels"
            raise UserError(f"this dataset has no {what}, needed by the {kind} task")
        return out

    def subset(self, index: torch.Tensor) -> "PointSplit":
        """The clouds at ``index`` (long tensor) as a new split."""
        pick = (lambda t: None if t is None else t[index])
        return PointSplit(self.points[index], pick(self.labels), pick(self.parts))


@dataclass
class PointCloudData:
    """A labelled dataset: train, val and test splits plus label names.

    ``class_names`` index the class labels, ``part_names`` the part labels (either may be
    generic names such as ``class3`` when the source does not name them). ``val`` is None
    until :meth:`with_val` carves it from train.
    """

    train: PointSplit
    test: PointSplit
    class_names: List[str]
    part_names: List[str]
    source: str = ""
    val: Optional[PointSplit] = None

    def names(self, kind: str) -> List[str]:
        return list(self.class_names if kind == "cls" else self.part_names)

    def with_val(self, fraction: float, seed: int = 0) -> "PointCloudData":
        """A copy whose ``val`` is ``fraction`` of the training clouds (stratified by class
        label when there is one, chosen by ``seed``) and whose ``train`` is the rest; the
        test split is left as it is. See :func:`l3d_app.data.val_split.carve_val`."""
        tr, va = carve_val(len(self.train), fraction, seed, self.train.labels)
        return PointCloudData(self.train.subset(tr), self.test, self.class_names, self.part_names,
                              self.source, val=self.train.subset(va))


def _label_names(labels: Sequence[Optional[torch.Tensor]], prefix: str,
                 given: Optional[Sequence[str]] = None) -> List[str]:
    """``given`` when it covers every label, else ``prefix0, prefix1, ...``."""
    top = max([int(x.max()) for x in labels if x is not None and x.numel()] + [-1]) + 1
    if given and len(given) >= top:
        return list(given)
    return [f"{prefix}{i}" for i in range(top)]


def _find(root: Path, names: Sequence[str]) -> Optional[Path]:
    for name in names:
        if (root / name).exists():
            return root / name
    return None


def _load_npy(path: Path) -> np.ndarray:
    return load_array_file(path, mmap_mode="r")


def _as_labels(array: np.ndarray, path: Path) -> torch.Tensor:
    if not np.issubdtype(array.dtype, np.integer) and not np.allclose(array, np.round(array)):
        raise UserError(f"labels in {path} must be integers")
    if array.size and array.min() < 0:
        raise UserError(f"labels in {path} must be >= 0")
    return torch.from_numpy(np.ascontiguousarray(array).astype(np.int64))


@DATASETS.register("course_pointcloud")
def course_pointcloud(root: str, kind: str = "cls", class_names: Optional[List[str]] = None,
                      part_names: Optional[List[str]] = None, max_train: int = 0,
                      max_test: int = 0, val_fraction: float = 0.1, val_seed: int = 0,
                      device=None) -> PointCloudData:
    """Load the course's ``.npy`` point-cloud data from ``root`` (see module docstring).

    Args:
        root: folder with the arrays (or with ``cls/`` and ``seg/`` sub-folders).
        kind: 'cls' (labels (N,)) or 'seg' (labels (N, P)); picks the sub-folder.
        class_names / part_names: optional names for the labels.
        max_train / max_test: keep only the first so many clouds (0 = all).
        val_fraction / val_seed: the validation split carved from train (see
            :meth:`PointCloudData.with_val`).
        device: ignored (datasets stay on the CPU; tasks move batches).
    """
    base = Path(str(root)).expanduser()
    if not base.is_dir():
        raise UserError(f"data.root '{base}' is not a folder")
    if (base / kind).is_dir():
        base = base / kind
    split = {}
    for name in ("train", "test"):
        data_path = _find(base, [f"{name}_data.npy", f"data_{name}.npy"])
        label_path = _find(base, [f"{name}_labels.npy", f"label_{name}.npy", f"labels_{name}.npy"])
        if data_path is None or label_path is None:
            raise UserError(f"missing {name}_data.npy / {name}_labels.npy in {base}")
        pts, lab = _load_npy(data_path), _load_npy(label_path)
        limit = {"train": max_train, "test": max_test}[name] or len(pts)
        if int(limit) < 0:
            raise UserError(f"max_{name} must be >= 0 (0: all), got {limit}")
        pts, lab = numeric_array(pts[:limit], str(data_path)), numeric_array(lab[:limit], str(label_path), lab.dtype)
        if pts.ndim != 3 or pts.shape[-1] != 3:
            raise UserError(f"{data_path} must hold (N, P, 3) points, got {pts.shape}")
        if not np.isfinite(pts).all():
            raise UserError(f"{data_path}: points contain NaN or Inf")
        labels = _as_labels(lab.reshape(len(lab), -1).squeeze(1) if lab.ndim == 2 and lab.shape[1] == 1
                            else lab, label_path)
        if labels.dim() == 1:
            split[name] = PointSplit(torch.from_numpy(pts), labels=labels)
        else:
            split[name] = PointSplit(torch.from_numpy(pts), parts=labels)
    tr, te = split["train"], split["test"]
    return PointCloudData(tr, te, _label_names([tr.labels, te.labels], "class", class_names),
                          _label_names([tr.parts, te.parts], "part", part_names),
                          source=f"course_pointcloud:{base}").with_val(val_fraction, val_seed)


def _read_h5(files: List[Path]):
    try:
        import h5py
    except ImportError:
        raise UserError("data=modelnet40 needs h5py: pip install h5py") from None
    pts, lab, pid = [], [], []
    for f in files:
        try:
            with h5py.File(f, "r") as h5:
                pts.append(np.asarray(h5["data"], dtype=np.float32))
                lab.append(np.asarray(h5["label"]).reshape(-1))
                if "pid" in h5:
                    pid.append(np.asarray(h5["pid"]))
        except (OSError, KeyError) as err:
            raise UserError(f"cannot read ModelNet40 HDF5 file {f}: {err}") from None
    parts = torch.from_numpy(np.concatenate(pid).astype(np.int64)) if len(pid) == len(files) else None
    return (torch.from_numpy(np.concatenate(pts)),
            torch.from_numpy(np.concatenate(lab).astype(np.int64)), parts)


@DATASETS.register("modelnet40")
def modelnet40(root: str, kind: str = "cls", val_fraction: float = 0.1, val_seed: int = 0,
               device=None) -> PointCloudData:
    """Load ModelNet40 HDF5 files ``ply_data_{train,test}*.h5`` from ``root`` (see module
    docstring), validation carved from train (``val_fraction``, ``val_seed``); ``kind`` and
    ``device`` are accepted for a uniform interface."""
    base = Path(str(root)).expanduser()
    if not base.is_dir():
        raise UserError(f"data.root '{base}' is not a folder")
    split = {}
    for name in ("train", "test"):
        files = sorted(base.glob(f"*{name}*.h5"))
        if not files:
            raise UserError(f"no ply_data_{name}*.h5 files in {base}")
        points, labels, parts = _read_h5(files)
        split[name] = PointSplit(points, labels=labels, parts=parts)
    names_file = _find(base, ["shape_names.txt", "modelnet40_shape_names.txt"])
    given = names_file.read_text().split() if names_file else None
    tr, te = split["train"], split["test"]
    return PointCloudData(tr, te, _label_names([tr.labels, te.labels], "class", given),
                          _label_names([tr.parts, te.parts], "part"),
                          source=f"modelnet40:{base}").with_val(val_fraction, val_seed)
