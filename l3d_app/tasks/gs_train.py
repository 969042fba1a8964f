"""gs_train: 3D Gaussian splatting from posed images (built-in scene, truck, NeRF-synthetic).

Initial splats: the truck's ``points/points_10000.npy`` when present, else ``n_init``
points sampled uniformly in the data's scene box; their colours (``init_colors=views``)
are the median of the training pixels they project to (the role of SfM point colours).
Each step renders one random training view with
:func:`~l3d_app.render.gaussians.rasterize_gaussians` on the data's background and
minimises ``L1 + ssim_lambda * (1 - SSIM)`` with Adam (per-parameter learning rates as in
3DGS, the means' rate times the scene extent and decayed exponentially). The SH degree
rises by one every ``sh_every`` steps up to ``sh_degree``.
:class:`~l3d_app.models.gaussians.DensityControl` runs in the shared loop's ``after_step``
hook; its accumulators are checkpointed, so ``resume=true`` continues bitwise like an
uninterrupted run (CPU). ``time_budget`` > 0 stops after that many seconds of training
steps (clean SIGINT stop of the shared loop), as in train_nerf.
Outputs: ``test_views.gif`` (prediction | ground truth per test view), ``progress.gif``
(a test view over training, prediction over ground truth), ``point_cloud.ply`` (3DGS
layout), ``metrics.json`` (psnr, ssim, n_gaussians, seconds, iters, history).
"""

from __future__ import annotations

import os
import signal
import time
from typing import Dict

import numpy as np
import torch

from l3d_app.geometry.gaussian_ply import save_gaussian_ply
from l3d_app.metrics.image import psnr, ssim
from l3d_app.models.gaussians import DensityControl, colors_from_views, init_from_points
from l3d_app.registry import DATASETS, TASKS
from l3d_app.render.gaussians import rasterize_gaussians
from l3d_app.runtime.media import save_gif
from l3d_app.runtime.paths import resolve_path
from l3d_app.runtime.training import Trainable, train
from l3d_app.tasks.common import require_positive


def _initial_points(cfg, data, generator):
    root = cfg.data.get("root", None)
    if root is not None and str(cfg.data.name) == "truck":
        f = resolve_path(str(root)) / "points" / "points_10000.npy"
        if f.is_file():
            return torch.from_numpy(np.load(f).astype(np.float32))
    lo, hi = data.scene_box[0].cpu(), data.scene_box[1].cpu()
    return lo + (hi - lo) * torch.rand(int(cfg.n_init), 3, generator=torch.Generator().manual_seed(int(cfg.seed)))


@TASKS.register("gs_train")
def gs_train(cfg, ctx) -> dict:
    """Train Gaussians, evaluate PSNR/SSIM on the test views, write gifs / ply / metrics."""
    require_positive(cfg, "iters", "eval_every")
    data = DATASETS.build(cfg.data).to(ctx.device)
    points = _initial_points(cfg, data, ctx.generator).to(ctx.device)
    colors = colors_from_views(points, data.images[data.train], data.cameras[data.train]) \
        if str(cfg.init_colors) == "views" else None
    model = init_from_points(points, colors, opacity=float(cfg.init_opacity)).to(ctx.device)
    centres = data.cameras.centers()
    extent = 1.1 * float((centres - centres.mean(0)).norm(dim=-1).max())
    lr = cfg.lr
    groups = [{"params": [model.means], "lr": float(lr.means) * extent, "name": "means"},
              {"params": [model.log_scales], "lr": float(lr.scales), "name": "scales"},
              {"params": [model.quats], "lr": float(lr.quats), "name": "quats"},
              {"params": [model.opacity_logits], "lr": float(lr.opacity), "name": "opacity"},
              {"params": [model.sh_dc], "lr": float(lr.sh_dc), "name": "sh_dc"},
              {"params": [model.sh_rest], "lr": float(lr.sh_dc) / 20.0, "name": "sh_rest"}]
    opt = torch.optim.Adam(groups, eps=1e-15)
    dc = DensityControl(extent, grad_threshold=float(cfg.densify.grad_threshold),
                        percent_dense=float(cfg.densify.percent_dense), min_opacity=float(cfg.densify.min_opacity),
                        max_screen_size=float(cfg.densify.max_screen_size),
                        max_world_scale=float(cfg.densify.max_world_scale), max_gaussians=int(cfg.densify.max_gaussians))
    trainable = Trainable({"gaussians": model}, opt, extra={"density": dc})  # accumulators resume too
    bg = data.background
    tr = data.train.to(ctx.device)
    H, W = data.image_size
    kw = dict(tile_size=int(cfg.tile_size))
    iters, budget = int(cfg.iters), float(cfg.get("time_budget", 0) or 0)
    stats = {"train_seconds": 0.0, "out": None, "steps": 0}
    lam = float(cfg.ssim_lambda)
    decay_steps = max(1, int(cfg.lr_decay_steps))

    def degree(step: int) -> int:
        return min(int(cfg.sh_degree), step // max(1, int(cfg.sh_every)))

    def render(cams, deg):
        return rasterize_gaussians(model.means, model.log_scales, model.quats, model.opacity_logits, model.sh,
                                   deg, cams, bg, **kw)

    def step_fn(step: int) -> Dict[str, torch.Tensor]:
        stats["_t0"] = time.perf_counter()
        frac = min(1.0, step / decay_steps)
        opt.param_groups[0]["lr"] = float(lr.means) * extent * (float(lr.means_final) / float(lr.means)) ** frac
        i = int(tr[int(torch.randint(0, len(tr), (1,), generator=ctx.generator, device=ctx.generator.device))])
        out = render(data.cameras[i], degree(step))
        pred, target = out["color"][0], data.images[i]
        l1 = (pred - target).abs().mean()
        loss = l1 + lam * (1 - ssim(pred, target)) if lam > 0 else l1
        stats["out"] = out
        return {"loss": loss, "l1": l1.detach(), "n_gaussians": torch.tensor(float(model.num)),
                "sh_degree": torch.tensor(float(degree(step)))}

    def after_step(step: int) -> None:
        out = stats.pop("out")
        done = step + 1
        if done <= int(cfg.densify.until) and out["means2d"].grad is not None:
            dc.accumulate(out["means2d"].grad, out["radii"].detach(), W, H)
            if done >= int(cfg.densify.start) and done % int(cfg.densify.every) == 0:
                r = dc.densify_and_prune(model, opt, generator=None,
                                         prune_screen=done > int(cfg.densify.opacity_reset_every))
                ctx.logger.log_scalars({"densify/n_gaussians": r["n"], "densify/cloned": r["cloned"],
                                        "densify/split": r["split"], "densify/pruned": r["pruned"]}, done)
            if int(cfg.densify.opacity_reset_every) > 0 and done % int(cfg.densify.opacity_reset_every) == 0:
                dc.reset_opacity(model, opt)
        stats["train_seconds"] += time.perf_counter() - stats.pop("_t0", time.perf_counter())
        stats["steps"] += 1
        if budget > 0 and stats["train_seconds"] >= budget:
            os.kill(os.getpid(), signal.SIGINT)

    test = data.test.to(ctx.device)
    prog_frames = []

    def render_test(deg) -> torch.Tensor:
        return torch.cat([render(data.cameras[int(i)], deg)["color"] for i in test]).clamp(0, 1)

    def eval_fn(step: int) -> Dict[str, float]:
        pred = render_test(degree(step))
        target = data.images[test]
        prog_frames.append(torch.cat([pred[0], target[0]], 0).cpu())
        return {"psnr": float(psnr(pred, target)), "ssim": float(ssim(pred, target)), "n_gaussians": model.num,
                "train_seconds": stats["train_seconds"]}

    with ctx.stopwatch.stage("train"):
        result = train(ctx, trainable, step_fn, iters, eval_fn=eval_fn, eval_every=int(cfg.eval_every),
                       checkpoint_every=int(cfg.checkpoint_every), resume=bool(cfg.resume), desc="gs_train",
                       after_step=after_step, log_every=int(cfg.log_every))
    with torch.no_grad():
        pred = render_test(degree(result.step))
        target = data.images[test]
        metrics = {"psnr": round(float(psnr(pred, target)), 4), "ssim": round(float(ssim(pred, target)), 4)}
        save_gif(ctx.path("test_views.gif"), torch.cat([pred, target], 2), fps=float(cfg.fps) / 4)
        if prog_frames:
            save_gif(ctx.path("progress.gif"), torch.stack(prog_frames), fps=float(cfg.fps))
    save_gaussian_ply(ctx.path("point_cloud.ply"), model)
    metrics.update({"n_gaussians": model.num, "iters": result.step,
                    "train_seconds": round(stats["train_seconds"], 3),
                    "steps_per_second": round(stats["steps"] / max(stats["train_seconds"], 1e-9), 3),
                    "history": result.history_rows()})
    return metrics
