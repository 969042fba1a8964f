"""box: recover an SDF box (centre, side lengths) from the course's four box images.

The model is rendered exactly as the course rendered the data (``../shared/data/README.md``):

* rays through pixel CENTRES, unit-length directions (``camera_rays(normalize=True)``);
* 64 samples at ``t = linspace(0, 5, 64)`` along each unit ray (``t`` is distance);
* per-sample opacity = ``alpha * Psi_beta(-sdf)`` (VolSDF Laplace CDF, alpha = 1, beta = 0.05)
  composited in alpha mode (``T_i = prod_{j<i} (1 - alpha_j)``), black background;
* colour = ``clamp(|p - centre|, 0.02, 0.98)``.

With the ground-truth box this reproduces the course images to 3.5e-6 (133 dB PSNR); rays
with camera-frame ``z = 1`` directions (``t`` = depth instead of distance) are off by up to
0.16, so ``depth [0, 5]`` in the README means distance along unit rays.

Training: MSE on ``batch_rays`` random pixels of the four images per step, Adam (``lr``,
decayed exponentially to ``lr * lr_final_factor``), through the shared :func:`train` loop.
``before_after.png``: the four views rendered before training, after it, and the images.

``mode=render`` renders the box given by ``render_center`` / ``render_size`` (default: the
true box) without training: ``turntable.gif``, ``depth.png`` (the first frame's depth,
normalised by its maximum, viridis, as the course shows it) and the PSNR of its renders from
the four data cameras against the course's images (``render_psnr``).

Relative ``data.root`` paths are resolved against the repository root (the folder holding
``main.py``), not the Hydra run directory nor the shell's working directory, so the default
``../shared/data/box`` works from anywhere.
"""

from __future__ import annotations

from typing import Dict

import torch

from l3d_app.errors import UserError
from l3d_app.geometry.rays import camera_rays
from l3d_app.metrics.image import psnr
from l3d_app.models.sdf_box import SDFBox
from l3d_app.registry import DATASETS, SAMPLERS, TASKS
from l3d_app.render.evaluation import render_views
from l3d_app.render.turntable import data_up, orbit_cameras, write_turntable
from l3d_app.render.volume.diagnostics import depth_colormap
from l3d_app.render.volume.renderer import render_rays_chunked
from l3d_app.runtime.config_values import config_floats
from l3d_app.runtime.media import save_png
from l3d_app.runtime.optim import build_optimizer
from l3d_app.runtime.paths import resolve_path
from l3d_app.runtime.random import randint
from l3d_app.runtime.training import Trainable, train
from l3d_app.tasks.common import loop_spec, require_positive


@TASKS.register("box")
def box(cfg, ctx) -> dict:
    """Fit the box; write metrics (box_center, box_size, errors, psnr) and a turntable gif."""
    require_positive(cfg, "iters", "batch_rays", "lr", "n_samples", "beta", "eval_stride", "chunk")
    mode = str(cfg.mode)
    if mode not in ("fit", "render"):
        raise UserError(f"box mode must be fit or render, got '{cfg.mode}'")
    center, size = ("render_center", "render_size") if mode == "render" else ("init_center", "init_size")
    vectors = {key: config_floats(cfg[key], key, 3) for key in (center, size, "true_center", "true_size")}
    if min(vectors[size]) <= 0:
        raise UserError(f"{size} must be three positive side lengths, got {list(cfg[size])}")
    data = DATASETS.build({**cfg.data, "root": str(resolve_path(cfg.data.root))}, device=ctx.device)
    origins, dirs = camera_rays(data.cameras, normalize=True)            # (4, H, W, 3)
    target = data.images
    flat_o, flat_d, flat_rgb = origins.reshape(-1, 3), dirs.reshape(-1, 3), target.reshape(-1, 3)
    n_pix = flat_o.shape[0]
    if mode == "render":
        return _render_only(cfg, ctx, data, origins, dirs)

    model = SDFBox(cfg.init_center, cfg.init_size, alpha=float(cfg.alpha), beta=float(cfg.beta)).to(ctx.device)
    iters = int(cfg.iters)
    opt, scheds = build_optimizer(cfg.optim, model.parameters(), iters)
    trainable = Trainable({"box": model}, opt, schedulers=scheds)
    sampler = SAMPLERS.build(cfg.sampler)
    gt_c = torch.tensor(list(cfg.true_center), dtype=torch.float32, device=ctx.device)
    gt_s = torch.tensor(list(cfg.true_size), dtype=torch.float32, device=ctx.device)
    stride = int(cfg.eval_stride)
    chunk = int(cfg.chunk)

    def step_fn(step: int) -> Dict[str, torch.Tensor]:
        idx = randint(0, n_pix, (int(cfg.batch_rays),), ctx.generator, ctx.device)
        pred = model.render_rays(flat_o[idx], flat_d[idx], sampler)["color"]
        return {"loss": ((pred - flat_rgb[idx]) ** 2).mean()}

    def render_views(s: int) -> torch.Tensor:
        o, d = origins[:, ::s, ::s], dirs[:, ::s, ::s]
        return render_rays_chunked(lambda a, b: model.render_rays(a, b, sampler), o, d, chunk)["color"]

    def eval_fn(step: int) -> Dict[str, float]:
        return {"center_error": float((model.center - gt_c).abs().max()),
                "size_error": float((model.size - gt_s).abs().max()),
                "psnr": float(psnr(render_views(stride), target[:, ::stride, ::stride]))}

    with torch.no_grad():
        before = render_views(1)
    with ctx.stopwatch.stage("train"):
        result = train(ctx, trainable, step_fn, loop_spec(cfg, "box"), eval_fn=eval_fn)
    with torch.no_grad():
        final = render_views(1)
        final_psnr = float(psnr(final, target))
    save_png(ctx.path("fit_views.png"), torch.cat([torch.cat(list(final), 1), torch.cat(list(target), 1)], 0))
    save_png(ctx.path("before_after.png"), torch.cat([torch.cat(list(v.clamp(0, 1)), 1) for v in (before, final, target)], 0))
    if int(cfg.gif_frames) > 0:
        _turntable(cfg, ctx, model, data)
    center, size = model.center.detach().cpu(), model.size.detach().cpu()
    return {
        "box_center": [round(float(v), 6) for v in center],
        "box_size": [round(float(v), 6) for v in size],
        "center_error": float((center - gt_c.cpu()).abs().max()),
        "size_error": float((size - gt_s.cpu()).abs().max()),
        "psnr": round(final_psnr, 4),
        "iters": result.step,
        "train_seconds": round(result.train_seconds, 4),     # the steps (evaluations excluded), resumed parts included
        "rays_per_second": round(result.steps_run * int(cfg.batch_rays) / max(result.train_seconds, 1e-9), 1),
        "n_params": sum(p.numel() for p in model.parameters()),
    }


@torch.no_grad()
def _turntable(cfg, ctx, model: SDFBox, data) -> None:
    """A small volume-rendered turntable of the fitted box (NDC focal 1 = 90 degree fov), about
    the data's up axis."""
    cams = orbit_cameras(int(cfg.gif_frames), float(cfg.gif_distance), float(cfg.gif_elevation), 90.0,
                         int(cfg.turntable_size), up=data_up(data), device=ctx.device)
    sampler = SAMPLERS.build(cfg.sampler)
    render = lambda a, b: {"color": model.render_rays(a, b, sampler)["color"]}  # noqa: E731
    write_turntable(ctx.path("turntable.gif"), lambda c: render_views(render, c, int(cfg.chunk))["color"], cams,
                    cfg.fps)


@torch.no_grad()
def _render_only(cfg, ctx, data, origins: torch.Tensor, dirs: torch.Tensor) -> dict:
    """``mode=render``: the given box without training (turntable, depth picture, PSNR of its
    renders from the data cameras against the data images)."""
    model = SDFBox(cfg.render_center, cfg.render_size, alpha=float(cfg.alpha), beta=float(cfg.beta)).to(ctx.device)
    sampler = SAMPLERS.build(cfg.sampler)
    views = render_rays_chunked(lambda a, b: model.render_rays(a, b, sampler), origins, dirs, int(cfg.chunk))
    save_png(ctx.path("views.png"), torch.cat([torch.cat(list(views["color"].clamp(0, 1)), 1),
                                               torch.cat(list(data.images), 1)], 0))
    cams = orbit_cameras(max(1, int(cfg.gif_frames)), float(cfg.gif_distance), float(cfg.gif_elevation), 90.0,
                         int(cfg.turntable_size), up=data_up(data), device=ctx.device)
    out = render_views(lambda a, b: model.render_rays(a, b, sampler), cams, int(cfg.chunk))
    depth = depth_colormap(out["depth"][0], out["opacity"][0] > 0.5)
    save_png(ctx.path("depth.png"), depth)
    if int(cfg.gif_frames) > 0:
        write_turntable(ctx.path("turntable.gif"), lambda c: out["color"], cams, cfg.fps)
    return {"mode": "render", "render_psnr": round(float(psnr(views["color"], data.images)), 4),
            "max_depth": round(float(out["depth"][0][out["opacity"][0] > 0.5].max()), 4),
            "num_frames": int(cams.batch_size) if hasattr(cams, "batch_size") else len(out["color"])}
