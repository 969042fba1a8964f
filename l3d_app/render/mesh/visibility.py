"""Visibility culling of an extracted mesh: keep only the faces some input camera sees.

A field trained from images is only constrained where a training ray looks. Marching cubes of
it also returns what no camera saw: the leftover of the initial sphere below a ground plate
seen only from above, surfaces inside closed objects. :func:`cull_unseen_faces` renders the
mesh's own depth maps through the cameras (our rasteriser, ``scale`` times finer than the
cameras) and keeps a face when its centroid is seen by at least one camera
(:func:`l3d_app.geometry.visibility.observed_mask`: inside the image, in front of the camera,
no farther than the mesh's depth at that pixel plus ``tolerance``, and facing the camera).
Where no camera looks the result is free space (an open mesh), not a guess.
"""

from __future__ import annotations

from typing import Tuple

import torch

from l3d_app.errors import UserError
from l3d_app.geometry.cameras import Cameras
from l3d_app.geometry.mesh import Mesh
from l3d_app.geometry.mesh_parts import submesh
from l3d_app.geometry.visibility import observed_mask
from l3d_app.render.mesh.rgbd import true_depth_maps


@torch.no_grad()
def seen_faces(mesh: Mesh, cameras: Cameras, tolerance: float, scale: int = 4) -> torch.Tensor:
    """(F,) bool: faces of ``mesh`` whose centroid at least one of ``cameras`` sees
    (``tolerance`` in world units: how far behind the mesh's own depth a centroid may lie)."""
    if not float(tolerance) > 0:
        raise UserError(f"tolerance must be > 0 (world units), got {tolerance}")
    mesh = mesh.to("cpu")
    cameras = cameras.to("cpu")
    depth = true_depth_maps(mesh, cameras, scale=int(scale))                 # (B, sH, sW), +inf empty
    centroids = mesh.face_verts().mean(dim=1)                               # (F, 3)
    return observed_mask(centroids, cameras, depth, float(tolerance), normals=mesh.face_normals())


def cull_unseen_faces(mesh: Mesh, cameras: Cameras, tolerance: float, scale: int = 4) -> Tuple[Mesh, float]:
    """The part of ``mesh`` the cameras see (:func:`seen_faces`) and the share of the mesh's
    area removed (0..1). A mesh nothing of which is seen is returned whole (share 0) rather
    than empty, so a caller never writes an empty file."""
    keep = seen_faces(mesh, cameras, tolerance, scale)
    if not bool(keep.any()):
        return mesh, 0.0
    area = mesh.to("cpu").face_areas()
    removed = float(area[~keep].sum() / area.sum().clamp_min(1e-30))
    return submesh(mesh, keep.to(mesh.faces.device)), removed


def cull_to_training_views(mesh: Mesh, data, box, resolution: int) -> Tuple[Mesh, float]:
    """The extracted ``mesh`` without the faces no TRAINING camera of ``data`` sees (the leftover of
    the initialisation below a plate seen from above, surfaces inside objects) and the share of its
    area removed. The depth tolerance is two marching-cubes cells of the ``box`` ((2, 3) or nested
    lists) at ``resolution``: the grid's own precision, not a tuned value."""
    lo, hi = torch.as_tensor(box, dtype=torch.float64)
    tolerance = 2.0 * float((hi - lo).max()) / int(resolution)
    cams = data.cameras[data.train.to(data.cameras.device)]
    return cull_unseen_faces(mesh, cams, tolerance)
