"""A short radiance-field fit before a surface task: which stretch of each training ray is empty.

``volsdf`` with ``free_space.steps`` > 0 calls :func:`fit_free_rays` before its own training: a
``free_space.model`` radiance field (default ``grid_field``) sampled by ``free_space.sampler``
(default ``occupancy``) is fitted to the training pixels for ``free_space.steps`` steps of
``free_space.batch_rays`` rays (colour MSE, ``free_space.optim``) through the shared training loop
(TensorBoard ``free_space/*``, no checkpoint), then every training ray is rendered once and its free
segment kept (at most ``free_space.max_rays`` of them, a random subset: the read-off renders each
once): from the box entry to where the field's accumulated opacity first reaches
``free_space.opacity``, less ``free_space.margin`` (world units)
(:class:`~l3d_app.render.volume.free_space.FreeRays`). The rays' indices and distances are saved to ``free_space.pt``
in the run directory, so ``resume=true`` does not fit them again (with ``free_space.save_levels``, a
list of other opacity levels, also each ray's distance at those: a diagnosis aid for
bench/diagnose_free_space.py). With a ``time_budget`` the stage stops at :func:`stage_deadline`:
at most a third of the budget, and at most half of what the budget leaves after the task's predicted
final work; where that is too short the stage is skipped. ``free_space.w_front`` adds a front prior to
the stage's loss on the rays the images' alpha covers (:func:`fit_free_rays`).
"""

from __future__ import annotations

import time
from typing import Optional

import torch

from l3d_app.errors import UserError
from l3d_app.losses.free_space import termination_distance
from l3d_app.models.background import background_parameter
from l3d_app.registry import MODELS, SAMPLERS
from l3d_app.render.volume.free_space import FreeRays, free_distances
from l3d_app.render.volume.radiance import render_field_rays
from l3d_app.render.volume.samplers import ray_aabb
from l3d_app.runtime.budget import TimeBudget
from l3d_app.runtime.optim import build_optimizer
from l3d_app.runtime.random import randint, randperm
from l3d_app.runtime.training import LoopSpec, Trainable, train
from l3d_app.tasks.common import require_fade_end, require_nonnegative, require_positive

FILE = "free_space.pt"


def check_free_space_config(cfg) -> None:
    """One line, exit 2, before any data is read: the stage's knobs (``cfg`` = ``free_space``)."""
    named = {f"free_space.{k}": cfg.get(k) for k in ("steps", "auto_steps", "batch_rays", "opacity", "margin",
                                                      "margin_beta", "points", "weight", "ray_weight", "chunk",
                                                      "max_rays", "w_front")}
    steps = named["free_space.steps"]
    if steps != "auto" and (isinstance(steps, bool) or not isinstance(steps, (int, float)) or steps < 0):
        raise UserError(f"free_space.steps must be auto or a number >= 0, got {steps!r}")
    require_nonnegative(named, "free_space.auto_steps", "free_space.margin", "free_space.margin_beta",
                        "free_space.weight", "free_space.ray_weight", "free_space.max_rays", "free_space.w_front")
    require_positive(named, "free_space.batch_rays", "free_space.points", "free_space.chunk", "free_space.opacity")
    if str(cfg.get("proposal")) not in ("uniform", "surface"):
        raise UserError(f"free_space.proposal must be uniform or surface, got {cfg.get('proposal')!r}")
    cand, mix = cfg.get("candidates"), cfg.get("mix")
    if isinstance(cand, bool) or not isinstance(cand, int) or cand < 1:
        raise UserError(f"free_space.candidates must be an integer >= 1, got {cand!r}")
    if isinstance(mix, bool) or not isinstance(mix, (int, float)) or not 0 <= mix < 1:
        raise UserError(f"free_space.mix must lie in [0, 1), got {mix!r}")
    if str(cfg.get("loss")) not in ("occupancy", "density", "outside"):
        raise UserError(f"free_space.loss must be occupancy, density or outside, got {cfg.get('loss')!r}")
    rmb = cfg.get("ray_margin_beta")
    if rmb is not None and (isinstance(rmb, bool) or not isinstance(rmb, (int, float)) or rmb < 0):
        raise UserError(f"free_space.ray_margin_beta must be null or a number >= 0, got {rmb!r}")
    rm = cfg.get("ray_margin")
    if rm is not None and (isinstance(rm, bool) or not isinstance(rm, (int, float))
                           or not 0 <= rm <= float(cfg.get("margin", 0))):
        raise UserError(f"free_space.ray_margin must be null or a number in [0, free_space.margin], got {rm!r}")
    if str(cfg.get("ray_loss", "opacity")) not in ("opacity", "log_depth"):
        raise UserError(f"free_space.ray_loss must be opacity or log_depth, got {cfg.get('ray_loss')!r}")
    if str(cfg.get("ray_cut", "none")) not in ("none", "multi_view"):
        raise UserError(f"free_space.ray_cut must be none or multi_view, got {cfg.get('ray_cut')!r}")
    require_fade_end(cfg.get("until"), "free_space.until")
    extra = cfg.get("save_levels")
    if extra is not None and (isinstance(extra, (str, bytes)) or not hasattr(extra, "__iter__") or any(
            isinstance(x, bool) or not isinstance(x, (int, float)) or not 0 < x <= 1 for x in extra)):
        raise UserError(f"free_space.save_levels must be a list of opacity levels in (0, 1], got {extra!r}")
    if float(cfg.opacity) > 1.0:
        raise UserError(f"free_space.opacity must lie in (0, 1] (an accumulated opacity), got {cfg.opacity}")


def resolve_free_space(cfg):
    """A copy of ``cfg`` (= ``free_space``, checked) with ``steps`` a number: ``auto`` gives ``auto_steps``
    with either density (the stage was chosen with VolSDF's Laplace density; NeuS without it kept the
    mound over ``ground``'s objects: docs/measured/volsdf.md)."""
    from omegaconf import OmegaConf
    out = OmegaConf.create(OmegaConf.to_container(cfg, resolve=True))
    if out.steps == "auto":
        out.steps = int(out.auto_steps)
    return out


MIN_STAGE_SECONDS = 90.0
"""A stage the budget gives less wall time than this is skipped. Not tuned: the shortest full 600-step
stage measured on the development scenes took 79 s (its first ~35 s the occupancy sampler's warm-up,
and after the fit a read-off of up to 2M training rays: 42 s on `dev256` after a 32-step fit), rounded up; a first setting of 30 s stopped the stage
on `dev256` inside its warm-up (32 steps) and still paid the read-off (docs/measured/volsdf.md)."""


def stage_deadline(time_budget: float, elapsed: float, eval_seconds: Optional[float], evals_after: float,
                   reserve: float, minimum: float = MIN_STAGE_SECONDS) -> Optional[float]:
    """The task's elapsed wall seconds at which the free-space stage must stop.

    Args:
        time_budget: the task's budget (s); <= 0: none, the stage is not limited (returns 0.0).
        elapsed: the task's wall seconds so far.
        eval_seconds: one validation render of the initial field (s), the dearest an evaluation gets
            (a fuzzy surface skips no empty ray); None: unknown, only the third applies.
        evals_after: the rendering after training in validations (:func:`~l3d_app.runtime.budget.views_in_validations`).
        reserve: the task's other seconds after training (artefacts).
    Returns:
        ``min(budget / 3, elapsed + (budget - elapsed - final) / 2)`` with ``final = eval_seconds x
        (1 + evals_after) + reserve`` (the last validation, then the test views): the stage
        takes at most half of what the final work leaves; None (skip the stage) when that leaves it
        under ``minimum`` seconds.
    """
    budget = TimeBudget(time_budget, reserve, clock=lambda: elapsed, evals_after=evals_after)
    return budget.stage_deadline(eval_seconds, minimum)


def front_weight(cfg, covered: Optional[torch.Tensor]) -> float:
    """``free_space.w_front`` (``cfg`` = ``free_space``) where the images' alpha says which rays end on a
    surface (``covered`` not None), 0 where it is unknown (RGB captures): the prior has no rays to act on."""
    return float(cfg.get("w_front") or 0.0) if covered is not None else 0.0


def fit_free_rays(cfg, ctx, data, box, origins: torch.Tensor, dirs: torch.Tensor, colors: torch.Tensor,
                  learn_background, deadline: float, resume: bool,
                  covered: Optional[torch.Tensor] = None) -> Optional[FreeRays]:
    """Fit the stage's radiance field to the training rays (``origins``, unit ``dirs``, ``colors``
    (R, 3)) and return their free segments; None when interrupted. ``cfg`` = ``free_space``;
    ``learn_background`` as the task's (one RGB behind the box when the data does not know it);
    ``deadline``: the task's elapsed seconds where the fit stops (:func:`stage_deadline`; 0: none);
    ``covered`` (R,) bool: the images' alpha says the ray ends on a surface (None: unknown, and
    ``free_space.w_front`` is off, logged), for ``free_space.w_front`` (x the batch's covered rays' mean
    :func:`termination_distance` over the box diagonal: the front-most density the images allow)."""
    w_front = front_weight(cfg, covered)
    if float(cfg.get("w_front") or 0.0) > 0 and covered is None:
        ctx.logger.text("free_space", "w_front: the data has no alpha (which rays end on a surface is unknown): off")
    path = ctx.path(FILE)
    if resume and path.exists():     # the fitted run's rays and their distances
        saved = torch.load(path, map_location="cpu", weights_only=True)
        keep = saved["index"].to(ctx.device)
        return FreeRays.from_distances(origins[keep], dirs[keep], saved["distance"].to(ctx.device), box,
                                       float(cfg.margin), keep)
    t_start = time.perf_counter()
    model = MODELS.build(cfg.model, scene_box=box).to(ctx.device)
    sampler = SAMPLERS.build(cfg.sampler, scene_box=box).to(ctx.device)
    background = background_parameter(learn_background, data)
    params = list(model.parameters()) + ([background["rgb"]] if background["rgb"].requires_grad else [])
    opt, scheds = build_optimizer(cfg.optim, params, int(cfg.steps))
    trainable = Trainable({"field": model, "background": background}, opt, extra={"sampler": sampler},
                          schedulers=scheds)
    n, batch = origins.shape[0], int(cfg.batch_rays)
    lo, hi = torch.tensor(box[0], device=ctx.device), torch.tensor(box[1], device=ctx.device)
    diagonal = float((hi - lo).norm())

    def step_fn(step: int):
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

    result = train(ctx, trainable, step_fn, LoopSpec(int(cfg.steps), desc="free space (radiance field)",
                                                     log_prefix="free_space", checkpoint=False),
                   budget=TimeBudget.of(ctx, seconds=float(deadline), reserve=0.0))
    if result.interrupted:
        return None
    model.eval()
    keep = torch.arange(n, device=ctx.device)
    if 0 < int(cfg.max_rays) < n:    # a random subset of the rays: the read-off costs a render of each
        keep = torch.sort(randperm(n, ctx.generator, ctx.device)[: int(cfg.max_rays)])[0]
    with torch.no_grad():
        sampler.update(result.step, model, ctx.generator, force=True)
        extra = [float(x) for x in (cfg.get("save_levels") or [])]
        dist = free_distances(model, sampler, origins[keep], dirs[keep], [float(cfg.opacity)] + extra, int(cfg.chunk))
    free = FreeRays.from_distances(origins[keep], dirs[keep], dist[:, 0], box, float(cfg.margin), keep)
    saved = {"index": keep.cpu(), "distance": dist[:, 0].cpu()}
    if extra:   # for diagnosis (bench/diagnose_free_space.py): the same rays' distances at other levels
        saved.update(levels=torch.tensor(extra), level_distances=dist[:, 1:].cpu())
    torch.save(saved, path)
    ctx.logger.text("free_space", f"radiance field: {result.step} steps; {len(free)} of {len(keep)} training rays "
                                  f"have a free segment, mean length {float((free.far - free.near).mean()):.3f}; "
                                  f"{time.perf_counter() - t_start:.1f} s")
    return free
