"""The course's bunny point cloud for neural-SDF fitting: ``data=bunny data.path=FILE``.

``FILE`` is an ``.npz`` with key ``verts`` (N, 3); as in the course, every second point is kept
(``stride``) and the cloud is centred by subtracting its mean.
"""

from __future__ import annotations

import torch

from l3d_app.data.array_files import load_array_file, numeric_array
from l3d_app.errors import UserError
from l3d_app.geometry.pointcloud import PointCloud
from l3d_app.registry import DATASETS
from l3d_app.runtime.paths import resolve_path


@DATASETS.register("bunny")
def bunny_points(path: str = None, key: str = "verts", stride: int = 2, center: bool = True,
                 device=None) -> PointCloud:
    """PointCloud of ``npz[key][::stride]`` (world units), centred when ``center``."""
    if not path:
        raise UserError("data=bunny needs data.path=FILE (an .npz with key 'verts')")
    if isinstance(stride, bool) or not isinstance(stride, int) or stride < 1:
        raise UserError(f"data.stride must be an integer >= 1 (keep every stride-th point), got {stride!r}")
    file = resolve_path(path)
    if not file.exists():
        raise UserError(f"bunny point cloud not found: {file}")
    with load_array_file(file) as npz:
        if key not in npz:
            raise UserError(f"{file} has no key '{key}' (keys: {', '.join(npz.files)})")
        pts = numeric_array(npz[key], f"{file}:{key}")
    if pts.ndim != 2 or pts.shape[1] != 3 or pts.shape[0] == 0:
        raise UserError(f"{file}:{key} must be an (N, 3) array, got {pts.shape}")
    p = torch.from_numpy(pts[:: max(1, int(stride))].copy())
    if center:
        p = p - p.mean(dim=0)
    return PointCloud(points=p).to(device=device) if device is not None else PointCloud(points=p)
