"""Learned models: encodings, NeRF fields, SDF networks and grids, Gaussians, PointNet /
DGCNN, single-view decoders."""

from l3d_app.exports import lazy_exports

# Registering modules: importing the package completes its registries.
from l3d_app.models import nerf, pointnet, dgcnn, sdf_net, sdf_grid, svr_decoders, svr_pseudo  # noqa: F401,E402

__getattr__, __dir__, __all__ = lazy_exports(__name__, {
    "HarmonicEncoding": "encodings",
    "GridEncoding": "encodings",
    "NeRFMLP": "nerf",
    "GridField": "nerf",
    "SDFField": "sdf_net",
    "SDFGridField": "sdf_grid",
    "GaussianModel": "gaussians",
    "PointNetCls": "pointnet",
    "PointNetSeg": "pointnet",
    "DGCNN": "dgcnn",
})
