"""The step a run expects to end at, for schedules that must finish when a time budget stops it.

A task's schedules (learning rate, an annealed beta, coarse-to-fine levels) are written for
``iters`` steps. When ``time_budget`` stops the loop earlier, a schedule read by step is cut
mid-way: the rate never decays, beta never reaches its end. A :class:`Horizon` holds the
loop's running prediction of the last step (``iters`` when the budget does not bind; the
training loop updates it, :func:`~l3d_app.runtime.training.train` ``horizon=``), and
:meth:`Horizon.nominal` maps a step to the step of the ``iters``-long schedule it stands for,
so a budget-stopped run is the whole schedule, compressed. Schedules made of events (densify
every 100 steps, reset the opacities every 1000) read :meth:`Horizon.advance`: the nominal
interval each step covers, never moving back, and :func:`scheduled_event` tells whether an
event falls inside it.
"""

from __future__ import annotations

import math
from typing import Dict, Optional, Tuple


class Horizon:
    """``steps``: the predicted number of steps of the run, in ``[1, iters]``.

    Args:
        iters: the schedules' nominal length (the task's ``iters``).
    """

    def __init__(self, iters: int):
        self.iters = max(1, int(iters))
        self.steps = float(self.iters)
        self.reached: Optional[float] = None    # the nominal step :meth:`advance` last reached

    def advance(self, done: int) -> Tuple[float, float]:
        """``(previous, now)``: the nominal interval that the step ending at ``done`` (1-based
        count of steps done) covers; ``now = max(previous, nominal(done))``, so an event is never
        met twice when the prediction rises again. ``(done - 1, done)`` while the prediction is
        ``iters`` (no budget, or one that does not bind). The first call (also after resuming
        from a checkpoint written without this state) starts from ``nominal(done - 1)``."""
        previous = self.nominal(done - 1) if self.reached is None else self.reached
        self.reached = max(previous, self.nominal(done))
        return previous, self.reached

    def nominal(self, step: float) -> float:
        """The step of the ``iters``-long schedule that ``step`` of this run stands for
        (``step * iters / steps``; ``step`` itself while the prediction is ``iters``)."""
        return float(step) * self.iters / self.steps

    def update(self, done: int, predicted: float) -> None:
        """Take the loop's prediction of the last step, clamped to ``[done + 1, iters]``
        (at least one step remains). It may rise again when steps get faster: a schedule
        then moves back slightly, which is smoother than a prediction held at its lowest."""
        self.steps = float(min(self.iters, max(float(done) + 1.0, float(predicted))))

    def state_dict(self) -> Dict[str, Optional[float]]:
        return {"iters": self.iters, "steps": self.steps, "reached": self.reached}

    def load_state_dict(self, state: Dict[str, Optional[float]]) -> None:
        self.iters, self.steps = int(state["iters"]), float(state["steps"])
        self.reached = state.get("reached")      # checkpoints before advance() have none


def scheduled_event(previous: float, now: float, every: int, first: float = 1, last: float = math.inf) -> bool:
    """Whether a multiple ``m`` of ``every`` with ``first <= m <= last`` lies in ``(previous, now]``
    (the latest such multiple is tested: several crossed at once are one event). With integer
    steps ``(done - 1, done)`` this is ``first <= done <= last and done % every == 0``.

    Args:
        previous, now: the interval of (nominal) steps done, ``previous <= now``.
        every: the event's period in steps (> 0).
        first, last: the first and last steps at which the event may happen.
    """
    m = math.floor(min(float(now), float(last)) / int(every)) * int(every)
    return m > previous and m >= first
