"""render360: a turntable gif of a mesh or point cloud (built-in scene, file, or surface).

The camera path comes from the ``camera`` group (a 360-degree turntable by default, or a
single relative view); meshes go through ``renderer``, point clouds through
``point_renderer``. With ``points_beside=true`` a mesh's frames get a second panel on the
right: ``points_beside_samples`` points drawn area-uniformly on its surface (coloured like the
mesh where it has colours), rendered by ``point_renderer`` from the same cameras.
"""

from __future__ import annotations

import torch

from l3d_app.errors import UserError
from l3d_app.geometry.mesh import Mesh
from l3d_app.geometry.mesh_colors import gradient_colors
from l3d_app.geometry.sampling import sample_points_on_mesh
from l3d_app.registry import CAMERA_PATHS, DATASETS, RENDERERS, TASKS
from l3d_app.render.evaluation import render_frames
from l3d_app.runtime.media import save_gif, save_png
from l3d_app.tasks.common import check_output_knobs, require_positive


def build_scene(cfg, device):
    """The data source's Mesh or PointCloud, re-textured if ``retexture.enabled``."""
    scene = DATASETS.build(cfg.data, device=device)
    if cfg.retexture.enabled:
        if not isinstance(scene, Mesh):
            raise UserError("retexture applies to meshes; this data source gives a point cloud")
        scene = gradient_colors(scene, cfg.retexture.axis, cfg.retexture.color1, cfg.retexture.color2)
    return scene


@TASKS.register("render360")
def render360(cfg, ctx) -> dict:
    """Render the camera path's views; write turntable.gif (+ first frame PNG); log frames."""
    require_positive(cfg, "image_size", "num_frames", "fps", "distance", "fov", "batch_frames")
    beside = bool(cfg.get("points_beside", False))
    if beside:
        require_positive(cfg, "points_beside_samples")
    check_output_knobs(cfg)
    cams = CAMERA_PATHS.build(cfg.camera, device=ctx.device)
    scene = build_scene(cfg, ctx.device)
    is_mesh = isinstance(scene, Mesh)
    if beside and not is_mesh:
        raise UserError("points_beside shows a mesh's sampled points; this data source is a point cloud")
    renderer = RENDERERS.build(cfg.renderer if is_mesh else cfg.point_renderer)
    with ctx.stopwatch.stage("render"):
        out = render_frames(renderer, scene, cams, int(cfg.batch_frames), desc="render360")
    seconds = ctx.stopwatch.stages["render"]
    frames = out["image"]
    if beside:
        cloud = sample_points_on_mesh(scene.to("cpu"), int(cfg.points_beside_samples), ctx.generator,  # CPU draws
                                      return_colors=scene.vert_colors is not None or scene.has_texture)
        cloud = cloud.to(device=ctx.device)
        points = render_frames(RENDERERS.build(cfg.point_renderer), cloud, cams, int(cfg.batch_frames),
                               desc="render360 points", keys=("image",))
        frames = torch.cat([frames, points["image"]], dim=2)             # (N, H, 2W, 3): mesh | points
    save_gif(ctx.path("turntable.gif"), frames, fps=float(cfg.fps))
    save_png(ctx.path("frame0.png"), frames[0])
    ctx.logger.image_sequence("render360/frames", frames)
    coverage = float(out["alpha"].mean())
    ctx.logger.log_scalars({"render360/frames_per_second": len(cams) / seconds,
                            "render360/coverage": coverage}, step=0)
    size = {"n_verts": scene.num_verts, "n_faces": scene.num_faces} if is_mesh else \
        {"n_points": scene.num_points}
    return {
        "num_frames": len(cams),
        "image_size": int(cfg.image_size),
        **size,
        "render_seconds": round(seconds, 4),
        "frames_per_second": round(len(cams) / seconds, 3),
        "coverage": round(coverage, 5),
        **({"points_beside_samples": int(cfg.points_beside_samples)} if beside else {}),
    }
