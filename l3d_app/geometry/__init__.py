"""Geometry: cameras, rays, transforms, meshes, point clouds, voxels, SDF primitives,
sampling and exact point-to-mesh distances. Imports nothing above :mod:`l3d_app.runtime`."""

from l3d_app.exports import lazy_exports

# Registering modules: importing the package completes its registries.
from l3d_app.geometry import camera_paths  # noqa: F401,E402

__getattr__, __dir__, __all__ = lazy_exports(__name__, {
    "Cameras": "cameras",
    "look_at": "cameras",
    "look_at_cameras": "cameras",
    "Mesh": "mesh",
    "PointCloud": "pointcloud",
    "load_mesh": "mesh_io",
    "save_mesh": "mesh_io",
    "camera_rays": "rays",
    "sample_surface": "sampling",
    "sample_points_on_mesh": "sampling",
    "sdf_to_mesh": "marching_cubes",
    "unproject_depth": "rgbd",
    "turntable": "camera_paths",
})
