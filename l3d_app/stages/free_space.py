"""Known free space: a short radiance-field fit before a surface method, which stretch of each training ray is empty.

A radiance field is not bound to one surface: where the images show the far side of a gap it puts its
density there, and the stretch of each training ray before the density starts is empty. The stage fits
one (``model``, default ``grid_field``, sampled by ``sampler``, default ``occupancy``; Adam at ``lr``) to
the training pixels for ``steps`` steps of ``batch_rays`` rays (colour MSE, TensorBoard ``free_space/*``,
no checkpoint), then renders every training ray once (at most ``max_rays`` of them, a random subset) and
keeps its free segment, from the box entry to where the field's accumulated opacity first reaches
``opacity``, less ``margin`` (:class:`~l3d_app.render.volume.free_space.FreeRays`): the product
``free_rays`` that the loss terms ``free_points`` and ``free_rays`` read (:mod:`~l3d_app.losses.free_space`).
The rays' indices and distances are saved to ``free_space.pt`` in the run directory, so a resumed run
reads them back. ``w_front`` adds a front prior to the fit on the rays the images' alpha covers: where a
uniform face does not pin the depth, the density sits in front, so no stretch ends behind the surface.
With a time budget the stage stops at the budget's
:meth:`~l3d_app.runtime.budget.TimeBudget.stage_deadline`, or is skipped when that leaves it under
:data:`MIN_STAGE_SECONDS`.
"""

from __future__ import annotations

import time
from typing import Any, Dict, Mapping, Optional

import torch

from l3d_app.errors import UserError
from l3d_app.losses.free_space import termination_distance
from l3d_app.registry import MODELS, SAMPLERS, STAGES
from l3d_app.render.volume.free_space import FreeRays, free_distances
from l3d_app.render.volume.radiance import render_field_rays
from l3d_app.render.volume.samplers import ray_aabb
from l3d_app.runtime.budget import TimeBudget
from l3d_app.runtime.optim import build_optimizer
from l3d_app.runtime.random import randint, randperm
from l3d_app.runtime.training import LoopSpec, Trainable, train
from l3d_app.stages.base import MethodState, Stage

FILE = "free_space.pt"
MIN_STAGE_SECONDS = 90.0
"""A free-space stage that the time budget gives less wall time than this is skipped: the shortest
600-step free-space stage measured on the development scenes took 79 s (its first ~35 s the occupancy
sampler's warm-up, then the read-off of up to 2M rays), rounded up (docs/measured/volsdf.md)."""


@STAGES.register("free_space")
class FreeSpaceStage(Stage):
    """The stage of the module docstring; its product is ``free_rays`` (skipped when no weighted loss term
    reads it).

    Args:
        steps: the fit's steps (0: off). batch_rays: rays per step.
        opacity: the accumulated opacity in (0, 1] at which a ray's free stretch ends ...
        margin: ... less this (world units).
        w_front: the front prior's weight (x the covered rays' mean expected stopping distance over the box
            diagonal, :func:`~l3d_app.losses.free_space.termination_distance`; off without alpha).
        max_rays: read off at most this many training rays (0: all). chunk: rays per read-off render.
        model, sampler: the radiance field's ``MODELS`` / ``SAMPLERS`` configs (None: ``grid_field`` /
            ``occupancy`` with their defaults). lr: its Adam step (eps 1e-15 for the grid's table).
    """

    produces = "free_rays"

    def __init__(self, steps: int = 600, batch_rays: int = 2048, opacity: float = 0.3, margin: float = 0.05,
                 w_front: float = 0.01, max_rays: int = 2_000_000, chunk: int = 16384,
                 model: Optional[Mapping[str, Any]] = None, sampler: Optional[Mapping[str, Any]] = None,
                 lr: float = 0.01):
        for key, value in (("steps", steps), ("max_rays", max_rays)):
            if isinstance(value, bool) or not isinstance(value, int) or value < 0:
                raise UserError(f"free_space {key} must be an integer >= 0, got {value!r}")
        for key, value in (("batch_rays", batch_rays), ("chunk", chunk)):
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise UserError(f"free_space {key} must be a positive integer, got {value!r}")
        for key, value in (("margin", margin), ("w_front", w_front), ("lr", lr)):
            if isinstance(value, bool) or not isinstance(value, (int, float)) or value < 0:
                raise UserError(f"free_space {key} must be a number >= 0, got {value!r}")
        if isinstance(opacity, bool) or not isinstance(opacity, (int, float)) or not 0 < opacity <= 1:
            raise UserError(f"free_space opacity must lie in (0, 1] (an accumulated opacity), got {opacity!r}")
        self.steps, self.batch_rays, self.max_rays, self.chunk = steps, batch_rays, max_rays, chunk
        self.opacity, self.margin, self.w_front, self.lr = float(opacity), float(margin), float(w_front), float(lr)
        self.model_cfg = dict(model or {"name": "grid_field"})
        self.sampler_cfg = dict(sampler or {"name": "occupancy"})
        self.free: Optional[FreeRays] = None
        self.skipped, self.seconds = False, 0.0

    def before_training(self, state: MethodState, ctx, budget: TimeBudget) -> bool:
        if self.steps <= 0 or self.produces not in state.needed:
            return True
        deadline = budget.stage_deadline(budget.eval_price, MIN_STAGE_SECONDS)
        if state.resuming:     # the saved stretches, or none where the run being resumed skipped its stage
            deadline = 0.0 if ctx.path(FILE).exists() else None
        price = "unknown" if budget.eval_price is None else f"{budget.eval_price:.1f} s"
        if deadline is None:
            self.skipped = True
            ctx.logger.text("free_space", f"skipped: time_budget {budget.seconds:g} s leaves it under "
                                          f"{MIN_STAGE_SECONDS:g} s after the predicted final work (a validation: "
                                          f"{price})")
            return True
        ctx.logger.text("free_space", f"stage until {deadline:.1f} s of the task (0: no limit; a validation: "
                                      f"{price})")
        with ctx.stopwatch.stage("free_space"):
            self.free = self.fit(state, ctx, deadline)
        self.seconds = ctx.stopwatch.stages.get("free_space", 0.0)
        if self.free is None:     # interrupted during the stage: nothing trained yet
            return False
        state.products[self.produces] = self.free
        return True

    def fit(self, state: MethodState, ctx, deadline: float) -> Optional[FreeRays]:
        """Fit the radiance field to the training rays and return their free segments (None when interrupted);
        ``deadline``: the task's elapsed seconds where the fit stops (0: none)."""
        rays, box = state.rays, state.box
        origins, dirs, colors, covered = rays.origins, rays.unit_dirs(), rays.rgb, rays.covered
        if state.resuming and ctx.path(FILE).exists():     # the fitted run's rays and their distances
            saved = torch.load(ctx.path(FILE), map_location="cpu", weights_only=True)
            keep = saved["index"].to(ctx.device)
            return FreeRays.from_distances(origins[keep], dirs[keep], saved["distance"].to(ctx.device), box,
                                           self.margin, keep)
        w_front = self.w_front if covered is not None else 0.0
        if self.w_front > 0 and covered is None:
            ctx.logger.text("free_space", "w_front: the data has no alpha (which rays end on a surface is unknown): "
                                          "off")
        t_start = time.perf_counter()
        model = MODELS.build(self.model_cfg, scene_box=box).to(ctx.device)
        sampler = SAMPLERS.build(self.sampler_cfg, scene_box=box).to(ctx.device)
        background = state.background()
        params = list(model.parameters()) + ([background["rgb"]] if background["rgb"].requires_grad else [])
        opt, scheds = build_optimizer({"name": "adam", "lr": self.lr, "eps": 1e-15}, params, self.steps)
        trainable = Trainable({"field": model, "background": background}, opt, extra={"sampler": sampler},
                              schedulers=scheds)
        n, batch, lo, hi = origins.shape[0], self.batch_rays, state.lo, state.hi
        diagonal = float((hi - lo).norm())

        def step_fn(step: int) -> Dict[str, torch.Tensor]:
            sampler.update(step, model, ctx.generator)
            idx = randint(0, n, (batch,), ctx.generator, ctx.device)
            out = render_field_rays(model, origins[idx], dirs[idx], sampler, perturb=True, generator=ctx.generator,
                                    background=background["rgb"].clamp(0, 1))
            logs = {"loss": ((out["color"] - colors[idx]) ** 2).mean(), "samples_per_ray": out["samples_per_ray"]}
            if w_front > 0:
                near, far, hit = ray_aabb(origins[idx], dirs[idx], lo, hi)
                cov = covered[idx] & hit
                front = (termination_distance(out["depth"], out["opacity"], near, far)[cov].mean() / diagonal
                         if bool(cov.any()) else out["depth"].sum() * 0.0)
                logs["loss"], logs["front"] = logs["loss"] + w_front * front, front.detach()
            return logs

        result = train(ctx, trainable, step_fn, LoopSpec(self.steps, desc="free space (radiance field)",
                                                         log_prefix="free_space", checkpoint=False),
                       budget=TimeBudget.of(ctx, seconds=float(deadline), reserve=0.0))
        if result.interrupted:
            return None
        model.eval()
        keep = torch.arange(n, device=ctx.device)
        if 0 < self.max_rays < n:    # a random subset of the rays: the read-off costs a render of each
            keep = torch.sort(randperm(n, ctx.generator, ctx.device)[: self.max_rays])[0]
        with torch.no_grad():
            sampler.update(result.step, model, ctx.generator, force=True)
            dist = free_distances(model, sampler, origins[keep], dirs[keep], self.opacity, self.chunk)
        free = FreeRays.from_distances(origins[keep], dirs[keep], dist, box, self.margin, keep)
        torch.save({"index": keep.cpu(), "distance": dist.cpu()}, ctx.path(FILE))
        ctx.logger.text("free_space", f"radiance field: {result.step} steps; {len(free)} of {len(keep)} training rays "
                                      f"have a free segment, mean length {float((free.far - free.near).mean()):.3f}; "
                                      f"{time.perf_counter() - t_start:.1f} s")
        return free

    def metrics(self) -> Dict[str, Any]:
        return {"free_space_seconds": round(self.seconds, 4), "free_space_skipped": self.skipped,
                "free_space_rays": 0 if self.free is None else len(self.free)}
