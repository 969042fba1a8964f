"""gs_train: 3D Gaussian splatting from posed images (built-in scene, truck, NeRF-synthetic).

Initial splats: the dataset's own points (``data.points``, e.g. the truck's
``points_10000.npy``) when it carries them, else ``n_init`` points drawn uniformly in its
scene box; colours (``init_colors``): ``views`` = median of the training pixels each point
projects to, ``points`` = the dataset's ``point_colors``, ``grey``. Each step renders one
random training view and minimises ``L1 + ssim_lambda (1 - SSIM)`` (+ the strategy's
regulariser) with Adam (per-parameter rates as in 3DGS; the means' rate is scaled by the
scene extent and decays exponentially, a LambdaLR the shared loop steps). The SH degree
rises by one every ``sh_every`` steps up to ``sh_degree``. Densification is the
``strategy=`` group (:mod:`l3d_app.strategies`), checkpointed with the model.
Every step schedule (the means' LR decay, the SH degree, the strategy's densification,
resets and ``until``) is read at the nominal step of a
:class:`~l3d_app.runtime.horizon.Horizon`. ``schedule=steps`` (the default) reads it by
step: a time budget that binds cuts the schedule where it stops the run.
``schedule=budget`` lets the training loop predict that stop, so the whole schedule is
compressed into the steps that fit (in proportion to the training time: the prediction uses
the mean seconds per step so far) and the run ends with the refinement after the last
densification; on the development scene ``ground`` at 128 px on 2 AVX2 cores it read lower
than ``steps`` (val -0.32 / -0.14 dB on seeds 0 / 1: the splats reach the cap sooner, every
later step is dearer, fewer steps fit; docs/measured/gaussians.md). ``schedule=refine``
compresses the LR decay and the SH degree as ``budget`` does, but the strategy densifies and
resets on its step cadence; only the end of its growth phase (``until``) is scaled by the
steps that fit over ``iters`` (predicted from the recent seconds per step, as the reset guard
does), so a budget-stopped run still ends with a refinement phase.
Validation views are evaluated every ``eval_every`` steps (TensorBoard ``val/``, with a
prediction | truth | error | depth picture); the test views once at the end.
Outputs: ``test_views.gif``, ``progress.gif`` (a validation view over training),
``point_cloud.ply`` (3DGS layout), ``metrics.json``.
"""

from __future__ import annotations

from typing import List

import torch

from l3d_app.errors import UserError
from l3d_app.geometry.gaussian_ply import save_gaussian_ply
from l3d_app.pipelines.splats import SplatSteps, evaluate_views, initial_splats, scene_extent, splat_optimizer
from l3d_app.registry import DATASETS, STRATEGIES, TASKS
from l3d_app.render.gaussians.rasterize import rasterize_gaussians
from l3d_app.render.gaussians.panels import depth_range
from l3d_app.runtime.horizon import Horizon
from l3d_app.runtime.media import save_gif, to_uint8
from l3d_app.runtime.training import Trainable, log_test, train
from l3d_app.tasks.common import background_parameter, require_positive
from l3d_app.tasks.viewer_common import finish_viewer, gaussian_view, start_viewer


SCHEDULES = ("steps", "budget", "refine")


@TASKS.register("gs_train")
def gs_train(cfg, ctx) -> dict:
    """Train Gaussians; val figures during training, test figures once; gifs / ply / metrics."""
    require_positive(cfg, "iters", "eval_every", "sh_every", "lr_decay_steps", "tile_size", "log_every")
    if cfg.get("sh_degree") not in (0, 1, 2, 3):      # checked now, not when the schedule reaches it mid-run
        raise UserError(f"sh_degree must be 0, 1, 2 or 3, got {cfg.get('sh_degree')!r}")
    if cfg.get("schedule") not in SCHEDULES:
        raise UserError(f"schedule must be steps, budget or refine, got {cfg.get('schedule')!r}")
    raw = DATASETS.build(cfg.data)
    if len(raw.val) == 0:
        raise UserError(f"gs_train needs validation views and data '{cfg.data.name}' has none")
    data = raw.to(ctx.device)
    model = initial_splats(raw, data, ctx.generator, int(cfg.n_init), str(cfg.init_colors), float(cfg.init_opacity),
                           bool(cfg.isotropic), float(cfg.init_scale), float(cfg.init_max_coverage),
                           data_name=str(cfg.data.name)).to(ctx.device)
    extent = scene_extent(data.cameras[data.train], float(cfg.extent_margin))   # training cameras only (3DGS)
    background = background_parameter(cfg.learn_background, data)  # learnt for real captures
    on_budget, refine = cfg.schedule == "budget", cfg.schedule == "refine"
    horizon = Horizon(int(cfg.iters))     # budget / refine: the loop predicts the budget's stop, the schedules end there
    opt, sched = splat_optimizer(model, background, cfg.lr, extent, float(cfg.adam_eps), int(cfg.lr_decay_steps),
                                 horizon=horizon)
    strategy = STRATEGIES.build(cfg.strategy)
    strategy.initialize(model, opt, extent)
    steps = SplatSteps(model, opt, strategy, data.train, data.images, ctx.generator, float(cfg.ssim_lambda),
                       int(cfg.sh_degree), int(cfg.sh_every), horizon=horizon)
    prog_frames: List[torch.Tensor] = []     # uint8 (H, W, 3) validation panels: checkpointed, so a resumed gif is whole
    trainable = Trainable({"gaussians": model, "background": background}, opt, schedulers=[sched],
                          extra={"strategy": strategy, "horizon": horizon, "progress_frames": prog_frames,
                                 "step_times": steps.step_times})    # step costs cover the resumed parts of a run
    info, degree = steps.info, steps.degree

    def render(i: int, deg: int):
        return rasterize_gaussians(model.means, model.log_scales3, model.quats, model.opacity_logits, model.sh,
                                   deg, data.cameras[i], background["rgb"].clamp(0, 1), tile_size=int(cfg.tile_size))

    live = start_viewer(cfg, ctx, data, *gaussian_view(model, background["rgb"], degree, int(cfg.tile_size)))

    def step_fn(step: int):
        i = steps.begin()
        out = render(i, degree(step))
        loss, l1 = steps.photometric(out["color"][0], i)
        return {"loss": steps.finish(loss, out, step), "l1": l1.detach(), "n_gaussians": torch.tensor(float(model.num))}

    def steps_left(step: int) -> float:
        """Steps after this one on the strategy's schedule: by step, to ``iters`` or fewer where the
        time budget (at the recent wall seconds per step) ends the run sooner; on the budget's
        horizon, the nominal steps to ``iters``. The strategy skips an opacity reset near the end."""
        if on_budget:
            return int(cfg.iters) - info["schedule"][1]
        seconds = float(cfg.time_budget) - float(cfg.reserve) - ctx.stopwatch.elapsed
        return steps.steps_left(step, int(cfg.iters), seconds if float(cfg.time_budget) > 0 else None)

    def after_step(step: int) -> None:
        if refine:       # events by step; the growth phase ends in proportion to the steps that fit
            info["schedule"] = (step, step + 1)
            left = steps_left(step)     # at the recent seconds per step: the splats only grow
            info["until_scale"] = min(1.0, (step + 1 + left) / int(cfg.iters))
        else:
            info["schedule"] = horizon.advance(step + 1)      # the strategy's steps on the same schedule
            left = steps_left(step)
        logs = steps.after_step(step, left)
        if on_budget and step % int(cfg.log_every) == 0:   # how far the compressed schedule has come
            logs = {**logs, "nominal_step": info["schedule"][1], "predicted_steps": horizon.steps}
        elif refine and step % int(cfg.log_every) == 0:  # where the growth phase ends, the LR's nominal step
            logs = {**logs, "nominal_step": horizon.nominal(step + 1), "predicted_steps": horizon.steps}
            if getattr(strategy, "until", None) is not None:
                logs["until"] = strategy.phase_end(float(strategy.until), info)
        if logs:
            ctx.logger.log_scalars({f"strategy/{k}": v for k, v in logs.items()}, step + 1)

    lo_hi = depth_range(data.cameras[int(data.val[0])].centers()[0], data.scene_box)

    def evaluate(views, deg):
        return evaluate_views(lambda i: render(i, deg), views, data.images, lo_hi)

    def eval_fn(step: int):
        pred, _, panel, m = evaluate(data.val, degree(step))
        prog_frames.append(torch.from_numpy(to_uint8(panel)))
        return {**m, "n_gaussians": model.num, "images": {"pred_truth_error_depth": panel}}

    with ctx.stopwatch.stage("train"):
        result = train(ctx, trainable, step_fn, int(cfg.iters), eval_fn=eval_fn, eval_every=int(cfg.eval_every),
                       checkpoint_every=int(cfg.checkpoint_every), resume=bool(cfg.resume), desc="gs_train",
                       after_step=after_step, log_every=int(cfg.log_every), time_budget=float(cfg.time_budget),
                       reserve=float(cfg.reserve), reserve_evals=len(data.test) / len(data.val),
                       horizon=horizon if (on_budget or refine) else None)
    finish_viewer(live, ctx, result.step)
    with torch.no_grad():
        pred, target, panel, test = evaluate(data.test, degree(result.step))
    test = {k: round(v, 4) for k, v in test.items()}
    log_test(ctx, test, result.step, images={"pred_truth_error_depth": panel})
    save_gif(ctx.path("test_views.gif"), torch.cat([pred, target], 2), fps=float(cfg.fps) / 4)
    if prog_frames:
        save_gif(ctx.path("progress.gif"), torch.stack(prog_frames).float() / 255.0, fps=float(cfg.fps))
    save_gaussian_ply(ctx.path("point_cloud.ply"), **model.tensors())
    return {**test, **result.val_metrics(), **result.timing(), "n_gaussians": model.num,
            "background": [round(float(c), 4) for c in background["rgb"].detach().clamp(0, 1)],
            **steps.step_cost(), "history": result.history_rows()}

