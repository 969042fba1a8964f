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
