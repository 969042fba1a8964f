"""gs_render: render a 3DGS PLY (ours or any standard one) as a turntable gif of panels.

``python main.py task=gs_render ply=FILE [distance=4 elevation=20 image_size=256]``:
cameras on a turntable around the (opacity-weighted) centre of the splats at
``distance`` (0: 2.5x the splats' robust radius), up = world +Y (``up`` to change).
Each frame is colour | depth | mask as the course shows them: the expected depth coloured
with ``depth_cmap`` over one FIXED range for every frame (``depth_range``, default the
camera distance -/+ the splats' robust radius; the course uses [5, 7] at distance 6) and
the accumulated opacity thresholded at ``mask_threshold``. ``path=course``: the course's own 32 views instead
(:func:`~l3d_app.geometry.course_orbit.course_orbit`: azimuths -180..180, elevation 30, distance 6 from the
splats' mean, up -y, focal 5 half-widths; depth over [5, 7] unless ``depth_range`` is given).
Writes ``turntable.gif`` and ``metrics.json`` (n_gaussians, seconds, frames_per_second).
"""

from __future__ import annotations

import time

import torch

from l3d_app.errors import UserError
from l3d_app.geometry.cameras import Cameras, look_at
from l3d_app.geometry.course_orbit import COURSE_DISTANCE, course_orbit
from l3d_app.geometry.gaussian_ply import load_gaussian_ply
from l3d_app.models.gaussians import GaussianModel
from l3d_app.registry import TASKS
from l3d_app.render.gaussians.rasterize import rasterize_gaussians
from l3d_app.render.gaussians.panels import colorize_depth, require_colormap, side_by_side
from l3d_app.runtime.config_values import config_floats
from l3d_app.runtime.media import save_gif
from l3d_app.runtime.paths import resolve_path
from l3d_app.tasks.common import require_positive


@TASKS.register("gs_render")
def gs_render(cfg, ctx) -> dict:
    require_positive(cfg, "num_frames", "image_size")
    cmap = require_colormap(str(cfg.depth_cmap))
    up, background = config_floats(cfg.up, "up", 3), config_floats(cfg.background, "background", 3)
    depth_range = config_floats(cfg.depth_range, "depth_range", 2) if cfg.get("depth_range") else None
    if depth_range and not depth_range[1] > depth_range[0]:
        raise UserError(f"depth_range must be [near, far] with far > near, got {depth_range}")
    path_name = str(cfg.get("path", "turntable"))
    if path_name not in ("turntable", "course"):
        raise UserError(f"path must be turntable or course, got {path_name!r}")
    if not cfg.get("ply"):
        raise UserError("gs_render needs a file: add ply=FILE (a 3DGS point_cloud.ply)")
    path = resolve_path(str(cfg.ply))
    if not path.is_file():
        raise UserError(f"PLY file not found: {path}")
    model = GaussianModel(**load_gaussian_ply(path)).to(ctx.device)
    with torch.no_grad():
        w = torch.sigmoid(model.opacity_logits)
        centre = (model.means * w[:, None]).sum(0) / w.sum().clamp_min(1e-12)
        radius = max(float((model.means - centre).norm(dim=-1).quantile(0.9)), 1e-6)
        dist = float(cfg.distance) if float(cfg.distance) > 0 else 2.5 * radius
        lo, hi = depth_range or (max(dist - radius, 0.0), dist + radius)
        n, size = int(cfg.num_frames), int(cfg.image_size)
        if path_name == "course":        # the course's 32 views around the splats' mean, depth over [5, 7]
            cams = course_orbit(size, model.means.mean(0).cpu().tolist(), device=ctx.device)
            n, (lo, hi) = len(cams), depth_range or (COURSE_DISTANCE - 1.0, COURSE_DISTANCE + 1.0)
        else:
            azim = torch.arange(n, dtype=torch.float32) * 360.0 / n
            R, t = look_at(dist, float(cfg.elevation), azim, at=centre.cpu().tolist(), up=up)
            f = size / 2 / torch.tan(torch.deg2rad(torch.tensor(float(cfg.fov) / 2)))
            cams = Cameras(R, t, f, f, size / 2, size / 2, size, size).to(ctx.device)
        t0 = time.perf_counter()
        outs = [rasterize_gaussians(model.means, model.log_scales, model.quats, model.opacity_logits, model.sh,
                                    int(cfg.sh_degree), cams[i], background) for i in range(n)]
        fps = n / max(time.perf_counter() - t0, 1e-9)
        frames = []
        for o in outs:
            mask = o["alpha"][0] > float(cfg.mask_threshold)
            depth = colorize_depth(o["expected_depth"][0], lo, hi, mask=mask, cmap=cmap)
            frames.append(side_by_side([o["color"][0], depth, mask.float()]))
    save_gif(ctx.path("turntable.gif"), torch.stack(frames), fps=float(cfg.fps))
    return {"n_gaussians": model.num, "frames_per_second": round(fps, 3), "depth_range": [round(lo, 4), round(hi, 4)],
            "frames": n, "path": path_name}
