"""Data sources: built-in procedural scenes and datasets, loaders for real formats. Every
module here registers its sources in :data:`l3d_app.registry.DATASETS` on import."""

from l3d_app.exports import lazy_exports

# Registering modules: importing the package completes its registries.
from l3d_app.data import scenes, mesh_points, rgbd_views, surfaces, box_images, bunny, nerf_views, nerf_formats, point_sets, shape_parts, shape_scans, svr_shapes, room_scene, colmap, photos, nerfstudio, course_rgbd, course_nerf  # noqa: F401,E402

__getattr__, __dir__, __all__ = lazy_exports(__name__, {
    "builtin_scene": "scenes",
    "MultiViewData": "nerf_views",
    "PointCloudData": "point_sets",
})
