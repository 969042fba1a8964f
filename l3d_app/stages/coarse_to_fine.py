"""Coarse-to-fine grid levels during training (Neuralangelo's progressive levels)."""

from __future__ import annotations

from typing import Dict

from l3d_app.errors import UserError
from l3d_app.models.level_schedule import LevelSchedule
from l3d_app.registry import STAGES
from l3d_app.stages.base import MethodState, Stage


@STAGES.register("coarse_to_fine")
class CoarseToFine(Stage):
    """``first`` grid levels of the model's encoding active at step 0, one more every ``every`` steps
    (:class:`~l3d_app.models.level_schedule.LevelSchedule`; 0: all levels from the start; a model without
    levels is left alone); logs ``active_levels``."""

    def __init__(self, first: int = 4, every: int = 100):
        for key, value in (("first", first), ("every", every)):
            if isinstance(value, bool) or not isinstance(value, int) or value < 0:
                raise UserError(f"coarse_to_fine {key} must be an integer >= 0, got {value!r}")
        self.first, self.every = first, every

    def setup(self, state: MethodState, ctx) -> None:
        self.levels = LevelSchedule(state.model, self.first, self.every)

    def on_step(self, state: MethodState, nominal: float) -> Dict[str, float]:
        self.levels.apply(int(nominal))
        return {"active_levels": float(self.levels.active)}
