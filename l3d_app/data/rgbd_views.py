"""RGB-D data source (``data=rgbd``): a built-in scene seen by a ring of depth cameras,
unprojected into one coloured point cloud in the world frame."""

from __future__ import annotations

from l3d_app.data.scenes import builtin_scene
from l3d_app.errors import UserError
from l3d_app.geometry.cameras import look_at_cameras
from l3d_app.geometry.pointcloud import PointCloud
from l3d_app.geometry.rgbd import unproject_depth
from l3d_app.render.mesh.rgbd import rgbd_from_mesh
from l3d_app.registry import DATASETS


@DATASETS.register("rgbd")
def rgbd_views(scene: str = "orientation", num_views: int = 4, image_size: int = 128,
               distance: float = 3.0, elevation: float = 20.0, fov: float = 50.0,
               device=None) -> PointCloud:
    """Render ``scene`` (see :data:`l3d_app.data.scenes.SCENES`) unlit from ``num_views``
    azimuths ``360 k / num_views`` degrees at ``distance`` (world units) and ``elevation``
    (degrees), square images of ``image_size`` px with field of view ``fov`` (degrees);
    unproject every covered pixel. Returns the union (P, 3) with albedo colours."""
    if int(num_views) < 1:
        raise UserError(f"num_views must be >= 1, got {num_views}")
    mesh = builtin_scene(scene, device=device)
    azim = [360.0 * k / int(num_views) for k in range(int(num_views))]
    cams = look_at_cameras(distance, elevation, azim, fov, int(image_size), device=mesh.device)
    views = rgbd_from_mesh(mesh, cams)
    return unproject_depth(views["depth"], cams, views["rgb"], views["mask"])
