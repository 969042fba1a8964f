"""gs_train: 3D Gaussian splatting from posed images (built-in scene, truck, NeRF-synthetic).

Initial splats: the dataset's own points (``data.points``, e.g. the truck's
``points_10000.npy``) when it carries them, else ``n_init`` points drawn uniformly in its
scene box; colours (``init_colors``): ``views`` = median of the training pixels each point
projects to, ``points`` = the dataset's ``point_colors``, ``grey``. Scales: the neighbour distance,
shrunk by one factor to ``init_max_coverage``; a photo capture's (points, background unknown: walls and
floor are scene) capped per splat instead, and the view cells they leave uncovered get splats of their
own (:func:`~l3d_app.models.gaussian_start.cover_views`). Each step renders one
random training view and minimises ``L1 + ssim_lambda (1 - SSIM)`` (+ the strategy's
regulariser) with Adam (per-parameter rates as in 3DGS; the means' rate is scaled by the
scene extent and decays exponentially, a LambdaLR the shared loop steps). The SH degree
rises by one every ``sh_every`` steps up to ``sh_degree``. Densification is the
``strategy=`` group (:mod:`l3d_app.strategies`), checkpointed with the model.
Every step schedule (the means' LR decay, the SH degree, the strategy's densification and
resets) is read by step: a time budget that binds cuts the schedule where it stops the run, and
the strategy hears (``info["steps_left"]``) how many steps the budget still leaves at the recent
seconds per step (:meth:`~l3d_app.runtime.budget.TimeBudget.steps_that_fit`).
The data, initialisation, optimiser and per-step work are shared with ``surfels``
(:mod:`l3d_app.pipelines.splats`).
Validation views are evaluated every ``eval_every`` steps (TensorBoard ``val/``, with a
prediction | truth | error | depth picture); the test views once at the end.
``+init_points=N`` (N > 0) keeps that many of the data's initial points (a seeded random subset, as the course
subsamples its cloud). Outputs: ``test_views.gif``, ``progress.gif`` (the course's grid: the first
four validation views over training, or ``+progress_views=K`` of them, their ground truth below),
``point_cloud.ply`` (3DGS layout), ``metrics.json``.
"""

from __future__ import annotations

from typing import List

import torch

from l3d_app.errors import UserError
from l3d_app.models.background import background_parameter
from l3d_app.pipelines.live_viewer import finish_viewer, gaussian_view, start_viewer
from l3d_app.pipelines.splats import (SplatSteps, evaluate_views, initial_splats, scene_extent, splat_optimizer,
                                     write_splat_outputs)
from l3d_app.registry import DATASETS, STRATEGIES, TASKS
from l3d_app.render.gaussians.panels import depth_range
from l3d_app.render.gaussians.progress_grid import progress_grid
from l3d_app.render.gaussians.rasterize import rasterize_gaussians
from l3d_app.runtime.budget import TimeBudget
from l3d_app.runtime.media import to_uint8
from l3d_app.runtime.training import Trainable, train
from l3d_app.tasks.common import loop_spec, require_positive


@TASKS.register("gs_train")
def gs_train(cfg, ctx) -> dict:
    """Train Gaussians; val figures during training, test figures once; gifs / ply / metrics."""
    require_positive(cfg, "iters", "eval_every", "sh_every", "lr_decay_steps", "tile_size", "log_every")
    if cfg.get("sh_degree") not in (0, 1, 2, 3):      # checked now, not when the schedule reaches it mid-run
        raise UserError(f"sh_degree must be 0, 1, 2 or 3, got {cfg.get('sh_degree')!r}")
    raw = DATASETS.build(cfg.data)
    if len(raw.val) == 0:
        raise UserError(f"gs_train needs validation views and data '{cfg.data.name}' has none")
    data = raw.to(ctx.device)
    model = initial_splats(raw, data, ctx.generator, int(cfg.n_init), str(cfg.init_colors), float(cfg.init_opacity),
                           bool(cfg.isotropic), float(cfg.init_scale), float(cfg.init_max_coverage),
                           data_name=str(cfg.data.name),
                           init_points=int(cfg.init_points) if "init_points" in cfg else 0).to(ctx.device)
    extent = scene_extent(data.cameras[data.train], float(cfg.extent_margin))   # training cameras only (3DGS)
    background = background_parameter(cfg.learn_background, data)  # learnt for real captures
    opt, sched = splat_optimizer(model, background, cfg.lr, extent, float(cfg.adam_eps), int(cfg.lr_decay_steps))
    strategy = STRATEGIES.build(cfg.strategy)
    strategy.initialize(model, opt, extent)
    steps = SplatSteps(model, opt, strategy, data.train, data.images, ctx.generator, float(cfg.ssim_lambda),
                       int(cfg.sh_degree), int(cfg.sh_every))
    prog_frames: List[torch.Tensor] = []     # uint8 (H, W, 3) validation grids: checkpointed, so a resumed gif is whole
    trainable = Trainable({"gaussians": model, "background": background}, opt, schedulers=[sched],
                          extra={"strategy": strategy, "progress_frames": prog_frames,
                                 "step_times": steps.step_times})    # step costs cover the resumed parts of a run
    degree = steps.degree
    budget = TimeBudget.of(ctx, evals_after=len(data.test) / len(data.val))   # the test views

    def render(i: int, deg: int):
        return rasterize_gaussians(model.means, model.log_scales3, model.quats, model.opacity_logits, model.sh,
                                   deg, data.cameras[i], background["rgb"].clamp(0, 1), tile_size=int(cfg.tile_size))

    live = start_viewer(cfg, ctx, data, *gaussian_view(model, background["rgb"], degree, int(cfg.tile_size)))

    def step_fn(step: int):
        i = steps.begin()
        out = render(i, degree(step))
        loss, l1 = steps.photometric(out["color"][0], i)
        return {"loss": steps.finish(loss, out, step), "l1": l1.detach(), "n_gaussians": torch.tensor(float(model.num))}

    lo_hi = depth_range(data.cameras[int(data.val[0])].centers()[0], data.scene_box)

    def evaluate(views, deg):
        return evaluate_views(lambda i: render(i, deg), views, data.images, lo_hi)

    grid_kw = {"views": int(cfg.progress_views)} if "progress_views" in cfg else {}   # +progress_views=K (4)

    def eval_fn(step: int):
        pred, truth, panel, m = evaluate(data.val, degree(step))
        prog_frames.append(torch.from_numpy(to_uint8(progress_grid(pred, truth, **grid_kw))))
        return {**m, "n_gaussians": model.num, "images": {"pred_truth_error_depth": panel}}

    with ctx.stopwatch.stage("train"):
        result = train(ctx, trainable, step_fn, loop_spec(cfg, "gs_train", log_every=int(cfg.log_every)), eval_fn,
                       budget, steps.after_step_hook(int(cfg.iters), budget, ctx.logger))
    finish_viewer(live, ctx, result.step)
    test = write_splat_outputs(ctx, model, result.step, *evaluate(data.test, degree(result.step)), prog_frames,
                               float(cfg.fps))
    return {**test, **result.val_metrics(), **result.timing(), "n_gaussians": model.num,
            "background": [round(float(c), 4) for c in background["rgb"].detach().clamp(0, 1)],
            **steps.step_cost(), "history": result.history_rows()}
