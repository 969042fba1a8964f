"""A mesh of a splat model's surface: TSDF fusion of its rendered depth in the training views,
marching cubes, culling to what the training cameras see, and scores against a true surface.

:func:`fused_mesh` renders every training view (``render(view) -> {"median_depth", "alpha",
"color"}``), keeps the pixels where the accumulated opacity passes 0.5 (where the median depth,
the depth at which the transmittance crosses 0.5, is defined), sizes the voxel grid by the scene:
the box of those pixels' points (inside the data's scene box, without the 0.1% outermost per axis)
over ``resolution`` voxels along its longest side, the truncation ``truncation`` voxels, the grid
over that box grown by 5% and the truncation, fuses depth and colour
(:func:`~l3d_app.geometry.tsdf.fuse_depth_maps`, free space carved by the transparent pixels),
meshes the zero level (:func:`~l3d_app.geometry.tsdf.tsdf_mesh`) and keeps the faces some training
camera sees (:func:`~l3d_app.render.mesh.visibility.cull_unseen_faces`, tolerance two voxels: the
grid's own precision; depth maps at twice the cameras' resolution, a quarter of the cost of four times). :func:`truth_scores` scores a mesh as volsdf's is scored.
"""

from __future__ import annotations

from typing import Callable, Dict, Optional, Sequence, Tuple

import torch

from l3d_app.errors import UserError
from l3d_app.geometry.cameras import Cameras
from l3d_app.geometry.depth_normals import depth_to_points
from l3d_app.geometry.mesh import Mesh
from l3d_app.geometry.tsdf import fuse_depth_maps, tsdf_mesh
from l3d_app.metrics.surface_scores import surface_scores
from l3d_app.render.mesh.rgbd import true_depth_maps
from l3d_app.render.mesh.visibility import cull_unseen_faces
from l3d_app.runtime.progress import progress

SURFACE_ALPHA = 0.5     # a pixel holds a surface where its accumulated opacity passes this (the median depth's level)
BOX_TAIL = 1e-3         # the surface's box leaves out this share of the points on each side of each axis ...
BOX_MARGIN = 0.05       # ... and is grown by this share of its longest side (plus the truncation) for the fusion
CULL_SCALE = 2          # the culling's depth maps at this many times the cameras' resolution (volsdf's: 4)


def surface_box(points: torch.Tensor):
    """(lo (3,), hi (3,)) of the points (N, 3) between their ``BOX_TAIL`` and ``1 - BOX_TAIL``
    quantiles per axis: the rendered surface's extent without the few stray splats far out."""
    n = points.shape[0]
    k_lo, k_hi = max(1, int(BOX_TAIL * n)), max(1, n - int(BOX_TAIL * n))
    return points.kthvalue(k_lo, 0).values, points.kthvalue(k_hi, 0).values


@torch.no_grad()
def fused_mesh(render: Callable[[int], Dict[str, torch.Tensor]], views: Sequence[int], cams: Cameras,
               scene_box: torch.Tensor, resolution: int, truncation: float, cull: bool = True
               ) -> Tuple[Optional[Mesh], Dict[str, float]]:
    """(mesh or None when no surface was fused, figures: ``mesh_voxel``, ``mesh_truncation`` (world
    units), ``mesh_culled_area``); see the module docstring. ``cams``: the cameras of ``views``."""
    depth, valid, color = [], [], []
    for v in progress(list(views), desc="surfels: depth of the training views"):
        out = render(int(v))
        depth.append(out["median_depth"][0])
        valid.append(out["alpha"][0] > SURFACE_ALPHA)
        color.append(out["color"][0].clamp(0, 1))
    depth, valid, color = torch.stack(depth), torch.stack(valid), torch.stack(color)
    valid &= depth > 0
    points = depth_to_points(depth, cams.to(device=depth.device))[valid]
    box = scene_box.to(points)
    points = points[((points >= box[0]) & (points <= box[1])).all(-1)]
    if points.shape[0] == 0:
        return None, {"mesh_faces": 0}
    lo, hi = surface_box(points)
    voxel = float((hi - lo).max()) / int(resolution)
    trunc = float(truncation) * voxel
    pad = BOX_MARGIN * float((hi - lo).max()) + trunc
    box = torch.stack([torch.maximum(lo - pad, box[0]), torch.minimum(hi + pad, box[1])])
    stats = {"mesh_voxel": round(voxel, 6), "mesh_truncation": round(trunc, 6)}
    try:
        vol = fuse_depth_maps(depth, cams, voxel, trunc, colors=color, valid=valid, box=box.tolist())
        mesh = tsdf_mesh(vol)
    except UserError:
        return None, {**stats, "mesh_faces": 0}
    if cull:
        mesh, stats["mesh_culled_area"] = cull_unseen_faces(mesh, cams, 2.0 * voxel, scale=CULL_SCALE)
    stats["mesh_faces"] = int(mesh.num_faces)
    return mesh, stats


@torch.no_grad()
def truth_scores(mesh: Mesh, truth: Mesh, cams: Cameras, n: int, threshold: float, seed: int = 2) -> Dict[str, float]:
    """:func:`~l3d_app.metrics.surface_scores.surface_scores` of ``mesh`` against ``truth``, the
    observed part being what ``cams`` (the training cameras) see of the truth (depth at 4x their
    resolution); rounded to 6 digits."""
    cams = cams.to("cpu")
    depth = true_depth_maps(truth.to("cpu"), cams, scale=4)
    scores = surface_scores(mesh, truth, cameras=cams, depth_maps=depth, n=int(n), threshold=float(threshold),
                            seed=seed)
    return {k: round(v, 6) for k, v in scores.items()}
