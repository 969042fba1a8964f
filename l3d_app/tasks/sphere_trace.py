"""sphere_trace: a sphere-traced turntable of an analytic SDF (any ``data=*_implicit`` shape).

No mesh is made: every pixel's ray is marched through the data source's analytic SDF
(:func:`l3d_app.data.surfaces.make_sdf`, the shape and parameters of ``data``) by
:func:`l3d_app.render.sdf.sphere_tracing.sphere_trace_box` inside the shape's bounds, and
shaded by its autograd normal. Writes ``turntable.gif``, ``frame0.png``, ``depth0.png``
(depth normalised by its maximum, viridis, as the course shows depth) and metrics.json:
``hit_fraction``, ``mean_iterations`` (SDF evaluations per ray), ``max_abs_sdf_at_hits``
(the hits' distance to the surface; <= eps by construction, a broken tracer shows here).
"""

from __future__ import annotations

import torch

from l3d_app.data.surfaces import make_sdf
from l3d_app.errors import UserError
from l3d_app.geometry.rays import camera_rays
from l3d_app.registry import CAMERA_PATHS, TASKS
from l3d_app.render.volume.diagnostics import depth_colormap
from l3d_app.render.sdf.sphere_tracing import render_sdf_shaded, sphere_trace_box
from l3d_app.runtime.media import save_gif, save_png
from l3d_app.runtime.progress import progress
from l3d_app.tasks.common import require_nonnegative, require_positive

_SDF_KEYS = ("major_radius", "minor_radius", "radii", "exponents", "radius", "size")


def _analytic_sdf(data_cfg):
    if data_cfg.get("name") != "implicit":
        raise UserError("sphere_trace traces an analytic SDF: use data=<shape>_implicit "
                        "(torus_implicit, sphere_implicit, box_implicit, superquadric_implicit, union_implicit)")
    kwargs = {k: (list(data_cfg[k]) if k in ("radii", "exponents", "size") else float(data_cfg[k]))
              for k in _SDF_KEYS if data_cfg.get(k) is not None}
    return make_sdf(str(data_cfg.shape), **kwargs)


@TASKS.register("sphere_trace")
def sphere_trace_task(cfg, ctx) -> dict:
    """Trace and shade every frame of the turntable; write the gif, depth picture and metrics."""
    require_positive(cfg, "image_size", "num_frames", "fps", "max_iters", "eps", "inexact_step_scale")
    require_nonnegative(cfg, "box_padding")
    sdf = _analytic_sdf(cfg.data)
    lo, hi = sdf.bounds()
    pad = float(cfg.box_padding)
    box = ([c - pad for c in lo], [c + pad for c in hi])
    step_scale = 1.0 if sdf.exact else float(cfg.inexact_step_scale)
    cams = CAMERA_PATHS.build(cfg.camera, device=ctx.device)
    H, W = cams.height, cams.width
    frames, hits, iters, worst, depth0 = [], [], [], 0.0, None
    with ctx.stopwatch.stage("render"):
        for i in progress(range(len(cams)), desc="sphere_trace"):
            o, d = camera_rays(cams[i])
            o, d = o.reshape(-1, 3), d.reshape(-1, 3)
            res = sphere_trace_box(sdf, o, d, box, max_iters=int(cfg.max_iters), eps=float(cfg.eps),
                                   step_scale=step_scale)
            rgb = render_sdf_shaded(sdf, o, d, box, background=float(cfg.background), max_iters=int(cfg.max_iters),
                                    eps=float(cfg.eps), step_scale=step_scale)
            frames.append(rgb.reshape(H, W, 3).cpu())
            hits.append(res.hit.float().mean())
            iters.append(res.iterations.float().mean())
            if bool(res.hit.any()):
                worst = max(worst, float(sdf(res.points[res.hit & ~res.inside]).abs().max()))
            if i == 0:
                z = (res.points - o) @ cams.R[0, 2]                       # camera-frame depth
                depth0 = depth_colormap(z.reshape(H, W), res.hit.reshape(H, W)).cpu()
    seconds = ctx.stopwatch.stages["render"]
    frames = torch.stack(frames)
    save_gif(ctx.path("turntable.gif"), frames, fps=float(cfg.fps))
    save_png(ctx.path("frame0.png"), frames[0])
    save_png(ctx.path("depth0.png"), depth0)
    ctx.logger.image_sequence("sphere_trace/frames", frames)
    ctx.logger.image("sphere_trace/depth0", depth0, 0)
    return {
        "shape": str(cfg.data.shape),
        "num_frames": len(cams),
        "image_size": int(cfg.image_size),
        "hit_fraction": round(float(torch.stack(hits).mean()), 5),
        "mean_iterations": round(float(torch.stack(iters).mean()), 3),
        "max_abs_sdf_at_hits": worst,
        "render_seconds": round(seconds, 4),
        "frames_per_second": round(len(cams) / seconds, 3),
    }
