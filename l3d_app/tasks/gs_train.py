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
Validation views are evaluated every ``eval_every`` steps (TensorBoard ``val/``, with a
prediction | truth | error | depth picture); the test views once at the end.
Outputs: ``test_views.gif``, ``progress.gif`` (a validation view over training),
``point_cloud.ply`` (3DGS layout), ``metrics.json``.
"""

from __future__ import annotations

import time
from typing import List

import torch

from l3d_app.errors import UserError
from l3d_app.geometry.gaussian_ply import save_gaussian_ply
from l3d_app.metrics.image import psnr, ssim
from l3d_app.models.background import background_parameter
from l3d_app.models.gaussian_start import cover_views
from l3d_app.models.gaussians import colors_from_views, init_from_points
from l3d_app.registry import DATASETS, STRATEGIES, TASKS
from l3d_app.render.gaussians.coverage import shrink_to_coverage
from l3d_app.render.gaussians.panels import colorize_depth, depth_range, error_map, side_by_side
from l3d_app.render.gaussians.rasterize import rasterize_gaussians
from l3d_app.runtime.budget import TimeBudget
from l3d_app.runtime.lr_schedules import exponential
from l3d_app.runtime.media import save_gif, to_uint8
from l3d_app.runtime.random import rand, randint
from l3d_app.runtime.training import Trainable, log_test, train
from l3d_app.tasks.common import loop_spec, require_positive
from l3d_app.pipelines.live_viewer import finish_viewer, gaussian_view, start_viewer


def _initial_model(cfg, raw, data, generator):
    points, colors = getattr(raw, "points", None), None
    if points is None:
        lo, hi = data.scene_box[0].cpu(), data.scene_box[1].cpu()
        points = lo + (hi - lo) * rand((int(cfg.n_init), 3), generator)
    points = points.float().to(data.images.device)
    mode = str(cfg.init_colors)
    if mode == "views":
        colors = colors_from_views(points, data.images[data.train], data.cameras[data.train])
    elif mode == "points":
        colors = getattr(raw, "point_colors", None)
        if colors is None:
            raise UserError(f"init_colors=points: data '{cfg.data.name}' has no point colours (use views or grey)")
    elif mode != "grey":
        raise UserError(f"init_colors must be views, points or grey, got {mode!r}")
    model = init_from_points(points, colors, opacity=float(cfg.init_opacity), isotropic=bool(cfg.isotropic),
                             scale_factor=float(cfg.init_scale)).to(points.device)
    views = data.train[torch.linspace(0, len(data.train) - 1, min(16, len(data.train))).long()]
    if getattr(raw, "points", None) is not None and not data.background_known:    # a photo capture: all is scene
        model = cover_views(model, data.images[views], data.cameras[views], float(cfg.init_max_coverage))
    elif float(cfg.init_max_coverage) > 0:          # bounded start-up cost (render/gaussians/coverage.py)
        model.log_scales.data = shrink_to_coverage(model.means, model.log_scales, model.quats,
                                                   torch.sigmoid(model.opacity_logits), data.cameras[views],
                                                   float(cfg.init_max_coverage))
    return model


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
    model = _initial_model(cfg, raw, data, ctx.generator).to(ctx.device)
    centres = data.cameras[data.train].centers()       # the training cameras only (3DGS): no test pose shapes training
    extent = float(cfg.extent_margin) * float((centres - centres.mean(0)).norm(dim=-1).max())
    lr = cfg.lr
    groups = [("means", model.means, float(lr.means) * extent), ("scales", model.log_scales, float(lr.scales)),
              ("quats", model.quats, float(lr.quats)), ("opacity", model.opacity_logits, float(lr.opacity)),
              ("sh_dc", model.sh_dc, float(lr.sh_dc)), ("sh_rest", model.sh_rest, float(lr.sh_rest))]
    background = background_parameter(cfg.learn_background, data)  # learnt for real captures
    if background["rgb"].requires_grad:
        groups.append(("background", background["rgb"], float(lr.background)))
    # fused: one vectorised pass per parameter for the whole update
    opt = torch.optim.Adam([{"params": [p], "lr": r, "name": n} for n, p, r in groups], eps=float(cfg.adam_eps),
                           fused=True)
    decay = exponential(float(lr.means_final) / float(lr.means), int(cfg.lr_decay_steps))
    sched = torch.optim.lr_scheduler.LambdaLR(opt, [decay] + [lambda s: 1.0] * (len(groups) - 1))
    strategy = STRATEGIES.build(cfg.strategy)
    strategy.initialize(model, opt, extent)
    prog_frames: List[torch.Tensor] = []     # uint8 (H, W, 3) validation panels: checkpointed, so a resumed gif is whole
    trainable = Trainable({"gaussians": model, "background": background}, opt,
                          extra={"strategy": strategy, "progress_frames": prog_frames},
                          schedulers=[sched])
    H, W = data.image_size
    tr, lam, info, step_times = data.train, float(cfg.ssim_lambda), {"width": W, "height": H}, []
    trainable.extra["step_times"] = step_times      # checkpointed: the step costs cover the resumed parts of a run

    budget = TimeBudget.of(ctx, evals_after=len(data.test) / len(data.val))   # the test views

    def degree(step: int) -> int:
        return min(int(cfg.sh_degree), step // int(cfg.sh_every))

    def render(i: int, deg: int):
        return rasterize_gaussians(model.means, model.log_scales3, model.quats, model.opacity_logits, model.sh,
                                   deg, data.cameras[i], background["rgb"].clamp(0, 1), tile_size=int(cfg.tile_size))

    live = start_viewer(cfg, ctx, data, *gaussian_view(model, background["rgb"], degree, int(cfg.tile_size)))

    def step_fn(step: int):
        info["t0"], info["c0"] = time.perf_counter(), time.process_time()
        i = int(tr[int(randint(0, len(tr), (1,), ctx.generator))])
        out = render(i, degree(step))
        pred, target = out["color"][0], data.images[i]
        l1 = (pred - target).abs().mean()
        loss = l1 + lam * (1 - ssim(pred, target)) if lam > 0 else l1
        reg = strategy.regularization(model)
        loss = loss if reg is None else loss + reg
        info.update(means2d=out["means2d"], radii=out["radii"])
        strategy.step_pre_backward(model, opt, step, info)
        return {"loss": loss, "l1": l1.detach(), "n_gaussians": torch.tensor(float(model.num))}

    def after_step(step: int) -> None:
        # steps after this one: to iters, or fewer where the budget (at the recent seconds per step) ends sooner
        fit = budget.steps_that_fit([t for t, _ in step_times[-50:]])
        info["steps_left"] = int(cfg.iters) - (step + 1) if fit is None else min(int(cfg.iters) - (step + 1), fit)
        logs = strategy.step_post_backward(model, opt, step, info, ctx.generator)
        if logs:
            ctx.logger.log_scalars({f"strategy/{k}": v for k, v in logs.items()}, step + 1)
        step_times.append((time.perf_counter() - info["t0"], time.process_time() - info["c0"]))

    lo_hi = depth_range(data.cameras[int(data.val[0])].centers()[0], data.scene_box)

    def evaluate(views, deg):
        outs = [render(int(i), deg) for i in views]
        pred = torch.cat([o["color"] for o in outs]).clamp(0, 1)
        target = data.images[views.to(ctx.device)]
        depth = colorize_depth(outs[0]["expected_depth"][0], *lo_hi, mask=outs[0]["alpha"][0] > 0.5)
        panel = side_by_side([pred[0], target[0], error_map(pred[0], target[0]), depth])
        return pred, target, panel, {"psnr": float(psnr(pred, target)), "ssim": float(ssim(pred, target))}

    def eval_fn(step: int):
        pred, _, panel, m = evaluate(data.val, degree(step))
        prog_frames.append(torch.from_numpy(to_uint8(panel)))
        return {**m, "n_gaussians": model.num, "images": {"pred_truth_error_depth": panel}}

    with ctx.stopwatch.stage("train"):
        result = train(ctx, trainable, step_fn, loop_spec(cfg, "gs_train", log_every=int(cfg.log_every)), eval_fn,
                       budget, after_step)
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
            **_step_cost(step_times), "history": result.history_rows()}


def _step_cost(times, first: int = 100) -> dict:
    """Mean wall and CPU (process) seconds per step over the first ``first`` steps and the rest
    (CPU time is the figure to compare on a shared machine, with threads=1)."""
    out = {}
    for name, part in (("first_100", times[:first]), ("after_100", times[first:])):
        out[f"seconds_per_step_{name}"] = round(sum(t[0] for t in part) / max(1, len(part)), 5)
        out[f"cpu_seconds_per_step_{name}"] = round(sum(t[1] for t in part) / max(1, len(part)), 5)
    return out
