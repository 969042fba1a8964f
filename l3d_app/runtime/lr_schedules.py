"""Learning-rate factor schedules for ``torch.optim.lr_scheduler.LambdaLR``."""

from __future__ import annotations

import math
from typing import Callable


def warmup_cosine(warmup: int, decay_start: int, decay_end: int, final_ratio: float) -> Callable[[int], float]:
    """Factor of step ``i`` (0-based): ``min(warm-up, cosine)``.

    warm-up: ``min(1, (i + 1) / warmup)`` (1 when ``warmup`` <= 0); cosine: 1 until
    ``decay_start``, then half a cosine down to ``final_ratio`` at ``decay_end``, held after.
    ``final_ratio = 1`` gives warm-up then a constant rate.
    """
    warmup, start, span = int(warmup), int(decay_start), max(1, int(decay_end) - int(decay_start))
    final = float(final_ratio)

    def factor(i: int) -> float:
        warm = 1.0 if warmup <= 0 else min(1.0, (i + 1) / warmup)
        p = min(1.0, max(0.0, (i - start) / span))
        return min(warm, final + (1.0 - final) * 0.5 * (1.0 + math.cos(math.pi * p)))

    return factor


def step_decay(decay: float, every: int) -> Callable[[float], float]:
    """Factor ``decay ** floor(i / every)`` (``torch.optim.lr_scheduler.StepLR``'s closed form)."""
    decay, every = float(decay), max(1, int(every))
    return lambda i: decay ** math.floor(i / every)


def exponential(final_factor: float, iters: int) -> Callable[[float], float]:
    """Factor ``final_factor ** (i / iters)``: 1 at step 0, ``final_factor`` at ``iters``."""
    final, n = float(final_factor), max(1, int(iters))
    return lambda i: final ** (min(float(i), n) / n)


def on_horizon(factor: Callable[[float], float], horizon) -> Callable[[int], float]:
    """``factor`` read at :meth:`~l3d_app.runtime.horizon.Horizon.nominal` of the step: the
    whole schedule within the steps a time budget leaves (unchanged when it does not bind)."""
    return lambda i: factor(horizon.nominal(i))
