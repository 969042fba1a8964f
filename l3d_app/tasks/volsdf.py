"""volsdf: a neural SDF + colour network trained from posed images by SDF volume rendering.

``python main.py task=volsdf beta=0.1`` (VolSDF, ``alpha``/``beta`` at the top level) or
``density=neus s=64`` (NeuS). Pieces:

* model (``model=sdf_grid_field``, default): :class:`~l3d_app.models.sdf_grid.SDFGridField`,
  a multi-resolution grid (table near zero) + small MLP initialised to a sphere of
  ``model.radius`` and pretrained to it (MLP only) for ``pretrain_steps``; its exact spatial
  gradient (no double backward) feeds the colour network (normal) and the eikonal loss. Grid
  levels are switched on coarse to fine: ``levels_start`` levels, one more every
  ``level_every`` steps. ``model=sdf_field`` is the slower harmonic-MLP alternative.
* density: VolSDF ``sigma = alpha * Psi_beta(-f)`` (:class:`~l3d_app.render.densities.LaplaceDensity`).
  ``beta`` is the initial value: ``beta_mode=anneal`` (default) takes it geometrically to
  ``beta_end`` over ``anneal_fraction`` of the steps, ``beta_mode=learnable`` trains it with
  the field (floor ``beta_min``), ``beta_mode=fixed`` keeps it. ``alpha=null`` ties
  ``alpha = 1/beta`` (VolSDF), a number fixes it. NeuS: ``density=neus`` with fixed ``s``.
  Why ``beta_end`` is small: a ray that passes a convex surface at distance ``h`` (curvature
  radius ``R``) accumulates optical depth ``exp(-h/beta) sqrt(pi R / (2 beta))`` (alpha = 1/beta),
  so silhouettes appear ``beta ln(sqrt(pi R / (2 beta)) / ln 2)`` OUTSIDE the zero level set and
  the learned surface shrinks by that much to match the images (0.023 on the 0.28 sphere at
  beta 0.01, measured 0.023-0.026).
* sampling only near the surface: a trilinear :class:`~l3d_app.render.sdf_volume.SDFGridCache`
  of the SDF (``cache_resolution``^3, refreshed every ``cache_every`` steps, no grad) gives
  ``n_coarse`` look-ups per ray whose VolSDF weights place ``n_fine`` field samples at the
  zero level set (:func:`~l3d_app.render.sdf_volume.render_sdf_rays`); metrics report both
  counts (``samples_per_ray``, ``fine_samples_per_ray``).
* loss: colour MSE + ``w_eikonal`` x eikonal loss at the fine samples and at
  ``eikonal_points`` random box points, through the shared
  :func:`~l3d_app.runtime.training.train` loop (evaluation, checkpoints, ``resume=true``);
  Adam (eps 1e-15) with ``warmup_steps`` linear warm-up then cosine decay to
  ``lr * lr_final_ratio``; ``time_budget`` > 0 stops training after that many seconds.
  ``pixel_jitter=true`` sends each training ray through a random point of its pixel.
* evaluation renders average ``supersample``^2 rays per pixel (the images are SSAA renders).

Evaluation: test PSNR / SSIM; a marching-cubes mesh of the SDF's zero level set, scored
against the ground-truth surface when the data has one (the built-in scene) by
:func:`~l3d_app.metrics.surface_scores.surface_scores`: ``chamfer`` = mean accuracy + mean
completeness, EXACT point-to-mesh distances of ``eval_points`` samples of each surface
(world units, not squared), ``chamfer_rel_diag`` the same over the true mesh's
bounding-box diagonal, ``f1`` / ``precision`` / ``recall`` at ``f1_threshold`` (0.05); the
``*_observed`` variants score only the true surface the TRAINING cameras see (and the
predicted surface nearest to it), ``observed_fraction`` its share of the true area.
Outputs: ``render.gif`` (360 colour), ``geometry.gif`` (360 sphere-traced shading of the SDF),
``mesh.<ply|obj>``, ``test_views.png``, ``metrics.json``.
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
from l3d_app.geometry.mesh_io import save_mesh
from l3d_app.geometry.rays import camera_rays, pixel_axes, supersampled_rays
from l3d_app.losses.eikonal import eikonal_loss, sdf_gradient
from l3d_app.metrics.image import psnr, ssim
from l3d_app.metrics.surface_scores import surface_scores
from l3d_app.models.sdf_grid import pretrain_field
from l3d_app.registry import DATASETS, MODELS, TASKS
from l3d_app.registry import DENSITIES, SAMPLERS
from l3d_app.render.sdf_volume import render_sdf_rays
from l3d_app.render.sphere_tracing import render_sdf_shaded
from l3d_app.render.volume import render_rays_chunked
from l3d_app.runtime.optim import build_optimizer
from l3d_app.runtime.media import save_gif, save_png
from l3d_app.runtime.training import Trainable, train
from l3d_app.tasks.common import require_positive


@TASKS.register("volsdf")
def volsdf(cfg, ctx) -> dict:
    """Train, evaluate (images and surface), write gifs / mesh / metrics."""
    require_positive(cfg, "iters", "batch_rays", "chunk", "supersample")
    data = DATASETS.build(cfg.data).to(ctx.device)
    box = data.scene_box.tolist()
    model = MODELS.build(cfg.model, scene_box=box).to(ctx.device)
    dens = DENSITIES.build(cfg.density).to(ctx.device)
    n_params = sum(p.numel() for p in model.parameters())
    resuming = bool(cfg.resume) and (ctx.out_dir / "checkpoint.pt").exists()
    if int(cfg.pretrain_steps) > 0 and not resuming:
        err = pretrain_field(model, float(cfg.model.radius if "radius" in cfg.model else cfg.model.sdf_net.radius),
                             box, int(cfg.pretrain_steps), generator=ctx.generator)
        ctx.logger.text("pretrain", f"sphere pretraining: mean |f - sdf_sphere| = {err:.4g}")
    levels = _LevelSchedule(model, int(cfg.levels_start), int(cfg.level_every))
    sampler = SAMPLERS.build(cfg.sampler, scene_box=box).to(ctx.device)

    origins, dirs = camera_rays(data.cameras, normalize=False)                # (N, H, W, 3), camera Z = 1
    tr = data.train.to(ctx.device)
    flat_o, flat_d = origins[tr].reshape(-1, 3), dirs[tr].reshape(-1, 3)
    du, dv = pixel_axes(data.cameras[tr])                                     # (n_train, 3) per pixel step
    flat_cam = torch.arange(len(tr), device=ctx.device).repeat_interleave(data.cameras.height * data.cameras.width)
    jitter = bool(cfg.pixel_jitter)
    supersample = int(cfg.supersample)
    flat_rgb = data.images[tr].reshape(-1, 3)
    n_rays, batch = flat_o.shape[0], int(cfg.batch_rays)
    lo = torch.tensor(box[0], device=ctx.device)
    hi = torch.tensor(box[1], device=ctx.device)

    groups = [{"params": list(model.parameters())}, {"params": list(dens.parameters()), "lr": float(cfg.lr_beta)}]
    opt, scheds = build_optimizer(cfg.optim, groups, int(cfg.iters))
    trainable = Trainable({"field": model, "density": dens}, opt, extra={"sampler": sampler}, schedulers=scheds)
    fixed = dict(estimator=sampler, density=dens, field=model, background=data.background)
    field_fn = _field_with_gradient(model)
    stats = {"samples_per_ray": 0.0, "fine_samples_per_ray": 0.0, "train_seconds": 0.0, "cpu_seconds": 0.0,
             "steps": 0}
    budget = float(cfg.get("time_budget", 0) or 0)

    def step_fn(step: int) -> Dict[str, torch.Tensor]:
        stats["_t0"], stats["_c0"] = time.perf_counter(), time.process_time()
        levels.apply(step)
        dens.schedule(step, int(cfg.iters))
        sampler.update(step, model, ctx.generator)
        idx = torch.randint(0, n_rays, (batch,), generator=ctx.generator,
                            device=ctx.generator.device).to(ctx.device)
        d = flat_d[idx]
        if jitter:     # a uniformly random point of the pixel: the images are box-filtered (SSAA)
            j = torch.rand(batch, 2, generator=ctx.generator, device=ctx.generator.device).to(ctx.device) - 0.5
            d = d + j[:, :1] * du[flat_cam[idx]] + j[:, 1:] * dv[flat_cam[idx]]
        d = torch.nn.functional.normalize(d, dim=-1)
        out = render_sdf_rays(field_fn, flat_o[idx], d, perturb=True, generator=ctx.generator, **fixed)
        color_loss = ((out["color"] - flat_rgb[idx]) ** 2).mean()
        logs = {"color_loss": color_loss.detach(), "samples_per_ray": out["samples_per_ray"].detach(),
                **{k: torch.tensor(v) for k, v in dens.stats().items()}, "active_levels": torch.tensor(float(levels.active))}
        loss = color_loss
        if float(cfg.w_eikonal) > 0:
            u = torch.rand(int(cfg.eikonal_points), 3, generator=ctx.generator,
                           device=ctx.generator.device).to(ctx.device)
            grads = [_gradient_at(model, lo + u * (hi - lo))]
            if "grad" in out:
                grads.append(out["grad"].reshape(-1, 3))
            eik = eikonal_loss(torch.cat(grads))
            loss = loss + float(cfg.w_eikonal) * eik
            logs["eikonal"] = eik.detach()
        stats["samples_per_ray"] = float(out["samples_per_ray"])
        stats["fine_samples_per_ray"] = float(out["fine_samples_per_ray"])
        logs["loss"] = loss
        return logs

    def after_step(step: int) -> None:
        stats["train_seconds"] += time.perf_counter() - stats.pop("_t0", time.perf_counter())
        stats["cpu_seconds"] += time.process_time() - stats.pop("_c0", time.process_time())
        stats["steps"] += 1
        if budget > 0 and stats["train_seconds"] >= budget:
            os.kill(os.getpid(), signal.SIGINT)     # the shared loop stops cleanly on SIGINT

    def render_fn(o: torch.Tensor, d: torch.Tensor) -> Dict[str, torch.Tensor]:
        out = render_sdf_rays(field_fn, o, d, **fixed)
        return {k: out[k] for k in ("color", "depth", "opacity")}

    n_eval = int(cfg.eval_views) if int(cfg.eval_views) > 0 else len(data.test)
    eval_idx = data.test[:n_eval].to(ctx.device)

    def render_views(views: torch.Tensor) -> torch.Tensor:
        """(V, H, W, 3) colours of the views, each pixel the mean of supersample^2 sub-pixel rays."""
        o, d = supersampled_rays(data.cameras[views], supersample)             # (V, H, W, s*s, 3)
        col = render_rays_chunked(render_fn, o, d, int(cfg.chunk))["color"]
        return col.mean(dim=-2)

    def eval_fn(step: int) -> Dict[str, float]:
        with torch.no_grad():
            pred = render_views(eval_idx)
        target = data.images[eval_idx]
        return {"psnr": float(psnr(pred.clamp(0, 1), target)), "ssim": float(ssim(pred.clamp(0, 1), target)),
                **dens.stats(), "samples_per_ray": stats["samples_per_ray"],
                "train_seconds": stats["train_seconds"], "cpu_seconds": stats["cpu_seconds"]}

    with ctx.stopwatch.stage("train"):
        result = train(ctx, trainable, step_fn, int(cfg.iters), eval_fn=eval_fn, eval_every=int(cfg.eval_every),
                       checkpoint_every=int(cfg.checkpoint_every), resume=bool(cfg.resume), desc="volsdf",
                       after_step=after_step)
    model.eval()
    with torch.no_grad():
        sampler.update(result.step, model, ctx.generator, force=True)
        te = data.test.to(ctx.device)
        pred = render_views(te).clamp(0, 1)
        target = data.images[te]
        metrics = {"psnr": round(float(psnr(pred, target)), 4), "ssim": round(float(ssim(pred, target)), 4)}
        save_png(ctx.path("test_views.png"), torch.cat([torch.cat(list(pred[:8]), 1), torch.cat(list(target[:8]), 1)], 0))
    with ctx.stopwatch.stage("mesh"):
        metrics.update(_surface_metrics(cfg, ctx, model, box, data))
    if int(cfg.gif_frames) > 0:
        with ctx.stopwatch.stage("gifs"):
            _turntables(cfg, ctx, model, render_fn, data, box)
    metrics.update({
        "density": str(cfg.density.name), **{f"{k}_final": round(v, 6) for k, v in dens.stats().items()},
        "iters": result.step, "n_params": n_params,
        "train_seconds": round(ctx.stopwatch.stages["train"], 4),
        "mesh_seconds": round(ctx.stopwatch.stages["mesh"], 4),
        "gif_seconds": round(ctx.stopwatch.stages.get("gifs", 0.0), 4),
        "samples_per_ray": round(stats["samples_per_ray"], 3),
        "fine_samples_per_ray": round(stats["fine_samples_per_ray"], 3),
        "rays_per_second": round(stats["steps"] * batch / max(stats["train_seconds"], 1e-9), 1),
        "seconds_per_step": round(stats["train_seconds"] / max(stats["steps"], 1), 4),
        # CPU time of the training steps (all threads): the per-step cost on a shared machine
        "cpu_seconds_per_step": round(stats["cpu_seconds"] / max(stats["steps"], 1), 4),
        "history": result.history_rows(),
    })
    return metrics


class _LevelSchedule:
    """Coarse-to-fine grid levels: ``start`` levels at step 0, one more every ``every`` steps
    (``start <= 0`` or ``every <= 0``: all levels from the start). No-op for models without levels."""

    def __init__(self, model, start: int, every: int):
        self.model = model if hasattr(model, "set_active_levels") else None
        self.start, self.every = int(start), int(every)
        self.active = 0

    def apply(self, step: int) -> None:
        if self.model is None:
            return
        n_levels = self.model.encoding.n_levels
        n = n_levels if self.start <= 0 or self.every <= 0 else self.start + step // self.every
        self.model.set_active_levels(min(n, n_levels))
        self.active = self.model.active_levels


def _field_with_gradient(model):
    """``fn(points, dirs) -> (sdf, rgb, grad f)``: the model's own exact gradient when it has one
    (:class:`~l3d_app.models.sdf_grid.SDFGridField`), else autograd (graph kept while training)."""
    if hasattr(model, "sdf_rgb_grad"):
        return model.sdf_rgb_grad

    def fn(points: torch.Tensor, dirs: torch.Tensor):
        if not torch.is_grad_enabled():
            return model(points, dirs)
        p = points.detach().requires_grad_(True)
        f, rgb = model(p, dirs)
        (g,) = torch.autograd.grad(f.sum(), p, create_graph=True)
        return f, rgb, g

    return fn


def _gradient_at(model, points: torch.Tensor) -> torch.Tensor:
    """(N, 3) differentiable SDF gradient at points (N, 3)."""
    if hasattr(model, "sdf_features_gradient"):
        return model.sdf_features_gradient(points)[2]
    return sdf_gradient(model.sdf, points, create_graph=True)


def _ground_truth(cfg):
    """The true mesh of the data's scene (the built-in scene), or None when the data has no
    known surface."""
    if str(cfg.data.name) != "nerf_builtin":
        return None
    from l3d_app.data.nerf_views import nerf_scene

    return nerf_scene()


@torch.no_grad()
def _surface_metrics(cfg, ctx, model, box, data) -> Dict[str, float]:
    """Marching cubes of the SDF -> mesh file; chamfer / F1 against the ground truth if known."""
    fmt = str(cfg.mesh_format).lower().lstrip(".")
    if fmt not in ("ply", "obj"):
        raise UserError(f"mesh_format must be ply or obj, got {cfg.mesh_format!r}")
    try:
        mesh = sdf_to_mesh(model.sdf, resolution=int(cfg.mesh_resolution), bounds=(box[0], box[1]),
                           device=ctx.device)
    except UserError as err:      # empty level set: say so, keep the other results
        print(f"l3d_app: warning: no mesh written: {err}", flush=True)
        ctx.logger.text("mesh", f"no mesh written: {err}")
        return {"mesh_faces": 0}
    save_mesh(mesh, ctx.path(f"mesh.{fmt}"))
    out: Dict[str, float] = {"mesh_faces": int(mesh.num_faces)}
    truth = _ground_truth(cfg)
    if truth is not None:
        scores = surface_scores(mesh, truth, cameras=data.cameras[data.train.to(data.cameras.device)],
                                n=int(cfg.eval_points), threshold=float(cfg.f1_threshold), seed=2)
        out.update({k: round(v, 6) for k, v in scores.items()})
    return out


@torch.no_grad()
def _turntables(cfg, ctx, model, render_fn, data, box) -> None:
    """render.gif (colour) and geometry.gif (sphere-traced SDF shading), 360 degrees."""
    dist = float(data.cameras.centers().norm(dim=-1).mean())
    size = int(cfg.gif_size) if int(cfg.gif_size) > 0 else data.cameras.width
    cams = turntable(int(cfg.gif_frames), dist, float(cfg.gif_elevation), float(data.cameras.fov()[0]), size,
                     device=ctx.device)
    o, d = camera_rays(cams, normalize=True)
    color = render_rays_chunked(render_fn, o, d, int(cfg.chunk))["color"].clamp(0, 1)
    geo = render_rays_chunked(lambda a, b: {"rgb": render_sdf_shaded(model.sdf, a, b, box)}, o, d,
                              int(cfg.chunk))["rgb"]
    for name, frames in (("render.gif", color), ("geometry.gif", geo)):
        if not bool(torch.isfinite(frames).all()):
            raise UserError(f"{name}: the render produced non-finite values")
        save_gif(ctx.path(name), frames, fps=float(cfg.fps))
