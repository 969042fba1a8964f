"""Optimisers with their LR schedules (registry ``OPTIMIZERS``, config group ``optim=``).

Each entry is ``fn(params, iters, lr, ...) -> (optimizer, [schedulers])``: ``params`` is an
iterable of parameters or of Adam parameter groups (a group may carry its own ``lr``), and
every schedule is in STEPS (never epochs, whose length depends on the dataset), written as a
``LambdaLR`` factor of the step (:mod:`~l3d_app.runtime.lr_schedules`) so that, given a
:class:`~l3d_app.runtime.horizon.Horizon`, it ends where a time budget ends the run. The
training loop steps the schedulers (``Trainable.schedulers``). Build from a config with
:func:`build_optimizer`.
"""

from __future__ import annotations

from typing import Any, Iterable, List, Mapping, Optional, Tuple

import torch

from l3d_app.errors import UserError
from l3d_app.registry import OPTIMIZERS
from l3d_app.runtime.horizon import Horizon
from l3d_app.runtime.lr_schedules import exponential, on_horizon, step_decay, warmup_cosine

Built = Tuple[torch.optim.Optimizer, List[Any]]


def build_optimizer(cfg: Mapping[str, Any], params: Iterable, iters: int,
                    horizon: Optional[Horizon] = None) -> Built:
    """``OPTIMIZERS.build(cfg, params=..., iters=...)``: the optimiser and its schedulers;
    with a ``horizon`` every schedule is read at ``horizon.nominal(step)`` (the training loop
    keeps it at the step a time budget will stop the run)."""
    opt, scheds = OPTIMIZERS.build(cfg, params=params, iters=int(iters))
    if horizon is not None:
        for sched in scheds:
            sched.lr_lambdas = [on_horizon(f, horizon) for f in sched.lr_lambdas]
    return opt, scheds


def _factor(opt: torch.optim.Optimizer, factor) -> List[Any]:
    return [torch.optim.lr_scheduler.LambdaLR(opt, factor)]


def _adam(params, lr: float, eps: float) -> torch.optim.Adam:
    if not float(lr) > 0 or not float(eps) > 0:
        raise UserError(f"lr and eps must be > 0, got lr={lr}, eps={eps}")
    return torch.optim.Adam(params, lr=float(lr), eps=float(eps))


@OPTIMIZERS.register("adam")
def adam(params, iters: int, lr: float = 1e-3, eps: float = 1e-8) -> Built:
    """Adam at a constant rate."""
    return _adam(params, lr, eps), []


@OPTIMIZERS.register("adam_step")
def adam_step(params, iters: int, lr: float = 1e-3, eps: float = 1e-8, decay: float = 0.33,
              decay_every: int = 1000) -> Built:
    """Adam, the rate multiplied by ``decay`` every ``decay_every`` steps."""
    if int(decay_every) < 1 or not 0 < float(decay) <= 1:
        raise UserError(f"adam_step needs decay_every >= 1 and decay in (0, 1], got {decay_every}, {decay}")
    opt = _adam(params, lr, eps)
    return opt, _factor(opt, step_decay(float(decay), int(decay_every)))


@OPTIMIZERS.register("adam_exp")
def adam_exp(params, iters: int, lr: float = 1e-3, eps: float = 1e-8, final_factor: float = 0.01) -> Built:
    """Adam, the rate decayed exponentially to ``lr * final_factor`` at step ``iters``."""
    if not float(final_factor) > 0:
        raise UserError(f"final_factor must be > 0, got {final_factor}")
    opt = _adam(params, lr, eps)
    return opt, _factor(opt, exponential(float(final_factor), int(iters)))


@OPTIMIZERS.register("adam_cosine")
def adam_cosine(params, iters: int, lr: float = 1e-3, eps: float = 1e-8, final_ratio: float = 0.05) -> Built:
    """Adam, half a cosine from ``lr`` to ``lr * final_ratio`` over ``iters`` steps."""
    opt = _adam(params, lr, eps)
    return opt, _factor(opt, warmup_cosine(0, 0, max(1, int(iters)), float(final_ratio)))


@OPTIMIZERS.register("warmup_cosine")
def adam_warmup_cosine(params, iters: int, lr: float = 1e-3, eps: float = 1e-8, warmup_steps: int = 50,
                       final_ratio: float = 0.05) -> Built:
    """Adam, linear warm-up over ``warmup_steps`` then a cosine to ``lr * final_ratio`` at ``iters``
    (:func:`~l3d_app.runtime.lr_schedules.warmup_cosine`; one factor for every group)."""
    opt = _adam(params, lr, eps)
    warm = int(warmup_steps)
    return opt, _factor(opt, warmup_cosine(warm, warm, int(iters), float(final_ratio)))
