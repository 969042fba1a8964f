"""Coarse-to-fine activation of a grid encoding's levels, by step."""

from __future__ import annotations


class LevelSchedule:
    """``start`` levels active at step 0, one more every ``every`` steps (``start <= 0`` or
    ``every <= 0``: all levels from the start). A no-op for models without
    ``set_active_levels`` (e.g. a harmonic-encoding SDF network)."""

    def __init__(self, model, start: int, every: int):
        self.model = model if hasattr(model, "set_active_levels") else None
        self.start, self.every = int(start), int(every)
        self.active = 0

    def apply(self, step: int) -> None:
        """Set the model's active levels for ``step``."""
        if self.model is None:
            return
        n_levels = self.model.encoding.n_levels
        n = n_levels if self.start <= 0 or self.every <= 0 else self.start + step // self.every
        self.model.set_active_levels(min(n, n_levels))
        self.active = self.model.active_levels
