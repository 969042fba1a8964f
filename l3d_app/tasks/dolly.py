"""dolly: the dolly-zoom effect (field of view and distance change together).

The subject (any mesh; the built-in scene by default) keeps its on-screen size while a
backdrop of pillars shows the change of perspective. Subject and backdrop are rendered
in separate passes and composited by depth, so textured subjects work too; the subject
pass also gives the measured on-screen width reported in metrics.json.
"""

from __future__ import annotations

import torch

from l3d_app.data.backdrops import pillar_backdrop
from l3d_app.geometry.camera_paths import dolly_zoom
from l3d_app.registry import DATASETS, RENDERERS, TASKS
from l3d_app.runtime.media import save_gif
from l3d_app.tasks.common import render_frames, require_positive


def composite_by_depth(a: dict, b: dict, background: torch.Tensor) -> torch.Tensor:
    """Per pixel, layer the nearer of two renders over the farther one.

    Each render has image (N, H, W, 3) already composited over ``background`` (3,),
    alpha (N, H, W) and depth (N, H, W). Returns the (N, H, W, 3) composite.
    """
    inf = torch.tensor(float("inf"))
    a_first = (torch.where(a["alpha"] > 0, a["depth"], inf)
               <= torch.where(b["alpha"] > 0, b["depth"], inf))[..., None]
    alpha_a, alpha_b = a["alpha"][..., None], b["alpha"][..., None]
    rgb_a = a["image"] - (1 - alpha_a) * background  # premultiplied colour
    rgb_b = b["image"] - (1 - alpha_b) * background
    near_rgb, far_rgb = torch.where(a_first, rgb_a, rgb_b), torch.where(a_first, rgb_b, rgb_a)
    near_alpha, far_alpha = torch.where(a_first, alpha_a, alpha_b), torch.where(a_first, alpha_b, alpha_a)
    return near_rgb + (1 - near_alpha) * (far_rgb + (1 - far_alpha) * background)


def subject_width(alpha: torch.Tensor) -> torch.Tensor:
    """(N,) on-screen width in pixels: the widest row of the (N, H, W) coverage map
    (fractional coverage counts fractionally, so anti-aliased edges give sub-pixel widths)."""
    return alpha.sum(dim=-1).amax(dim=-1)


@TASKS.register("dolly")
def dolly(cfg, ctx) -> dict:
    """Render the dolly zoom; write dolly.gif; report the subject width's spread."""
    require_positive(cfg, "image_size", "num_frames", "fps", "batch_frames", "subject_fraction")
    subject = DATASETS.build(cfg.data, device=ctx.device)
    renderer = RENDERERS.build(cfg.renderer)
    radius = float(subject.verts.norm(dim=-1).max())
    cams, dist = dolly_zoom(int(cfg.num_frames), (cfg.fov_start, cfg.fov_end), radius,
                            float(cfg.subject_fraction), int(cfg.image_size),
                            elevation=float(cfg.elevation), device=ctx.device)
    background = torch.tensor(list(cfg.background), dtype=torch.float32)
    with ctx.stopwatch.stage("render"):
        front = render_frames(renderer, subject, cams, int(cfg.batch_frames), desc="dolly subject")
        frames = front["image"]
        if cfg.backdrop:
            flat = RENDERERS.build({**cfg.renderer, "shading": "flat"})
            back = render_frames(flat, pillar_backdrop(device=ctx.device), cams,
                                 int(cfg.batch_frames), desc="dolly backdrop")
            frames = composite_by_depth(front, back, background)
    seconds = ctx.stopwatch.stages["render"]
    save_gif(ctx.path("dolly.gif"), frames, fps=float(cfg.fps))
    ctx.logger.image_sequence("dolly/frames", frames)
    widths = subject_width(front["alpha"])
    for i, (w, d) in enumerate(zip(widths.tolist(), dist.tolist())):
        ctx.logger.log_scalars({"dolly/subject_width_px": w, "dolly/distance": d}, step=i)
    spread = float((widths.max() - widths.min()) / widths.mean())
    return {
        "num_frames": len(cams),
        "image_size": int(cfg.image_size),
        "subject_width_px": round(float(widths.mean()), 3),
        "subject_width_spread": round(spread, 5),
        "render_seconds": round(seconds, 4),
        "frames_per_second": round(len(cams) / seconds, 3),
    }
