"""Import every module that registers something, so registries are complete.

Registration happens at import time (``@RENDERERS.register(...)``); the app calls
:func:`load_all` once before building anything from a config.
"""

from __future__ import annotations

import importlib

MODULES = (
    "l3d_app.data.scenes",
    "l3d_app.render.mesh_renderer",
    "l3d_app.render.soft_rasterize",
    "l3d_app.render.points",
    "l3d_app.data.rgbd_views",
    "l3d_app.data.mesh_points",
    "l3d_app.tasks.render360",
    "l3d_app.tasks.dolly",
    "l3d_app.data.surfaces",
    "l3d_app.tasks.surface_tradeoff",
    "l3d_app.data.box_images",
    "l3d_app.render.volume",
    "l3d_app.render.estimators",
    "l3d_app.render.densities",
    "l3d_app.render.neus",
    "l3d_app.runtime.optim",
    "l3d_app.tasks.box",
    "l3d_app.models.nerf",
    "l3d_app.data.nerf_views",
    "l3d_app.data.nerf_formats",
    "l3d_app.tasks.train_nerf",
    "l3d_app.data.point_sets",
    "l3d_app.data.shape_parts",
    "l3d_app.models.pointnet",
    "l3d_app.models.dgcnn",
    "l3d_app.tasks.pointnet_cls",
    "l3d_app.tasks.pointnet_seg",
    "l3d_app.tasks.pointnet_robustness",
    "l3d_app.losses.occupancy",
    "l3d_app.losses.mesh_regularizers",
    "l3d_app.tasks.fit_vox",
    "l3d_app.tasks.fit_point",
    "l3d_app.tasks.fit_mesh",
    "l3d_app.models.gaussians",
    "l3d_app.tasks.gs_train",
    "l3d_app.tasks.gs_render",
    "l3d_app.models.sdf_net",
    "l3d_app.models.sdf_grid",
    "l3d_app.data.bunny",
    "l3d_app.tasks.volsdf",
    "l3d_app.tasks.neural_sdf",
    "l3d_app.tasks.svr_train",
    "l3d_app.tasks.svr_eval",
    "l3d_app.data.svr_shapes",
    "l3d_app.models.svr_decoders",
    "l3d_app.models.svr_pseudo",
    "l3d_app.diffusion.builtin_prior",
    "l3d_app.tasks.train_prior",
    "l3d_app.tasks.sds_image",
    "l3d_app.diffusion.stable_diffusion",
    "l3d_app.tasks.sds_mesh",
    "l3d_app.tasks.sds_nerf",
)


def load_all() -> None:
    """Import all registering modules (idempotent)."""
    for name in MODULES:
        importlib.import_module(name)
