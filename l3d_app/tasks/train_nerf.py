"""train_nerf: fit a radiance field to posed images (built-in scene, NeRF-synthetic, truck).

``task=train_nerf`` (fast default): ``model=grid_field`` (multi-resolution grid + small MLP),
``sampler=occupancy`` (stratified samples in the scene box, empty cells skipped),
``optim=adam_step``. ``experiment=nerf_baseline`` is the course's setting on the same code
(``model=nerf_mlp``, ``sampler=hierarchical``: coarse and fine networks, 64 + 128 samples, 1024 rays, lr 5e-4);
an estimator that owns a network (the coarse one) gets it from ``attach_fields`` and adds its own loss.

Each step: ``batch_rays`` random pixels of the TRAIN views, colour MSE. Every ``eval_every``
steps the shared loop evaluates the VALIDATION views (``eval_views`` of them; PSNR / SSIM and
a ``pred | truth | error | depth`` picture in TensorBoard); the TEST views are rendered once,
after training (``psnr``, ``ssim`` in metrics.json; ``val_*`` the last validation).
``time_budget`` > 0: wall seconds for the whole task; the task declares what follows training to
the run's :class:`~l3d_app.runtime.budget.TimeBudget` (the test views in validations, the mesh with
``extract_mesh=true``, ``reserve`` seconds), which prices it; ``before_after.png`` is drawn when the picture
before training, priced on a spread part of its rays, fits the budget; the gif comes last with the frames that
still fit (:func:`~l3d_app.render.previews.write_turntables`). Outputs: ``turntable.gif`` (colour |
depth, orbiting the data's up axis), ``test_views.png``, ``metrics.json``; ``extract_mesh=true`` adds
``mesh.<fmt>`` of
``density = mesh_threshold`` coloured by the field (with ``mesh_cull``: only the faces some
training camera sees; the whole level set in ``mesh_uncut.ply``).
"""

from __future__ import annotations

import sys
import time
from typing import Dict

import torch

from l3d_app.geometry.rays import camera_rays
from l3d_app.models.background import background_parameter
from l3d_app.pipelines.views import BeforeAfter, evaluate_views
from l3d_app.registry import DATASETS, MODELS, SAMPLERS, TASKS
from l3d_app.render.evaluation import render_part
from l3d_app.render.field_mesh import extract_mesh, save_field_mesh, seconds_per_grid_point
from l3d_app.render.mesh.visibility import cull_to_training_views
from l3d_app.render.turntable import color_depth_frames
from l3d_app.render.volume.radiance import render_field_rays
from l3d_app.runtime.budget import TimeBudget, views_in_validations
from l3d_app.runtime.config_values import config_words
from l3d_app.runtime.media import save_png
from l3d_app.runtime.optim import build_optimizer
from l3d_app.runtime.random import randint
from l3d_app.runtime.training import Trainable, log_test, train
from l3d_app.tasks.common import loop_spec, require_mesh_formats, require_mesh_resolution, require_positive
from l3d_app.tasks.field_common import write_field_turntables
from l3d_app.pipelines.live_viewer import finish_viewer, radiance_view, start_viewer


@TASKS.register("train_nerf")
def train_nerf(cfg, ctx) -> dict:
    """Train on the train views, validate on val, test once; write the gif / metrics (/ mesh)."""
    require_positive(cfg, "iters", "batch_rays", "chunk", "eval_every")
    if bool(cfg.extract_mesh):
        require_mesh_resolution(cfg)
        require_mesh_formats(cfg)
    data = DATASETS.build(cfg.data).to(ctx.device)
    box = data.scene_box.tolist()
    model = MODELS.build(cfg.model, scene_box=box).to(ctx.device)
    sampler = SAMPLERS.build(cfg.sampler, scene_box=box).to(ctx.device)
    sampler.attach_fields(lambda: MODELS.build(cfg.model, scene_box=box).to(ctx.device))   # hierarchical: coarse
    # What lies outside the scene box: learnt when the data does not know it (real captures).
    background = background_parameter(cfg.learn_background, data)
    params = list(model.parameters()) + list(sampler.parameters()) + ([background["rgb"]] if background["rgb"].requires_grad else [])
    opt, scheds = build_optimizer(cfg.optim, params, int(cfg.iters))
    trainable = Trainable({"field": model, "background": background}, opt, extra={"sampler": sampler},
                          schedulers=scheds)

    origins, dirs = camera_rays(data.cameras, normalize=True)                 # (N, H, W, 3)
    tr = data.train.to(ctx.device)
    flat_o, flat_d, flat_rgb = origins[tr].reshape(-1, 3), dirs[tr].reshape(-1, 3), data.images[tr].reshape(-1, 3)
    n_rays, batch = flat_o.shape[0], int(cfg.batch_rays)
    stats = {"samples_per_ray": 0.0, "train_seconds": 0.0, "steps": 0}
    trainable.extra["step_stats"] = stats      # checkpointed: the rates cover the resumed parts of a run

    def render_fn(o, d, **kw):
        return render_field_rays(model, o, d, sampler, background=background["rgb"].clamp(0, 1),
                                 **kw)

    live = start_viewer(cfg, ctx, data, *radiance_view(model, sampler, background["rgb"], int(cfg.chunk)))

    def step_fn(step: int) -> Dict[str, torch.Tensor]:
        stats["_t0"] = time.perf_counter()
        sampler.update(step, model, ctx.generator)
        idx = randint(0, n_rays, (batch,), ctx.generator, ctx.device)
        out = render_fn(flat_o[idx], flat_d[idx], perturb=bool(cfg.perturb), generator=ctx.generator)
        stats["samples_per_ray"] = float(out["samples_per_ray"])
        loss = ((out["color"] - flat_rgb[idx]) ** 2).mean()
        proposal = sampler.training_loss(flat_rgb[idx])          # hierarchical: the coarse network's colour loss
        extra = {} if proposal is None else {"fine_loss": loss.detach(), "coarse_loss": proposal.detach()}
        return {"loss": loss if proposal is None else loss + proposal, **extra, "samples_per_ray": out["samples_per_ray"],
                "lr": torch.tensor(opt.param_groups[0]["lr"]),
                **{k: torch.tensor(float(v)) for k, v in sampler.stats().items()}}

    def after_step(step: int) -> None:
        stats["train_seconds"] += time.perf_counter() - stats.pop("_t0", time.perf_counter())
        stats["steps"] += 1

    def figures() -> Dict[str, float]:
        return {"samples_per_ray": stats["samples_per_ray"], "train_seconds": stats["train_seconds"],
                "rays_per_second": stats["steps"] * batch / max(stats["train_seconds"], 1e-9), **sampler.stats()}

    def evaluate(views: torch.Tensor):
        views = views.to(ctx.device)
        return evaluate_views(render_fn, data.cameras[views], data.images[views], int(cfg.chunk))

    val = data.val[: int(cfg.eval_views)] if int(cfg.eval_views) > 0 else data.val

    # what follows training: the test views (the gif takes what is left) and, extracted, the mesh
    budget = TimeBudget.of(ctx, evals_after=views_in_validations(len(val), len(data.test)))
    before_after = BeforeAfter()
    trainable.extra["before_after"] = before_after      # checkpointed: a resumed run keeps its "before"
    if len(val) and bool(cfg.before_after) and not (bool(cfg.resume) and ctx.path("checkpoint.pt").exists()):
        # priced on a part first: the untrained field skips no sample, and a picture that does not fit is not drawn
        price = budget.price_from_part(lambda: render_part(render_fn, data.cameras[val.to(ctx.device)],
                                                           most=int(cfg.chunk)))
        if budget.fits_before_training(price):
            budget.time_validation(lambda: before_after.before(ctx, lambda: evaluate(val)))   # the loop's first price
        else:
            note = (f"before_after: the picture before training would take about {price:.0f} s of "
                    f"time_budget={budget.seconds:g} s: not drawn")
            print(f"l3d_app: note: {note}", file=sys.stderr)
            ctx.logger.text("train/budget", note)

    def eval_fn(step: int) -> Dict[str, float]:
        sampler.update(step, model, ctx.generator)
        metrics, picture, _ = evaluate(val)
        before_after.after(picture)
        return {**metrics, **figures(), "images": {"views": picture}}

    mesh_reserve = budget.keep_mesh(int(cfg.mesh_resolution), float(cfg.mesh_reserve), lambda: seconds_per_grid_point(
        model.density, box, device=ctx.device)) if bool(cfg.extract_mesh) else 0.0
    with ctx.stopwatch.stage("train"):
        result = train(ctx, trainable, step_fn, loop_spec(cfg, "train_nerf"), eval_fn if len(val) else None, budget,
                       after_step)
    finish_viewer(live, ctx, result.step)
    with torch.no_grad():
        sampler.update(result.step, model, ctx.generator)
        test, picture, _ = evaluate(data.test)                                  # the one test evaluation
        log_test(ctx, test, result.step, images={"views": picture})
        save_png(ctx.path("test_views.png"), picture)
        metrics = {k: round(v, 4) for k, v in test.items()}
        metrics.update(before_after.save(ctx))
        if bool(cfg.extract_mesh):
            mesh = extract_mesh(lambda p: -model.density(p), box, int(cfg.mesh_resolution), -float(cfg.mesh_threshold),
                                color_fn=lambda v, n: model(v, -n)[1], device=ctx.device)
            if mesh is None:
                ctx.logger.text("mesh", "no mesh written: the density never reaches mesh_threshold in the box")
            else:
                if bool(cfg.mesh_cull):      # what no training camera sees: free space, not a leftover
                    save_field_mesh(mesh, ctx.path("mesh_uncut"), ["ply"])
                    mesh, metrics["mesh_culled_area"] = cull_to_training_views(mesh, data, box,
                                                                               int(cfg.mesh_resolution))
                save_field_mesh(mesh, ctx.path("mesh"), config_words(cfg.mesh_formats, "mesh_formats"))
            metrics["mesh_faces"] = 0 if mesh is None else int(mesh.num_faces)
            metrics["mesh_reserve_seconds"] = round(mesh_reserve, 4)
        metrics["gif_frames"] = write_field_turntables(cfg, ctx, data, {"turntable.gif": color_depth_frames(
            render_fn, int(cfg.chunk))}, budget)
    metrics.update({**{k: v for k, v in result.val_metrics().items() if k in ("val_psnr", "val_ssim")},
                    **result.timing(), "n_params": sum(p.numel() for p in [*model.parameters(), *sampler.parameters()]),
                    **{k: round(float(v), 5) for k, v in figures().items()}, "history": result.history_rows()})
    metrics["budget_stop"] = result.budget_stop
    metrics["background"] = [round(float(c), 4) for c in background["rgb"].detach().clamp(0, 1)]
    return metrics
