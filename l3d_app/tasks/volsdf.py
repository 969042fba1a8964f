"""volsdf: a neural SDF + colour network trained from posed images by SDF volume rendering.

``python main.py task=volsdf beta=0.1`` (VolSDF, ``alpha``/``beta`` at the top level) or
``density=neus s=64`` (NeuS). Pieces:

* model :class:`~l3d_app.models.sdf_net.SDFField` (SDF MLP without output activation,
  geometric init, then :func:`~l3d_app.models.sdf_net.pretrain_sphere` for ``pretrain_steps``);
* rays bounded by the data's scene box; a coarse SDF-only pass places ``n_fine`` samples near the
  zero level set (:func:`~l3d_app.render.sdf_volume.render_sdf_rays`); ``samples_per_ray``
  counts both passes;
* loss: colour MSE + ``w_eikonal`` x eikonal loss at random points in the box and at the fine
  samples of the batch, through the shared :func:`~l3d_app.runtime.training.train` loop
  (evaluation, checkpoints, ``resume=true``).

Evaluation: test PSNR / SSIM; a marching-cubes mesh of the SDF's zero level set, scored
against the ground-truth surface when the data has one (the built-in scene): ``chamfer`` is
the symmetric mean of NON-squared nearest distances (world units, ``mean_x d(x, Y) +
mean_y d(y, X)`` on ``eval_points`` samples of each surface), ``chamfer_diag`` the same divided by
the ground truth's bounding-box diagonal, ``f1`` the F-score at ``f1_threshold`` (0.05).
Outputs: ``render.gif`` (360 colour), ``geometry.gif`` (360 sphere-traced shading of the SDF),
``mesh.<ply|obj>``, ``test_views.png``, ``metrics.json``.
"""

from __future__ import annotations

import time
from typing import Dict

import torch

from l3d_app.errors import UserError
from l3d_app.geometry.camera_paths import turntable
from l3d_app.geometry.marching_cubes import sdf_to_mesh
from l3d_app.geometry.mesh_io import save_mesh
from l3d_app.geometry.rays import camera_rays
from l3d_app.geometry.sampling import sample_surface
from l3d_app.losses.eikonal import eikonal_loss
from l3d_app.metrics.chamfer import chamfer_distance
from l3d_app.metrics.fscore import fscore
from l3d_app.metrics.image import psnr, ssim
from l3d_app.models.sdf_net import pretrain_sphere
from l3d_app.registry import DATASETS, MODELS, TASKS
from l3d_app.render.sdf_volume import DENSITIES, render_sdf_rays
from l3d_app.render.sphere_tracing import render_sdf_shaded
from l3d_app.render.volume import render_rays_chunked
from l3d_app.runtime.media import save_gif, save_png
from l3d_app.runtime.training import Trainable, train
from l3d_app.tasks.common import require_positive


@TASKS.register("volsdf")
def volsdf(cfg, ctx) -> dict:
    """Train, evaluate (images and surface), write gifs / mesh / metrics."""
    require_positive(cfg, "iters", "batch_rays", "lr", "n_coarse", "n_fine", "chunk", "beta", "alpha", "s")
    density = str(cfg.density)
    if density not in DENSITIES:
        raise UserError(f"density must be one of {', '.join(DENSITIES)}, got {density!r}")
    data = DATASETS.build(cfg.data).to(ctx.device)
    box = data.scene_box.tolist()
    model = MODELS.build(cfg.model, scene_box=box).to(ctx.device)
    n_params = sum(p.numel() for p in model.parameters())
    if int(cfg.pretrain_steps) > 0 and not (bool(cfg.resume) and (ctx.out_dir / "checkpoint.pt").exists()):
        err = pretrain_sphere(model.sdf_net, float(cfg.model.sdf_net.radius), box, steps=int(cfg.pretrain_steps),
                              generator=ctx.generator)
        ctx.logger.text("pretrain", f"sphere pretraining: mean |f - sdf_sphere| = {err:.4g}")

    origins, dirs = camera_rays(data.cameras, normalize=True)                 # (N, H, W, 3)
    tr = data.train.to(ctx.device)
    flat_o, flat_d = origins[tr].reshape(-1, 3), dirs[tr].reshape(-1, 3)
    flat_rgb = data.images[tr].reshape(-1, 3)
    n_rays, batch = flat_o.shape[0], int(cfg.batch_rays)
    lo = torch.tensor(box[0], device=ctx.device)
    hi = torch.tensor(box[1], device=ctx.device)

    opt = torch.optim.Adam(model.parameters(), lr=float(cfg.lr))
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=max(1, int(cfg.iters)),
                                                       eta_min=float(cfg.lr) * float(cfg.lr_final_ratio))
    trainable = Trainable({"field": model}, opt, extra={"scheduler": sched})
    rkw = dict(scene_box=box, density=density, alpha=float(cfg.alpha), beta=float(cfg.beta), s=float(cfg.s),
               n_coarse=int(cfg.n_coarse), n_fine=int(cfg.n_fine), background=data.background)
    stats = {"samples_per_ray": 0.0, "fine_samples_per_ray": 0.0, "train_seconds": 0.0, "steps": 0}

    def step_fn(step: int) -> Dict[str, torch.Tensor]:
        stats["_t0"] = time.perf_counter()
        idx = torch.randint(0, n_rays, (batch,), generator=ctx.generator,
                            device=ctx.generator.device).to(ctx.device)
        out = render_sdf_rays(model.sdf, model, flat_o[idx], flat_d[idx], perturb=True, generator=ctx.generator,
                              **rkw)
        color_loss = ((out["color"] - flat_rgb[idx]) ** 2).mean()
        logs = {"color_loss": color_loss.detach(), "samples_per_ray": out["samples_per_ray"].detach()}
        loss = color_loss
        if float(cfg.w_eikonal) > 0:
            n_eik = int(cfg.eikonal_points)
            u = torch.rand(n_eik, 3, generator=ctx.generator, device=ctx.generator.device).to(ctx.device)
            near = (flat_o[idx, None, :] + out["t"][..., None] * flat_d[idx, None, :]).reshape(-1, 3)
            pick = torch.randint(0, near.shape[0], (n_eik,), generator=ctx.generator,
                                 device=ctx.generator.device).to(ctx.device)
            pts = torch.cat([lo + u * (hi - lo), near[pick].detach()]).requires_grad_(True)
            f = model.sdf(pts)
            (grad,) = torch.autograd.grad(f.sum(), pts, create_graph=True)
            eik = eikonal_loss(grad)
            loss = loss + float(cfg.w_eikonal) * eik
            logs["eikonal"] = eik.detach()
        stats["samples_per_ray"] = float(out["samples_per_ray"])
        stats["fine_samples_per_ray"] = float(out["fine_samples_per_ray"])
        logs["loss"] = loss
        return logs

    def after_step(step: int) -> None:
        sched.step()
        stats["train_seconds"] += time.perf_counter() - stats.pop("_t0", time.perf_counter())
        stats["steps"] += 1

    def render_fn(o: torch.Tensor, d: torch.Tensor) -> Dict[str, torch.Tensor]:
        out = render_sdf_rays(model.sdf, model, o, d, **rkw)
        return {k: out[k] for k in ("color", "depth", "opacity")}

    n_eval = int(cfg.eval_views) if int(cfg.eval_views) > 0 else len(data.test)
    eval_idx = data.test[:n_eval].to(ctx.device)

    def eval_fn(step: int) -> Dict[str, float]:
        pred = render_rays_chunked(render_fn, origins[eval_idx], dirs[eval_idx], int(cfg.chunk))["color"].clamp(0, 1)
        target = data.images[eval_idx]
        return {"psnr": float(psnr(pred, target)), "ssim": float(ssim(pred, target)),
                "samples_per_ray": stats["samples_per_ray"], "train_seconds": stats["train_seconds"]}

    with ctx.stopwatch.stage("train"):
        result = train(ctx, trainable, step_fn, int(cfg.iters), eval_fn=eval_fn, eval_every=int(cfg.eval_every),
                       checkpoint_every=int(cfg.checkpoint_every), resume=bool(cfg.resume), desc="volsdf",
                       after_step=after_step)
    model.eval()
    with torch.no_grad():
        te = data.test.to(ctx.device)
        pred = render_rays_chunked(render_fn, origins[te], dirs[te], int(cfg.chunk))["color"].clamp(0, 1)
        target = data.images[te]
        metrics = {"psnr": round(float(psnr(pred, target)), 4), "ssim": round(float(ssim(pred, target)), 4)}
        save_png(ctx.path("test_views.png"), torch.cat([torch.cat(list(pred[:8]), 1), torch.cat(list(target[:8]), 1)], 0))
    metrics.update(_surface_metrics(cfg, ctx, model, box))
    if int(cfg.gif_frames) > 0:
        _turntables(cfg, ctx, model, render_fn, data, box)
    metrics.update({
        "density": density, "alpha": float(cfg.alpha), "beta": float(cfg.beta), "s": float(cfg.s),
        "iters": result.step, "n_params": n_params,
        "train_seconds": round(ctx.stopwatch.stages["train"], 4),
        "samples_per_ray": round(stats["samples_per_ray"], 3),
        "fine_samples_per_ray": round(stats["fine_samples_per_ray"], 3),
        "rays_per_second": round(stats["steps"] * batch / max(stats["train_seconds"], 1e-9), 1),
        "history": result.history_rows(),
    })
    return metrics


def _ground_truth_points(cfg, n: int):
    """(n, 3) points on the data's true surface, or None when the data has no known surface."""
    if str(cfg.data.name) != "nerf_builtin":
        return None
    from l3d_app.data.nerf_truth import builtin_surface_points

    return builtin_surface_points(n, torch.Generator().manual_seed(1))


@torch.no_grad()
def _surface_metrics(cfg, ctx, model, box) -> Dict[str, float]:
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
    n = int(cfg.eval_points)
    gt = _ground_truth_points(cfg, n)
    if gt is not None:
        pred = sample_surface(mesh.to("cpu"), n, generator=torch.Generator().manual_seed(2)).points
        cd = float(chamfer_distance(pred, gt, squared=False))
        diag = float((gt.max(0).values - gt.min(0).values).norm())
        f = fscore(pred, gt, float(cfg.f1_threshold))
        out.update({"chamfer": round(cd, 6), "chamfer_diag": round(cd / diag, 6), "f1": round(f["f1"], 4),
                    "precision": round(f["precision"], 4), "recall": round(f["recall"], 4)})
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
