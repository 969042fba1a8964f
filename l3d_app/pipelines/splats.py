"""Training splats from posed images: the parts that ``gs_train`` (3D Gaussians) and ``surfels``
(2D Gaussian surfels) share, with plain arguments.

* :func:`initial_splats`: the data's own points (``data.points``; ``init_points`` > 0 keeps a seeded random
  subset of that many, as the course subsamples its cloud) or ``n_init`` points drawn in its scene box, coloured by the training views (median of the pixels each projects to), the data's
  point colours or grey; scales from the 3 nearest neighbours, shrunk until the splats cover a
  pixel at most ``max_coverage`` deep (:mod:`~l3d_app.render.gaussians.coverage`); for 3D splats of
  a photo capture (the data's points, its background unknown: walls and floor are scene) capped per
  splat instead, with splats for the view cells left uncovered
  (:func:`~l3d_app.models.gaussian_start.cover_views`). With
  ``surfels`` the rotations are uniformly random (the normals of the disks) and the third scale
  is a thickness of :data:`SURFEL_THICKNESS` x the first (never rendered: it keeps the
  strategies' 3D operations, split sampling and noise, inside the disk).
* :func:`scene_extent` (3DGS: the training cameras' spread) and :func:`splat_optimizer` (Adam per
  parameter group at the 3DGS rates, the means' rate scaled by the extent and decayed
  exponentially, a LambdaLR the shared loop steps).
* :class:`SplatSteps`: per step, the random training view, ``L1 + ssim_lambda (1 - SSIM)``, the
  strategy's regulariser and hooks (densification, :mod:`l3d_app.strategies`), the SH degree
  rising every ``sh_every`` steps, and the step's wall and CPU seconds.
  :meth:`SplatSteps.after_step_hook` is the loop's ``after_step``: densification and its figures logged.
* :func:`evaluate_views`: PSNR / SSIM of rendered views and a prediction | truth | error | depth panel.
* :func:`write_splat_outputs`: the test figures logged once, ``test_views.gif``, ``progress.gif`` and
  ``point_cloud.ply``.
"""

from __future__ import annotations

import math
import time
from typing import Callable, Dict, List, Mapping, Optional, Sequence, Tuple

import torch

from l3d_app.errors import UserError
from l3d_app.geometry.gaussian_ply import save_gaussian_ply
from l3d_app.metrics.image import psnr, ssim
from l3d_app.models.gaussian_start import cover_views
from l3d_app.models.gaussians import GaussianModel, colors_from_views, init_from_points
from l3d_app.render.gaussians.coverage import shrink_to_coverage
from l3d_app.render.gaussians.panels import colorize_depth, error_map, side_by_side
from l3d_app.runtime.budget import TimeBudget
from l3d_app.runtime.lr_schedules import exponential
from l3d_app.runtime.media import save_gif
from l3d_app.runtime.random import rand, randint, randn, randperm
from l3d_app.runtime.training import log_test

SURFEL_THICKNESS = 1e-3     # a surfel's third scale over its first (the disk's thickness for the strategies)
INIT_COLORS = ("views", "points", "grey")


def initial_splats(raw, data, generator: Optional[torch.Generator], n_init: int, init_colors: str = "views",
                   opacity: float = 0.1, isotropic: bool = False, scale_factor: float = 1.0,
                   max_coverage: float = 0.0, surfels: bool = False, data_name: str = "",
                   init_points: int = 0) -> GaussianModel:
    """The starting splats of a multi-view dataset (``raw``: as loaded, ``data``: on the run's
    device); see the module docstring. ``init_colors``: views | points | grey (``data_name`` for
    the message when the data has no point colours); ``init_points`` > 0: that many of the data's points,
    a random subset drawn with ``generator`` (0: all)."""
    points, colors, point_colors = getattr(raw, "points", None), None, getattr(raw, "point_colors", None)
    keep = int(init_points)
    if keep < 0:
        raise UserError(f"init_points must be >= 0 (0: all of the data's points), got {keep}")
    if points is not None and 0 < keep < len(points):
        subset = randperm(len(points), generator)[:keep]
        points = points[subset]
        point_colors = None if point_colors is None else point_colors[subset]
    if points is None:
        lo, hi = data.scene_box[0].cpu(), data.scene_box[1].cpu()
        points = lo + (hi - lo) * rand((int(n_init), 3), generator)
    points = points.float().to(data.images.device)
    mode = str(init_colors)
    if mode == "views":
        colors = colors_from_views(points, data.images[data.train], data.cameras[data.train])
    elif mode == "points":
        colors = point_colors
        if colors is None:
            raise UserError(f"init_colors=points: data '{data_name}' has no point colours (use views or grey)")
    elif mode != "grey":
        raise UserError(f"init_colors must be one of {', '.join(INIT_COLORS)}, got {mode!r}")
    model = init_from_points(points, colors, opacity=float(opacity), isotropic=bool(isotropic) and not surfels,
                             scale_factor=float(scale_factor)).to(points.device)
    if surfels:
        q = randn((model.num, 4), generator, points.device)
        model.quats.data = q / q.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        model.log_scales.data[:, 2] = model.log_scales.data[:, 0] + math.log(SURFEL_THICKNESS)
    if float(max_coverage) > 0:            # bounded start-up cost (0: the scales as initialised)
        views = data.train[torch.linspace(0, len(data.train) - 1, min(16, len(data.train))).long()]
        if not surfels and getattr(raw, "points", None) is not None and not data.background_known:  # a photo capture
            model = cover_views(model, data.images[views], data.cameras[views], float(max_coverage))
        else:
            model.log_scales.data = shrink_to_coverage(model.means, model.log_scales, model.quats,
                                                       torch.sigmoid(model.opacity_logits), data.cameras[views],
                                                       float(max_coverage))
    return model


def scene_extent(cams, margin: float) -> float:
    """``margin`` x the largest distance of the (training) cameras from their centroid (3DGS)."""
    centres = cams.centers()
    return float(margin) * float((centres - centres.mean(0)).norm(dim=-1).max())


def splat_optimizer(model: GaussianModel, background: torch.nn.ParameterDict, lr: Mapping[str, float],
                    extent: float, adam_eps: float, lr_decay_steps: int) -> Tuple[torch.optim.Optimizer, torch.optim.lr_scheduler.LambdaLR]:
    """Adam over the splats' parameter groups (named as the strategies expect: ``means`` first, at
    ``lr.means`` x ``extent`` decayed to ``lr.means_final`` over ``lr_decay_steps``; ``scales``,
    ``quats``, ``opacity``, ``sh_dc``, ``sh_rest``; ``background`` when it is learnt) and the
    LambdaLR of the decay."""
    groups = [("means", model.means, float(lr["means"]) * extent), ("scales", model.log_scales, float(lr["scales"])),
              ("quats", model.quats, float(lr["quats"])), ("opacity", model.opacity_logits, float(lr["opacity"])),
              ("sh_dc", model.sh_dc, float(lr["sh_dc"])), ("sh_rest", model.sh_rest, float(lr["sh_rest"]))]
    if background["rgb"].requires_grad:
        groups.append(("background", background["rgb"], float(lr["background"])))
    # fused: one vectorised pass per parameter for the whole update
    opt = torch.optim.Adam([{"params": [p], "lr": r, "name": n} for n, p, r in groups], eps=float(adam_eps),
                           fused=True)
    decay = exponential(float(lr["means_final"]) / float(lr["means"]), int(lr_decay_steps))
    return opt, torch.optim.lr_scheduler.LambdaLR(opt, [decay] + [lambda s: 1.0] * (len(groups) - 1))


class SplatSteps:
    """The per-step work both splat tasks share (see the module docstring).

    Args: model, optimiser, strategy (built, initialised); train_views (T,) indices; images
        (V, H, W, 3); generator; ssim_lambda; sh_degree, sh_every.
    ``info`` is the strategy's bookkeeping;
    ``step_times`` (wall, CPU seconds per step) is a list a task may checkpoint.
    """

    def __init__(self, model, optimizer, strategy, train_views: torch.Tensor, images: torch.Tensor,
                 generator: Optional[torch.Generator], ssim_lambda: float, sh_degree: int, sh_every: int):
        self.model, self.opt, self.strategy = model, optimizer, strategy
        self.train_views, self.images, self.generator = train_views, images, generator
        self.ssim_lambda, self.sh_degree, self.sh_every = float(ssim_lambda), int(sh_degree), int(sh_every)
        H, W = images.shape[1:3]
        self.info: Dict[str, object] = {"width": W, "height": H}
        self.step_times: List[Tuple[float, float]] = []

    def degree(self, step: int) -> int:
        """The SH degree at ``step``: one more every ``sh_every`` steps up to ``sh_degree``."""
        return min(self.sh_degree, step // self.sh_every)

    def begin(self) -> int:
        """Start timing a step; returns the training view it renders (drawn at random)."""
        self.info["t0"], self.info["c0"] = time.perf_counter(), time.process_time()
        return int(self.train_views[int(randint(0, len(self.train_views), (1,), self.generator))])

    def photometric(self, pred: torch.Tensor, view: int) -> Tuple[torch.Tensor, torch.Tensor]:
        """(loss, L1) of a rendered (H, W, 3) image against the view's: ``L1 + ssim_lambda (1 - SSIM)``."""
        target = self.images[view]
        l1 = (pred - target).abs().mean()
        return (l1 + self.ssim_lambda * (1 - ssim(pred, target)) if self.ssim_lambda > 0 else l1), l1

    def finish(self, loss: torch.Tensor, out: Dict[str, torch.Tensor], step: int) -> torch.Tensor:
        """The loss plus the strategy's regulariser; hands the render's screen-space bookkeeping
        (``means2d``, ``radii``) to the strategy before the backward pass."""
        reg = self.strategy.regularization(self.model)
        self.info.update(means2d=out["means2d"], radii=out["radii"])
        self.strategy.step_pre_backward(self.model, self.opt, step, self.info)
        return loss if reg is None else loss + reg

    def steps_left(self, step: int, iters: int, budget: TimeBudget) -> int:
        """Steps after ``step`` to ``iters``, or fewer where the time ``budget`` ends the run sooner at
        the mean wall seconds of the latest 50 steps (:meth:`TimeBudget.steps_that_fit`)."""
        left = int(iters) - (step + 1)
        fit = budget.steps_that_fit([t for t, _ in self.step_times[-50:]])
        return left if fit is None else min(left, fit)

    def after_step(self, step: int, steps_left: int) -> Dict[str, float]:
        """After the optimiser step: the strategy's densification (``steps_left``: steps the run still
        takes, so that it skips work the run would not profit from); records the step's seconds and
        returns the strategy's figures to log."""
        self.info["steps_left"] = steps_left
        logs = self.strategy.step_post_backward(self.model, self.opt, step, self.info, self.generator)
        self.step_times.append((time.perf_counter() - self.info["t0"], time.process_time() - self.info["c0"]))
        return logs

    def after_step_hook(self, iters: int, budget: TimeBudget, logger) -> Callable[[int], None]:
        """The loop's ``after_step(step)``: :meth:`after_step` with the steps still to come (to ``iters``,
        or fewer where the ``budget`` ends the run sooner, :meth:`steps_left`), the strategy's figures
        logged as ``strategy/<name>`` at ``step + 1`` through ``logger.log_scalars``."""
        def after_step(step: int) -> None:
            logs = self.after_step(step, self.steps_left(step, int(iters), budget))
            if logs:
                logger.log_scalars({f"strategy/{k}": v for k, v in logs.items()}, step + 1)
        return after_step

    def step_cost(self, first: int = 100) -> Dict[str, float]:
        """Mean wall and CPU (process) seconds per step over the first ``first`` steps and the rest."""
        out = {}
        for name, part in (("first_100", self.step_times[:first]), ("after_100", self.step_times[first:])):
            out[f"seconds_per_step_{name}"] = round(sum(t[0] for t in part) / max(1, len(part)), 5)
            out[f"cpu_seconds_per_step_{name}"] = round(sum(t[1] for t in part) / max(1, len(part)), 5)
        return out


@torch.no_grad()
def evaluate_views(render: Callable[[int], Dict[str, torch.Tensor]], views: Sequence[int], images: torch.Tensor,
                   depth_range: Tuple[float, float], depth_key: str = "expected_depth"):
    """Render ``views`` one by one with ``render(view) -> {"color" (1, H, W, 3), depth_key, "alpha"}``:
    predictions (V, H, W, 3), targets, a panel of the first view (prediction | truth | error | depth
    over ``depth_range``) and ``{"psnr", "ssim"}`` over all of them."""
    outs = [render(int(i)) for i in views]
    pred = torch.cat([o["color"] for o in outs]).clamp(0, 1)
    target = images[torch.as_tensor(views).to(images.device)]
    depth = colorize_depth(outs[0][depth_key][0], *depth_range, mask=outs[0]["alpha"][0] > 0.5)
    panel = side_by_side([pred[0], target[0], error_map(pred[0], target[0]), depth])
    return pred, target, panel, {"psnr": float(psnr(pred, target)), "ssim": float(ssim(pred, target))}


def write_splat_outputs(ctx, model: GaussianModel, step: int, pred: torch.Tensor, target: torch.Tensor,
                        panel: torch.Tensor, test: Mapping[str, float], progress_frames: List[torch.Tensor],
                        fps: float) -> Dict[str, float]:
    """The end of a splat run: the test figures (rounded to 4 decimals) logged at ``step`` with the
    ``panel``; ``test_views.gif`` (predictions (V, H, W, 3) beside their ``target``, at ``fps`` / 4),
    ``progress.gif`` (the uint8 (H, W, 3) validation ``progress_frames``, at ``fps``; none without
    frames) and ``point_cloud.ply`` (3DGS layout) in the run folder of ``ctx``. Returns the rounded
    test figures."""
    test = {k: round(v, 4) for k, v in test.items()}
    log_test(ctx, test, step, images={"pred_truth_error_depth": panel})
    save_gif(ctx.path("test_views.gif"), torch.cat([pred, target], 2), fps=float(fps) / 4)
    if progress_frames:
        save_gif(ctx.path("progress.gif"), torch.stack(progress_frames).float() / 255.0, fps=float(fps))
    save_gaussian_ply(ctx.path("point_cloud.ply"), **model.tensors())
    return test
