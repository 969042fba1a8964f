"""The cache of the built-in point-cloud datasets (``shape_parts``, ``shape_scans``) and their split.

A dataset is generated once per set of generation knobs and kept as ``<name>_<hash>.npz`` in the
cache folder (``$L3D_CACHE`` or ``~/.cache/l3d_app``); the hash is the first 12 hex digits of the
SHA-1 of the knobs as sorted JSON. Objects are stored class by class, ``n`` per class, the first
``train_per_class`` of each class train, the rest test.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path
from typing import Callable, Dict, Mapping, Optional, Tuple

import numpy as np
import torch

from l3d_app.data.point_sets import PointSplit
from l3d_app.runtime.files import atomic_path


def default_cache_dir() -> Path:
    """``$L3D_CACHE`` or ``~/.cache/l3d_app``."""
    return Path(os.environ.get("L3D_CACHE", Path.home() / ".cache" / "l3d_app"))


def cached_point_sets(name: str, knobs: Mapping[str, object], cache_dir: Optional[str],
                      generate: Callable[[], Dict[str, np.ndarray]]) -> Tuple[np.ndarray, np.ndarray, np.ndarray, Path]:
    """The arrays of dataset ``name`` for ``knobs``: read from its cache file, or made by ``generate()``
    (a dict of arrays with at least ``points`` (N, P, 3), ``labels`` (N,) and ``parts`` (N, P); every
    array it returns is saved) and cached atomically. A cache folder that cannot be written is a
    warning, and the run goes on without it. ``cache_dir`` None: :func:`default_cache_dir`.

    Returns points, labels, parts and the cache file's path."""
    digest = hashlib.sha1(json.dumps(dict(knobs), sort_keys=True).encode()).hexdigest()[:12]
    folder = Path(cache_dir).expanduser() if cache_dir else default_cache_dir()
    path = folder / f"{name}_{digest}.npz"
    if path.exists():
        with np.load(path) as z:
            return z["points"], z["labels"], z["parts"], path
    arrays = generate()
    try:
        with atomic_path(path) as tmp:
            with open(tmp, "wb") as f:
                np.savez(f, **arrays)
    except OSError as err:  # read-only cache: keep going without it
        print(f"l3d_app: warning: cannot cache {name} in {folder}: {err}")
    return arrays["points"], arrays["labels"], arrays["parts"], path


def class_block_splits(points: np.ndarray, labels: np.ndarray, parts: np.ndarray, per_class: int,
                       train_per_class: int) -> Tuple[PointSplit, PointSplit]:
    """(train, test) of arrays stored class by class, ``per_class`` objects each: the first
    ``train_per_class`` of every class train, the rest test; labels and parts as int64."""
    within = np.arange(len(labels)) % int(per_class)
    splits = []
    for mask in (within < int(train_per_class), within >= int(train_per_class)):
        splits.append(PointSplit(torch.from_numpy(points[mask]), labels=torch.from_numpy(labels[mask].astype(np.int64)),
                                 parts=torch.from_numpy(parts[mask].astype(np.int64))))
    return splits[0], splits[1]
