"""Renderers: mesh rasteriser + shaders, soft rasteriser, point splatting, volume
rendering of fields along rays, sphere tracing, Gaussian splatting. Pure functions over
tensors where possible; imports geometry, never models/data/tasks."""

from l3d_app.exports import lazy_exports

# Registering modules: importing the package completes its registries.
from l3d_app.render import mesh_renderer, soft_rasterize, points, volume  # noqa: F401,E402
from l3d_app.render import densities, estimators, neus  # noqa: F401,E402  (DENSITIES, SAMPLERS)

__getattr__, __dir__, __all__ = lazy_exports(__name__, {
    "MeshRenderer": "mesh_renderer",
    "SoftMeshRenderer": "soft_rasterize",
    "PointRenderer": "points",
    "VolumeRenderer": "volume",
    "rasterize_gaussians": "gaussians",
    "render_rays": "rendering",
    "render_field_rays": "radiance",
    "render_sdf_rays": "sdf_volume",
    "sphere_trace": "sphere_tracing",
    "rgbd_from_mesh": "rgbd",
    "true_depth_maps": "rgbd",
})
