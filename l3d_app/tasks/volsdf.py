"""volsdf: a neural SDF + colour network trained from posed images by SDF volume rendering.

The method is parts composed from config: the model (``model=``, :mod:`~l3d_app.models.sdf_grid`), the density
(``density=volsdf | neus | auto``, :mod:`~l3d_app.render.sdf.density_choice`), the sampler (``sampler=sdf_cache``),
the loss terms (``losses.*``, :mod:`~l3d_app.losses.terms`) and the stages (``stages.*``, :mod:`~l3d_app.stages`).
Validation every ``eval_every`` steps, the test views once at the end, then the marching-cubes mesh scored
against the data's true surface and the turntables. docs/neural_fields.md describes the method and its
outputs, docs/measured/volsdf.md its figures.
"""

from __future__ import annotations

from typing import Dict

import torch

from l3d_app.geometry.training_rays import TrainingRays
from l3d_app.losses.terms import Batch, LossTerms
from l3d_app.models.background import background_parameter
from l3d_app.models.sdf_gradients import field_with_gradient
from l3d_app.pipelines.live_viewer import finish_viewer, sdf_view, start_viewer
from l3d_app.pipelines.surfaces import surface_mesh, surface_turntables
from l3d_app.pipelines.views import BeforeAfter, evaluate_views
from l3d_app.registry import DATASETS, DENSITIES, MODELS, SAMPLERS, TASKS
from l3d_app.render.field_mesh import seconds_per_grid_point
from l3d_app.render.mesh.visibility import cull_to_training_views
from l3d_app.render.sdf.density_choice import choose_density, possible_configs, with_density_warmup
from l3d_app.render.sdf.volume import render_sdf_rays
from l3d_app.runtime.budget import TimeBudget, views_in_validations
from l3d_app.runtime.config_values import config_words
from l3d_app.runtime.horizon import Horizon
from l3d_app.runtime.media import save_png
from l3d_app.runtime.optim import build_optimizer
from l3d_app.runtime.random import randint
from l3d_app.runtime.step_clock import StepClock
from l3d_app.runtime.training import Trainable, log_test, train
from l3d_app.stages.base import MethodState, Stages
from l3d_app.tasks.common import loop_spec, require_mesh_formats, require_mesh_resolution, require_positive
from l3d_app.tasks.field_common import write_field_turntables


@TASKS.register("volsdf")
def volsdf(cfg, ctx) -> dict:
    """Train on the train views, validate on val, test once; surface scores, gifs, mesh, metrics."""
    require_positive(cfg, "iters", "batch_rays", "chunk", "supersample", "val_supersample", "eval_every")
    require_mesh_resolution(cfg)
    require_mesh_formats(cfg)
    with_density_warmup(cfg.optim, DENSITIES.get("volsdf"))      # auto or an integer >= 0, before the data is read
    losses, stages = LossTerms.build(cfg.losses), Stages.build(cfg.stages)    # checked before the data is read
    [DENSITIES.build(option) for option in possible_configs(cfg.density)]
    data = DATASETS.build(cfg.data).to(ctx.device)
    density_cfg, below = choose_density(cfg.density, data)
    dens = DENSITIES.build(density_cfg).to(ctx.device)
    ctx.logger.text("density", f"{density_cfg['name']} ({100 * below:.0f}% of the training cameras below the scene's "
                               f"centre; density={cfg.density.name})")
    box, iters = data.scene_box.tolist(), int(cfg.iters)
    model = MODELS.build(cfg.model, scene_box=box).to(ctx.device)
    rays = TrainingRays.of_views(data.cameras, data.images, data.masks, data.train.to(ctx.device))
    state = MethodState(data, rays, model, dens, box, iters, bool(cfg.resume) and ctx.path("checkpoint.pt").exists(),
                        losses.needs(), lambda: background_parameter(cfg.learn_background, data))
    stages.setup(state, ctx)
    sampler = SAMPLERS.build(cfg.sampler, scene_box=box).to(ctx.device)
    background = background_parameter(cfg.learn_background, data)  # learnt for real captures
    groups = [{"params": list(model.parameters()) + ([background["rgb"]] if background["rgb"].requires_grad else [])},
              {"params": list(dens.parameters()), "lr": dens.lr}]
    horizon = Horizon(iters)     # where a time budget will stop the run: the schedules end there
    optim_cfg = with_density_warmup(cfg.optim, dens)
    opt, scheds = build_optimizer(optim_cfg, groups, iters, horizon=horizon)
    trainable = Trainable({"field": model, "density": dens, "background": background}, opt,
                          extra={"sampler": sampler, "horizon": horizon}, schedulers=scheds)
    field_fn, batch, clock, last = field_with_gradient(model), int(cfg.batch_rays), StepClock(), {}
    trainable.extra["step_stats"] = clock      # checkpointed: the rates cover the resumed parts of a run
    live = start_viewer(cfg, ctx, data, *sdf_view(model, sampler, dens, background["rgb"], int(cfg.chunk)))

    def render(o, d, **kw):
        return render_sdf_rays(field_fn, o, d, sampler, dens, field=model, background=background["rgb"].clamp(0, 1),
                               **kw)

    def evaluate(views: torch.Tensor, supersample: int):
        views = views.to(ctx.device)
        with torch.no_grad():   # a fresh SDF cache (step -1: not a training step; the schedule goes on)
            sampler.update(-1, model, ctx.generator, force=True)   # evaluation renders skip the rays it calls empty
        return evaluate_views(render, data.cameras[views], data.images[views], int(cfg.chunk), supersample)

    val = data.val[: int(cfg.eval_views)] if int(cfg.eval_views) > 0 else data.val
    budget = TimeBudget.of(ctx, reserve=0.0, horizon=horizon, evals_after=views_in_validations(    # the test views
        len(val), len(data.test), int(cfg.supersample), int(cfg.val_supersample)))    # (the gifs take what is left)
    reserve = budget.keep_mesh(int(cfg.mesh_resolution), float(cfg.reserve),      # the mesh and its scores
                               lambda: seconds_per_grid_point(model.sdf, box, device=ctx.device))
    before_after = BeforeAfter()
    trainable.extra["before_after"] = before_after      # checkpointed: a resumed run keeps its "before"
    if len(val) and bool(cfg.before_after) and not state.resuming:   # the loop's first price (a fuzzy start: the dearest)
        budget.time_validation(lambda: before_after.before(ctx, lambda: evaluate(val, int(cfg.val_supersample))))
    interrupted = stages.before_training(state, ctx, budget)
    if interrupted is not None:     # nothing trained yet
        return {"interrupted_in": interrupted}
    losses.setup(state)

    def step_fn(step: int) -> Dict[str, torch.Tensor]:
        clock.start()
        nominal = horizon.nominal(step)      # = step unless the time budget binds
        logs = {k: torch.tensor(v) for k, v in stages.on_step(state, nominal).items()}
        dens.schedule(nominal, iters)
        sampler.update(step, model, ctx.generator)
        idx = randint(0, rays.n, (batch,), ctx.generator, ctx.device)
        o, d = rays.origins[idx], torch.nn.functional.normalize(rays.dirs[idx], dim=-1)
        out = render(o, d, perturb=True, generator=ctx.generator)
        loss, terms = losses(Batch(state, idx, o, d, rays.rgb[idx], out, nominal / max(iters, 1), ctx.generator), iters)
        last.update({k: float(out[k]) for k in ("samples_per_ray", "fine_samples_per_ray") if k in out})
        return {**logs, **terms, **{k: torch.tensor(float(v)) for k, v in dens.stats().items()}, "loss": loss,
                "samples_per_ray": out["samples_per_ray"], "nominal_step": torch.tensor(float(nominal)),
                "predicted_steps": torch.tensor(horizon.steps)}

    def eval_fn(step: int) -> Dict[str, float]:
        metrics, picture, _ = evaluate(val, int(cfg.val_supersample))
        before_after.after(picture)
        return {**metrics, **dens.stats(), "samples_per_ray": last.get("samples_per_ray", 0.0),
                "images": {"views": picture}, **{k: clock.state[k] for k in ("train_seconds", "cpu_seconds")}}

    with ctx.stopwatch.stage("train"):
        result = train(ctx, trainable, step_fn, loop_spec(cfg, "volsdf"), eval_fn if len(val) else None, budget,
                       clock.stop)
    finish_viewer(live, ctx, result.step)
    model.eval()
    with torch.no_grad():
        sampler.update(result.step, model, ctx.generator, force=True)
        test, picture, _ = evaluate(data.test, int(cfg.supersample))             # the one test evaluation
        log_test(ctx, test, result.step, images={"views": picture})
        save_png(ctx.path("test_views.png"), picture)
    metrics = {**{k: round(v, 4) for k, v in test.items()}, **before_after.save(ctx)}
    with ctx.stopwatch.stage("mesh"):
        cull = (lambda m: cull_to_training_views(m, data, box, int(cfg.mesh_resolution))) if cfg.mesh_cull else None
        metrics.update(surface_mesh(model.sdf, lambda v, n: field_fn(v, -n)[1], box, data, int(cfg.mesh_resolution),
                                    config_words(cfg.mesh_formats, "mesh_formats"), ctx.path, ctx.logger, ctx.device,
                                    cull=cull, n_points=int(cfg.eval_points)))
    frames = 0
    if int(cfg.gif_frames) > 0:
        with ctx.stopwatch.stage("gif"):
            frames = write_field_turntables(cfg, ctx, data, surface_turntables(model.sdf, render, box, int(cfg.chunk)),
                                            budget)
    seconds = {f"{k}_seconds": round(ctx.stopwatch.stages.get(k, 0.0), 4) for k in ("mesh", "gif")}
    return {**metrics, **{k: v for k, v in result.val_metrics().items() if k in ("val_psnr", "val_ssim")},
            "density": str(density_cfg["name"]), "cameras_below_fraction": round(below, 4),
            **{f"{k}_final": round(v, 6) for k, v in dens.stats().items()}, "beta": cfg.density.get("beta"),
            "iters": result.step, "n_params": sum(p.numel() for p in model.parameters()), **clock.rates(batch),
            "warmup_steps": int(optim_cfg.get("warmup_steps", 0)), **seconds, "mesh_reserve_seconds": round(reserve, 4),
            "gif_frames": frames, **stages.metrics(), **{k: round(v, 3) for k, v in last.items()},
            "budget_stop": result.budget_stop, "history": result.history_rows(),
            "background": [round(float(c), 4) for c in background["rgb"].detach().clamp(0, 1)]}
