"""dolly: the dolly-zoom effect (field of view and distance change together).

The subject keeps its on-screen size while a backdrop of pillars shows the change of
perspective. ``subject`` chooses what is framed and measured: ``largest_part`` (default:
the connected part with the most faces, e.g. the cow of ``cow_on_plane.obj``, not its
ground plane) or ``all`` (the whole mesh). ``framing`` chooses how: ``extent`` (default:
each frame's distance is solved so that the subject's projected horizontal extent is
``subject_fraction`` of the image width, :mod:`l3d_app.geometry.dolly_framing`) or
``sphere`` (the subject's bounding sphere keeps its size; exact only for spheres). The
camera looks at the subject's bounding-box centre. Scene and backdrop are rendered in
separate passes and composited by depth, so textured meshes work too; a pass of the
subject alone gives the measured on-screen width (its horizontal extent) reported in
metrics.json. ``print_fov`` writes each frame's field of view on it.
"""

from __future__ import annotations

import torch

from l3d_app.data.backdrops import pillar_backdrop
from l3d_app.errors import UserError
from l3d_app.geometry.camera_paths import dolly_distance
from l3d_app.geometry.dolly_framing import dolly_cameras, extent_distances
from l3d_app.geometry.mesh import Mesh
from l3d_app.geometry.mesh_parts import largest_part_mask, submesh
from l3d_app.registry import DATASETS, RENDERERS, TASKS
from l3d_app.render.evaluation import render_frames
from l3d_app.runtime.annotate import label_frames
from l3d_app.runtime.media import save_gif, save_png
from l3d_app.tasks.common import require_positive


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
    """(N,) on-screen width in pixels: the horizontal extent of the (N, H, W) coverage map, the sum
    over columns of each column's largest coverage (anti-aliased edges count fractionally, so the
    width is sub-pixel; for a disc it equals the widest row)."""
    return alpha.amax(dim=-2).sum(dim=-1)


SUBJECTS = ("largest_part", "all")
FRAMINGS = ("extent", "sphere")


@TASKS.register("dolly")
def dolly(cfg, ctx) -> dict:
    """Render the dolly zoom; write dolly.gif; report the subject width's spread."""
    require_positive(cfg, "image_size", "num_frames", "fps", "batch_frames", "subject_fraction")
    if cfg.subject not in SUBJECTS or cfg.framing not in FRAMINGS:
        raise UserError(f"subject must be one of {', '.join(SUBJECTS)} and framing one of {', '.join(FRAMINGS)}, "
                        f"got subject={cfg.subject} framing={cfg.framing}")
    lo_fov, hi_fov = float(cfg.fov_start), float(cfg.fov_end)
    if not (0 < lo_fov < 180 and 0 < hi_fov < 180):
        raise UserError(f"dolly fov range must lie in (0, 180) degrees, got [{lo_fov}, {hi_fov}]")
    if not 0 < float(cfg.subject_fraction) < 1:
        raise UserError(f"subject_fraction must be in (0, 1), got {cfg.subject_fraction}")
    scene = DATASETS.build(cfg.data, device=ctx.device)
    if not isinstance(scene, Mesh):
        raise UserError("dolly renders a mesh; this data source gives a point cloud")
    subject = scene if cfg.subject == "all" else submesh(scene, largest_part_mask(scene))
    renderer = RENDERERS.build(cfg.renderer)
    lo, hi = subject.bounds()
    centre = (lo + hi) / 2
    fov = torch.linspace(lo_fov, hi_fov, int(cfg.num_frames), dtype=torch.float64)
    view = dict(elevation=float(cfg.elevation), azimuth=float(cfg.azimuth), at=centre.tolist())
    if cfg.framing == "extent":
        dist = extent_distances(subject.verts, fov, float(cfg.subject_fraction), **view)
    else:
        radius = float((subject.verts - centre).norm(dim=-1).max())
        dist = dolly_distance(fov, radius, float(cfg.subject_fraction))
    cams = dolly_cameras(dist, fov, int(cfg.image_size), device=ctx.device, **view)
    background = torch.tensor(list(cfg.background), dtype=torch.float32)
    with ctx.stopwatch.stage("render"):
        alone = render_frames(renderer, subject, cams, int(cfg.batch_frames), desc="dolly subject")
        front = alone if subject is scene else \
            render_frames(renderer, scene, cams, int(cfg.batch_frames), desc="dolly scene")
        frames = front["image"]
        if cfg.backdrop:
            flat = RENDERERS.build({**cfg.renderer, "shading": "flat"})
            back = render_frames(flat, pillar_backdrop(device=ctx.device), cams,
                                 int(cfg.batch_frames), desc="dolly backdrop")
            frames = composite_by_depth(front, back, background)
    seconds = ctx.stopwatch.stages["render"]
    if cfg.print_fov:
        frames = label_frames(frames, [f"fov {v:.0f}" for v in fov.tolist()])
    save_gif(ctx.path("dolly.gif"), frames, fps=float(cfg.fps))
    save_png(ctx.path("first_frame.png"), frames[0])
    save_png(ctx.path("last_frame.png"), frames[-1])
    ctx.logger.image_sequence("dolly/frames", frames)
    widths = subject_width(alone["alpha"])
    for i, (w, d) in enumerate(zip(widths.tolist(), dist.tolist())):
        ctx.logger.log_scalars({"dolly/subject_width_px": w, "dolly/distance": d}, step=i)
    spread = float((widths.max() - widths.min()) / widths.mean())
    return {
        "num_frames": len(cams),
        "image_size": int(cfg.image_size),
        "subject": str(cfg.subject),
        "framing": str(cfg.framing),
        "subject_faces": subject.num_faces,
        "fov_start": lo_fov,
        "fov_end": hi_fov,
        "distance_start": round(float(dist[0]), 4),
        "distance_end": round(float(dist[-1]), 4),
        "subject_width_px": round(float(widths.mean()), 3),
        "subject_width_spread": round(spread, 5),
        "render_seconds": round(seconds, 4),
        "frames_per_second": round(len(cams) / seconds, 3),
    }
