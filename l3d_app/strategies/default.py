"""``strategy=default``: 3DGS adaptive density control (Kerbl et al. 2023), schedule included.

Over the steps ``<= until`` it accumulates, per splat, the norm of the screen-space (NDC)
gradient of its projected centre over the views in which it is visible. Every ``every``
steps from ``start`` on, splats whose average exceeds ``grad_threshold`` are cloned (max
scale ``<= percent_dense * extent``) or split into two children sampled from the parent
(scales / ``SPLIT_SHRINK``); transparent (``< min_opacity``), too large in the world
(``> max_world_scale * extent``) and, after the first opacity reset (from the start
without resets), too large on screen (``> max_screen_size`` px) splats are pruned; the
count never passes ``max_gaussians`` (the strongest gradients win). Every
``opacity_reset_every`` steps (0: never) opacities are clamped to ``reset_value``.
"""

from __future__ import annotations

import math
from typing import Any, Dict, Optional

import torch

from l3d_app.errors import UserError
from l3d_app.models.gaussians import PARAM_NAMES
from l3d_app.registry import STRATEGIES
from l3d_app.render.gaussians.rasterize import quaternion_to_rotation
from l3d_app.runtime.horizon import scheduled_event
from l3d_app.runtime.random import randn
from l3d_app.strategies.base import Strategy
from l3d_app.strategies.ops import replace_rows, zero_moments

SPLIT_SHRINK = 1.6      # 3DGS: a split child's scales are the parent's / 1.6 (0.8 * 2 children)


@STRATEGIES.register("default")
class DefaultStrategy(Strategy):
    """3DGS density control.

    Args:
        start, until, every: densify every ``every`` steps in ``[start, until]`` (1-based
            step counts: ``start=100`` is after the 100th step).
        grad_threshold: mean NDC screen-space gradient norm above which a splat densifies.
        percent_dense: clone if max scale <= this * scene extent, else split.
        min_opacity: prune below this opacity.
        max_screen_size: prune splats with a 2D radius above this (px; 0 = off).
        max_world_scale: prune splats larger than this fraction of the extent (0 = off).
        opacity_reset_every: steps between opacity resets (0 = never); reset_value: the clamp.
        reset_min_steps_left: a reset is skipped when fewer steps than this are left in the run
            (``info["steps_left"]``, on the nominal schedule; absent: never skipped): a reset costs
            15-20 dB that take about 100 steps to recover.
        densify_min_steps_left: a densification is skipped when fewer steps than this are left
            (the same ``steps_left``; 0: never skipped): its new splats (clones, split halves) would
            be scored nearly untrained when a time budget stops the run just after it.
        max_gaussians: cap on the count.

    The steps above are those of the task's schedule (``info["schedule"]``,
    :mod:`l3d_app.strategies.base`): by step by default.
    """

    def __init__(self, start: int = 100, until: int = 3000, every: int = 100, grad_threshold: float = 1e-4,
                 percent_dense: float = 0.01, min_opacity: float = 0.005, max_screen_size: float = 20.0,
                 max_world_scale: float = 0.1, opacity_reset_every: int = 1000, reset_value: float = 0.01,
                 max_gaussians: int = 100_000, reset_min_steps_left: int = 300, densify_min_steps_left: int = 100):
        super().__init__()
        if int(every) <= 0:
            raise UserError(f"strategy.every must be > 0, got {every}")
        self.start, self.until, self.every = int(start), int(until), int(every)
        self.grad_threshold = float(grad_threshold)
        self.percent_dense = float(percent_dense)
        self.min_opacity = float(min_opacity)
        self.max_screen_size = float(max_screen_size)
        self.max_world_scale = float(max_world_scale)
        self.opacity_reset_every = int(opacity_reset_every)
        self.reset_value = float(reset_value)
        self.reset_min_steps_left = int(reset_min_steps_left)
        self.densify_min_steps_left = int(densify_min_steps_left)
        self.max_gaussians = int(max_gaussians)
        self.grad_accum = self.count = self.max_radii = None

    # -- state -------------------------------------------------------------------------------
    def state_dict(self) -> Dict[str, Optional[torch.Tensor]]:
        """The accumulators (checkpointed so that a resumed run densifies identically)."""
        return {"grad_accum": self.grad_accum, "count": self.count, "max_radii": self.max_radii}

    def load_state_dict(self, state: Dict[str, Optional[torch.Tensor]]) -> None:
        for k in ("grad_accum", "count", "max_radii"):
            v = state.get(k)
            setattr(self, k, None if v is None else v.clone())

    def reset_stats(self, n: int, device) -> None:
        self.grad_accum = torch.zeros(n, device=device)
        self.count = torch.zeros(n, device=device)
        self.max_radii = torch.zeros(n, device=device)

    # -- hooks ---------------------------------------------------------------------------------
    def step_post_backward(self, model, optimizer, step: int, info: Dict[str, Any],
                           generator: Optional[torch.Generator] = None) -> Dict[str, float]:
        previous, done = self.schedule(step, info)      # (step, step + 1) unless the task's schedule says otherwise
        until = self.until
        logs: Dict[str, float] = {}
        grad = info["means2d"].grad
        if previous >= until or grad is None:
            return logs
        self.accumulate(grad, info["radii"].detach(), int(info["width"]), int(info["height"]))
        if (scheduled_event(previous, done, self.every, first=self.start, last=until)
                and (self.densify_min_steps_left <= 0
                     or info.get("steps_left", self.densify_min_steps_left) >= self.densify_min_steps_left)):
            r = self.densify_and_prune(model, optimizer, generator, prune_screen=done > self.opacity_reset_every)
            logs = {k: float(r[k]) for k in ("n", "cloned", "split", "pruned")}
        if (self.opacity_reset_every > 0 and scheduled_event(previous, done, self.opacity_reset_every, last=until)
                and info.get("steps_left", self.reset_min_steps_left) >= self.reset_min_steps_left):
            self.reset_opacity(model, optimizer)
        return logs

    # -- the operations ------------------------------------------------------------------------
    @torch.no_grad()
    def accumulate(self, means2d_grad: torch.Tensor, radii: torch.Tensor, width: int, height: int) -> None:
        """Add one step's screen-space gradients: means2d_grad (B, N, 2) px, radii (B, N) px."""
        n = means2d_grad.shape[1]
        if self.grad_accum is None or self.grad_accum.shape[0] != n:
            self.reset_stats(n, means2d_grad.device)
        scale = means2d_grad.new_tensor([0.5 * width, 0.5 * height])
        norm = (means2d_grad * scale).norm(dim=-1)
        vis = radii > 0
        self.grad_accum += (norm * vis).sum(0)
        self.count += vis.sum(0)
        self.max_radii = torch.maximum(self.max_radii, radii.max(0).values)

    @torch.no_grad()
    def densify_and_prune(self, model, optimizer, generator: Optional[torch.Generator] = None,
                          prune_screen: bool = False) -> Dict[str, int]:
        """One densification round; returns counts {cloned, split, pruned, n, was}."""
        if self.grad_accum is None or self.grad_accum.shape[0] != model.num:
            return {"cloned": 0, "split": 0, "pruned": 0, "n": model.num, "was": model.num}
        grads = self.grad_accum / self.count.clamp_min(1)
        max_scale = torch.exp(model.log_scales).max(-1).values
        high = grads >= self.grad_threshold
        room = max(0, self.max_gaussians - model.num)
        if int(high.sum()) > room // 2:                 # cap: keep the strongest only
            idx = torch.nonzero(high).reshape(-1)
            keep = idx[torch.argsort(grads[idx], descending=True)[: room // 2]]
            high = torch.zeros_like(high)
            high[keep] = True
        small = max_scale <= self.percent_dense * self.extent
        clone, split = high & small, high & ~small
        n0 = model.num
        # new splats: clones (same params), split children (2 per split, sampled inside)
        new = {name: [] for name in PARAM_NAMES}
        ci = torch.nonzero(clone).reshape(-1)
        for name in new:
            new[name].append(getattr(model, name)[ci])
        si = torch.nonzero(split).reshape(-1)
        if si.numel():
            s = torch.exp(model.log_scales[si]).repeat(2, 1)                # (2S, 3) or (2S, 1) isotropic
            noise = randn((s.shape[0], 3), generator, s.device)
            rot = quaternion_to_rotation(model.quats[si]).repeat(2, 1, 1)
            new["means"].append((rot @ (noise * s)[..., None])[..., 0] + model.means[si].repeat(2, 1))
            new["log_scales"].append(torch.log(s / SPLIT_SHRINK))
            for name in ("quats", "opacity_logits", "sh_dc", "sh_rest"):
                new[name].append(getattr(model, name)[si].repeat(2, *([1] * (getattr(model, name).dim() - 1))))
        added = {k: torch.cat(v) for k, v in new.items()}
        n_add = added["means"].shape[0]
        # prune: split parents, transparent, too large
        opac = torch.sigmoid(model.opacity_logits)
        prune = split | (opac < self.min_opacity)
        if self.max_world_scale > 0:
            prune |= max_scale > self.max_world_scale * self.extent
        if prune_screen and self.max_screen_size > 0:
            prune |= self.max_radii > self.max_screen_size
        keep = torch.cat([~prune, torch.ones(n_add, dtype=torch.bool, device=prune.device)])
        replace_rows(model, optimizer, added, keep)
        self.reset_stats(model.num, model.means.device)
        return {"cloned": int(ci.numel()), "split": int(si.numel()), "pruned": int(prune.sum()), "n": model.num,
                "was": n0}

    @torch.no_grad()
    def reset_opacity(self, model, optimizer) -> None:
        """Clamp opacities to at most ``reset_value`` (3DGS reset) and zero their Adam moments."""
        logit = math.log(self.reset_value / (1 - self.reset_value))
        model.opacity_logits.data.clamp_(max=logit)
        zero_moments(optimizer, model.opacity_logits, None)
