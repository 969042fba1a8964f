"""render360: a 360-degree turntable gif of a mesh (built-in scene or any mesh file)."""

from __future__ import annotations

from l3d_app.geometry.camera_paths import turntable
from l3d_app.registry import DATASETS, RENDERERS, TASKS
from l3d_app.runtime.media import save_gif
from l3d_app.tasks.common import render_frames, require_positive


@TASKS.register("render360")
def render360(cfg, ctx) -> dict:
    """Render ``num_frames`` views around the mesh; write turntable.gif; log the frames."""
    require_positive(cfg, "image_size", "num_frames", "fps", "distance", "fov", "batch_frames")
    mesh = DATASETS.build(cfg.data, device=ctx.device)
    renderer = RENDERERS.build(cfg.renderer)
    cams = turntable(int(cfg.num_frames), float(cfg.distance), float(cfg.elevation),
                     float(cfg.fov), int(cfg.image_size), device=ctx.device)
    with ctx.stopwatch.stage("render"):
        out = render_frames(renderer, mesh, cams, int(cfg.batch_frames), desc="render360")
    seconds = ctx.stopwatch.stages["render"]
    save_gif(ctx.path("turntable.gif"), out["image"], fps=float(cfg.fps))
    ctx.logger.image_sequence("render360/frames", out["image"])
    coverage = float(out["alpha"].mean())
    ctx.logger.log_scalars({"render360/frames_per_second": len(cams) / seconds,
                            "render360/coverage": coverage}, step=0)
    return {
        "num_frames": len(cams),
        "image_size": int(cfg.image_size),
        "n_verts": mesh.num_verts,
        "n_faces": mesh.num_faces,
        "render_seconds": round(seconds, 4),
        "frames_per_second": round(len(cams) / seconds, 3),
        "coverage": round(coverage, 5),
    }
