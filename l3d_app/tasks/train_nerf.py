"""train_nerf: fit a radiance field to posed images (built-in scene, NeRF-synthetic, truck).

Two named configurations share this code:

* ``task=train_nerf`` (fast default): :class:`~l3d_app.models.nerf.GridField` (multi-resolution
  grid + small MLP), rays bounded by the scene box, stratified samples with jitter, and an
  :class:`~l3d_app.render.occupancy.OccupancyGrid` that skips samples in empty cells.
* ``task=nerf_baseline`` (the course's settings): :class:`~l3d_app.models.nerf.NeRFMLP`
  6 x 128, skip at layer 3, 6 / 2 harmonic frequencies, 128 stratified samples, 1024 rays
  per batch, Adam lr 5e-4 decayed by 0.8 every 50 epochs, no occupancy grid. An epoch is
  ``len(train rays) / batch_rays`` steps (N_train * H * W / 1024, e.g. 400 steps for 100
  64x64 views), so the decay happens every ``lr_decay_epochs * steps_per_epoch`` steps.

Each step: ``batch_rays`` random pixels of the training views, MSE on colour, Adam. The
shared :func:`~l3d_app.runtime.training.train` loop evaluates PSNR / SSIM on test views
(against step and wall time), checkpoints and resumes (``resume=true``); the occupancy grid
is updated from the field's density in the loop's ``after_step`` hook and checkpointed
with it. ``time_budget`` > 0 stops training after that many seconds of training steps
(evaluation excluded) through the loop's clean SIGINT stop (used by ``bench/bench_nerf.py``).
Outputs: ``turntable.gif`` (colour | depth), ``test_views.png``, ``metrics.json``
(psnr, ssim, seconds, iters, n_params, occupied_fraction, samples_per_ray, rays_per_second)
and with ``extract_mesh=true`` a marching-cubes mesh of ``density = mesh_threshold``.
"""

from __future__ import annotations

import os
import signal
import time
from typing import Dict

import torch

from l3d_app.errors import UserError
from l3d_app.geometry.camera_paths import turntable
from l3d_app.geometry.marching_cubes import sdf_to_mesh
from l3d_app.geometry.mesh import Mesh
from l3d_app.geometry.mesh_io import save_mesh
from l3d_app.geometry.rays import camera_rays
from l3d_app.metrics.image import psnr, ssim
from l3d_app.registry import DATASETS, MODELS, TASKS
from l3d_app.registry import SAMPLERS
from l3d_app.render.radiance import render_field_rays
from l3d_app.runtime.optim import build_optimizer
from l3d_app.render.volume import render_rays_chunked
from l3d_app.runtime.media import save_gif, save_png
from l3d_app.runtime.training import Trainable, train
from l3d_app.tasks.common import require_positive


def _build_data(cfg, device):
    data = DATASETS.build(cfg.data)
    return data.to(device)


@TASKS.register("train_nerf")
def train_nerf(cfg, ctx) -> dict:
    """Train, evaluate on the test views, write the gif / metrics (/ mesh)."""
    require_positive(cfg, "iters", "batch_rays", "lr", "n_samples", "chunk", "eval_every")
    data = _build_data(cfg, ctx.device)
    box = data.scene_box.tolist()
    bg = data.background
    model = MODELS.build(cfg.model, scene_box=box).to(ctx.device)
    n_params = sum(p.numel() for p in model.parameters())

    origins, dirs = camera_rays(data.cameras, normalize=True)                 # (N, H, W, 3)
    tr = data.train.to(ctx.device)
    flat_o, flat_d = origins[tr].reshape(-1, 3), dirs[tr].reshape(-1, 3)
    flat_rgb = data.images[tr].reshape(-1, 3)
    n_rays, batch = flat_o.shape[0], int(cfg.batch_rays)
    steps_per_epoch = max(1, n_rays // batch)

    opt, scheds = build_optimizer(cfg.optim, model.parameters(), int(cfg.iters))
    sampler = SAMPLERS.build(cfg.sampler, scene_box=box).to(ctx.device)
    grid = getattr(sampler, "grid", None)
    trainable = Trainable({"field": model}, opt, extra={"sampler": sampler}, schedulers=scheds)
    render_kw = dict(estimator=sampler, background=bg)
    stats = {"samples_per_ray": 0.0, "train_seconds": 0.0, "steps": 0}
    budget = float(cfg.get("time_budget", 0) or 0)

    def step_fn(step: int) -> Dict[str, torch.Tensor]:
        t0 = time.perf_counter()
        sampler.update(step, model, ctx.generator)
        idx = torch.randint(0, n_rays, (batch,), generator=ctx.generator,
                            device=ctx.generator.device).to(ctx.device)
        out = render_field_rays(model, flat_o[idx], flat_d[idx], perturb=bool(cfg.perturb),
                                generator=ctx.generator, **render_kw)
        loss = ((out["color"] - flat_rgb[idx]) ** 2).mean()
        stats["samples_per_ray"] = float(out["samples_per_ray"])
        stats["_t0"] = t0
        logs = {"loss": loss, "samples_per_ray": out["samples_per_ray"].detach(),
                "lr": torch.tensor(opt.param_groups[0]["lr"])}
        if grid is not None:
            logs["occupied_fraction"] = torch.tensor(grid.occupied_fraction)
        return logs

    def after_step(step: int) -> None:
        stats["train_seconds"] += time.perf_counter() - stats.pop("_t0", time.perf_counter())
        stats["steps"] += 1
        if budget > 0 and stats["train_seconds"] >= budget:
            os.kill(os.getpid(), signal.SIGINT)     # the shared loop stops cleanly on SIGINT

    def render_views(cam_idx: torch.Tensor) -> Dict[str, torch.Tensor]:
        o, d = origins[cam_idx.to(ctx.device)], dirs[cam_idx.to(ctx.device)]
        fn = lambda a, b: {k: v for k, v in render_field_rays(model, a, b, **render_kw).items()  # noqa: E731
                           if k in ("color", "depth", "opacity")}
        return render_rays_chunked(fn, o, d, int(cfg.chunk))

    n_eval = int(cfg.eval_views) if int(cfg.eval_views) > 0 else len(data.test)
    eval_idx = data.test[:n_eval]

    def eval_fn(step: int) -> Dict[str, float]:
        sampler.update(step, model, ctx.generator)
        pred = render_views(eval_idx)["color"].clamp(0, 1)
        target = data.images[eval_idx.to(ctx.device)]
        out = {"psnr": float(psnr(pred, target)), "ssim": float(ssim(pred, target)),
               "samples_per_ray": stats["samples_per_ray"],
               "rays_per_second": stats["steps"] * batch / max(stats["train_seconds"], 1e-9),
               "train_seconds": stats["train_seconds"]}
        if grid is not None:
            out["occupied_fraction"] = grid.occupied_fraction
        return out

    with ctx.stopwatch.stage("train"):
        result = train(ctx, trainable, step_fn, int(cfg.iters), eval_fn=eval_fn, eval_every=int(cfg.eval_every),
                       checkpoint_every=int(cfg.checkpoint_every), resume=bool(cfg.resume), desc="train_nerf",
                       after_step=after_step)
    with torch.no_grad():
        sampler.update(result.step, model, ctx.generator)
        final = render_views(data.test)
        target = data.images[data.test.to(ctx.device)]
        pred = final["color"].clamp(0, 1)
        metrics = {"psnr": round(float(psnr(pred, target)), 4), "ssim": round(float(ssim(pred, target)), 4)}
        save_png(ctx.path("test_views.png"), torch.cat([torch.cat(list(pred[:8]), 1), torch.cat(list(target[:8]), 1)], 0))
        if int(cfg.gif_frames) > 0:
            _turntable(cfg, ctx, render_kw, model, grid, data)
        if bool(cfg.extract_mesh):
            metrics["mesh_faces"] = _extract_mesh(cfg, ctx, model, box)
    train_s = ctx.stopwatch.stages["train"]
    metrics.update({
        "iters": result.step,
        "n_params": n_params,
        "train_seconds": round(train_s, 4),
        "occupied_fraction": round(grid.occupied_fraction, 5) if grid is not None else 1.0,
        "samples_per_ray": round(stats["samples_per_ray"], 3),
        "rays_per_second": round(stats["steps"] * batch / max(stats["train_seconds"], 1e-9), 1),
        "steps_per_epoch": steps_per_epoch,
        "history": result.history_rows(),
    })
    return metrics


@torch.no_grad()
def _turntable(cfg, ctx, render_kw, model, grid, data) -> None:
    """360-degree gif: colour | depth (depth normalised over the frames, white = near)."""
    dist = float(data.cameras.centers().norm(dim=-1).mean())
    cams = turntable(int(cfg.gif_frames), dist, float(cfg.gif_elevation), float(data.cameras.fov()[0]),
                     int(cfg.gif_size) if int(cfg.gif_size) > 0 else data.cameras.width, device=ctx.device)
    o, d = camera_rays(cams, normalize=True)
    fn = lambda a, b: {k: v for k, v in render_field_rays(model, a, b, **render_kw).items()  # noqa: E731
                       if k in ("color", "depth", "opacity")}
    out = render_rays_chunked(fn, o, d, int(cfg.chunk))
    depth = out["depth"] / out["opacity"].clamp_min(1e-6)
    hit = out["opacity"] > 0.5
    lo = depth[hit].min() if hit.any() else depth.min()
    hi = depth[hit].max() if hit.any() else depth.max()
    gray = torch.where(hit, 1.0 - 0.8 * (depth - lo) / (hi - lo).clamp_min(1e-6), torch.zeros_like(depth))
    frames = torch.cat([out["color"].clamp(0, 1), gray[..., None].expand(*gray.shape, 3)], dim=2)
    if not bool(torch.isfinite(frames).all()):
        raise UserError("turntable render produced non-finite values")
    save_gif(ctx.path("turntable.gif"), frames, fps=float(cfg.fps))


@torch.no_grad()
def _extract_mesh(cfg, ctx, model, box) -> int:
    """Marching cubes of ``density = mesh_threshold`` over the scene box -> mesh.<mesh_format>,
    vertices coloured by the field (looking along -normal)."""
    fmt = str(cfg.mesh_format).lower().lstrip(".")
    if fmt not in ("ply", "obj"):
        raise UserError(f"mesh_format must be ply or obj, got {cfg.mesh_format!r}")
    thr = float(cfg.mesh_threshold)
    neg_density = lambda p: -model.density(p.reshape(-1, 3)).reshape(p.shape[:-1])  # noqa: E731
    try:
        mesh = sdf_to_mesh(neg_density, resolution=int(cfg.mesh_resolution), bounds=(box[0], box[1]), level=-thr,
                           colors=None, device=ctx.device)
    except UserError as err:   # empty level set: say so, keep the run's other results
        print(f"l3d_app: warning: no mesh written: {err}", flush=True)
        ctx.logger.text("mesh", f"no mesh written: {err}")
        return 0
    normals = mesh.vertex_normals()
    _, rgb = model(mesh.verts, -normals)
    save_mesh(Mesh(verts=mesh.verts, faces=mesh.faces, vert_colors=rgb.clamp(0, 1)), ctx.path(f"mesh.{fmt}"))
    return mesh.num_faces
