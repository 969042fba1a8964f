"""gs_render: render a 3DGS PLY (ours or any standard one) as a turntable gif.

``python main.py task=gs_render ply=FILE [distance=4 elevation=20 image_size=256]``:
cameras on a turntable around the (opacity-weighted) centre of the splats at
``distance`` (0: 2.5x the splats' robust radius), up = world +Y (``up`` to change).
Writes ``turntable.gif`` and ``metrics.json`` (n_gaussians, seconds, frames_per_second).
"""

from __future__ import annotations

import time

import torch

from l3d_app.errors import UserError
from l3d_app.geometry.cameras import Cameras, look_at
from l3d_app.geometry.gaussian_ply import load_gaussian_ply
from l3d_app.registry import TASKS
from l3d_app.render.gaussians import rasterize_gaussians
from l3d_app.runtime.media import save_gif
from l3d_app.runtime.paths import resolve_path


@TASKS.register("gs_render")
def gs_render(cfg, ctx) -> dict:
    if not cfg.get("ply"):
        raise UserError("gs_render needs a file: add ply=FILE (a 3DGS point_cloud.ply)")
    path = resolve_path(str(cfg.ply))
    if not path.is_file():
        raise UserError(f"PLY file not found: {path}")
    model = load_gaussian_ply(path).to(ctx.device)
    with torch.no_grad():
        w = torch.sigmoid(model.opacity_logits)
        centre = (model.means * w[:, None]).sum(0) / w.sum().clamp_min(1e-12)
        radius = float((model.means - centre).norm(dim=-1).quantile(0.9))
        dist = float(cfg.distance) if float(cfg.distance) > 0 else 2.5 * max(radius, 1e-6)
        n, size = int(cfg.num_frames), int(cfg.image_size)
        azim = torch.arange(n, dtype=torch.float32) * 360.0 / n
        R, t = look_at(dist, float(cfg.elevation), azim, at=centre.cpu().tolist(), up=list(cfg.up))
        f = size / 2 / torch.tan(torch.deg2rad(torch.tensor(float(cfg.fov) / 2)))
        cams = Cameras(R, t, f, f, size / 2, size / 2, size, size).to(ctx.device)
        t0 = time.perf_counter()
        frames = torch.cat([rasterize_gaussians(model.means, model.log_scales, model.quats, model.opacity_logits,
                                                model.sh, int(cfg.sh_degree), cams[i], list(cfg.background))["color"]
                            for i in range(n)])
        fps = n / max(time.perf_counter() - t0, 1e-9)
    save_gif(ctx.path("turntable.gif"), frames.clamp(0, 1), fps=float(cfg.fps))
    return {"n_gaussians": model.num, "frames_per_second": round(fps, 3)}
