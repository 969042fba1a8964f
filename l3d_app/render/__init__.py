"""Renderers, by what they render: ``mesh/`` (hard and soft rasterisers, shaders, RGB-D),
``points/`` (disc splats, the pseudo-renderer), ``volume/`` (emission-absorption along rays,
samplers and estimators, occupancy grids), ``sdf/`` (SDF densities, SDF volume rendering,
sphere tracing), ``gaussians/`` (tiled Gaussian splatting); shared pictures (turntables,
charts, palettes, evaluation views) at this level. Pure functions over tensors where
possible; imports geometry, never models/data/tasks."""

from l3d_app.exports import lazy_exports

# Registering subpackages: importing the package completes its registries.
from l3d_app.render import mesh, points, volume, sdf  # noqa: F401,E402

__getattr__, __dir__, __all__ = lazy_exports(__name__, {
    "MeshRenderer": "mesh.renderer",
    "SoftMeshRenderer": "mesh.soft_rasterize",
    "PointRenderer": "points.renderer",
    "VolumeRenderer": "volume.renderer",
    "rasterize_gaussians": "gaussians.rasterize",
    "render_rays": "volume.rendering",
    "render_field_rays": "volume.radiance",
    "render_sdf_rays": "sdf.volume",
    "sphere_trace": "sdf.sphere_tracing",
    "rgbd_from_mesh": "mesh.rgbd",
    "true_depth_maps": "mesh.rgbd",
})
