"""The interface every densification strategy implements (modelled on gsplat's ``Strategy``).

The training task calls, per run and per step::

    strategy.initialize(model, optimizer, scene_extent)          # once, before training/resume
    loss = loss + strategy.regularization(model)                  # inside the step (may be None)
    strategy.step_pre_backward(model, optimizer, step, info)      # after the render, before backward
    logs = strategy.step_post_backward(model, optimizer, step, info, generator)
                                                                  # after the optimiser step

``info`` is the render's bookkeeping: ``means2d`` (B, N, 2) pixels with its gradient after
backward, ``radii`` (B, N) pixels (0 = culled), ``width``, ``height`` (pixels).
``info["schedule"]`` (optional) is ``(previous, now)``, the step counts on the task's nominal
schedule that this step takes the run from and to (floats, e.g. a
:class:`~l3d_app.runtime.horizon.Horizon`'s :meth:`~l3d_app.runtime.horizon.Horizon.advance`);
absent, ``(step, step + 1)``. A strategy reads its own schedule (start, until, every) through
:meth:`Strategy.schedule` and :func:`~l3d_app.runtime.horizon.scheduled_event`.
``info["steps_left"]`` (optional) is how many steps the run has after this one (to ``iters``, or
fewer where the time budget ends it sooner).
``generator`` is the run's CPU generator (draw with :mod:`l3d_app.runtime.random`).
``step`` is 0-based (the step just taken). A strategy may resize the model's parameters;
it must then swap the new ``Parameter`` objects into the optimiser
(:func:`l3d_app.strategies.ops.replace_rows`). The returned ``logs`` (name -> number) are
logged by the task under ``strategy/``.
"""

from __future__ import annotations

from typing import Any, Dict, Optional, Tuple

import torch


class Strategy:
    """No densification: the set of splats stays as initialised. Subclasses override hooks."""

    def __init__(self) -> None:
        self.extent = 1.0

    def initialize(self, model, optimizer: torch.optim.Optimizer, scene_extent: float) -> None:
        """Called once before training (and before a resumed state is loaded)."""
        self.extent = float(scene_extent)

    def regularization(self, model) -> Optional[torch.Tensor]:
        """A scalar added to the loss (None: nothing)."""
        return None

    def step_pre_backward(self, model, optimizer, step: int, info: Dict[str, Any]) -> None:
        """After the forward pass, before ``backward`` (e.g. to retain a gradient)."""

    def step_post_backward(self, model, optimizer, step: int, info: Dict[str, Any],
                           generator: Optional[torch.Generator] = None) -> Dict[str, float]:
        """After the optimiser step of ``step``; returns figures to log (may be empty)."""
        return {}

    @staticmethod
    def schedule(step: int, info: Dict[str, Any]) -> Tuple[float, float]:
        """``(previous, now)`` step counts of this step on the nominal schedule (``info["schedule"]``,
        else ``(step, step + 1)``: 0-based ``step`` just taken)."""
        previous, now = info.get("schedule", (step, step + 1))
        return float(previous), float(now)

    def state_dict(self) -> Dict[str, Any]:
        return {}

    def load_state_dict(self, state: Dict[str, Any]) -> None:
        pass
