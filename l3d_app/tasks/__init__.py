"""Tasks: one file per task, each wiring library pieces and registering itself in
:data:`l3d_app.registry.TASKS`. Importing this package registers every task (and, through
the tasks' own imports, what they build). Shared wiring lives in ``common.py`` and the
``*_common.py`` helpers; a task never imports another task.
"""

from l3d_app.tasks import (box, dolly, fit_mesh, fit_point, fit_vox, gs_render,  # noqa: F401
                           gs_train, neural_sdf, pointnet_cls, pointnet_robustness, pointnet_seg,
                           render360, sds_image, sds_mesh, sds_nerf, surface_tradeoff, svr_eval,
                           surfels, svr_train, train_nerf, train_prior, volsdf, process_images,
                           ray_diagnostics, sphere_trace, stereo_depth, pca_normals, sampling_variance, render_path, view)
