"""Point clouds sampled on a mesh surface, coloured by albedo or by PCA normals."""

from __future__ import annotations

from typing import Optional

import torch

from l3d_app.data.scenes import builtin_scene, mesh_file
from l3d_app.errors import UserError
from l3d_app.geometry.normals import estimate_normals
from l3d_app.geometry.pointcloud import PointCloud
from l3d_app.geometry.sampling import sample_points_on_mesh
from l3d_app.registry import DATASETS


@DATASETS.register("mesh_points")
def mesh_points(scene: str = "orientation", path: Optional[str] = None, num_samples: int = 20000,
                color: str = "albedo", k: int = 16, seed: int = 0, device=None) -> PointCloud:
    """``num_samples`` area-uniform points on a built-in ``scene`` (or the mesh file ``path``).

    ``color``: 'albedo' (the mesh's colours/texture at each point) or 'normals' (normals
    estimated by PCA over ``k`` neighbours, oriented outward, shown as (n + 1) / 2).
    """
    if color not in ("albedo", "normals"):
        raise UserError(f"data.color must be 'albedo' or 'normals', got {color!r}")
    if int(num_samples) <= 0:
        raise UserError(f"data.num_samples must be positive, got {num_samples}")
    mesh = mesh_file(path) if path else builtin_scene(scene, normalize=True)
    gen = torch.Generator().manual_seed(int(seed))
    has_colors = mesh.vert_colors is not None or mesh.has_texture
    cloud = sample_points_on_mesh(mesh, int(num_samples), generator=gen,
                                  return_colors=has_colors and color == "albedo")
    if color == "normals":
        normals = estimate_normals(cloud.points, k=int(k), orient="outward")
        cloud = PointCloud(cloud.points, colors=(normals + 1) / 2, normals=normals)
    return cloud if device is None else cloud.to(device)
