"""The step a run expects to end at, for schedules that must finish when a time budget stops it.

A task's schedules (learning rate, an annealed beta, coarse-to-fine levels) are written for
``iters`` steps. When ``time_budget`` stops the loop earlier, a schedule read by step is cut
mid-way: the rate never decays, beta never reaches its end. A :class:`Horizon` holds the
loop's running prediction of the last step (``iters`` when the budget does not bind; the
training loop updates it, :func:`~l3d_app.runtime.training.train` ``horizon=``), and
:meth:`Horizon.nominal` maps a step to the step of the ``iters``-long schedule it stands for,
so a budget-stopped run is the whole schedule, compressed.
"""

from __future__ import annotations

from typing import Dict


class Horizon:
    """``steps``: the predicted number of steps of the run, in ``[1, iters]``.

    Args:
        iters: the schedules' nominal length (the task's ``iters``).
    """

    def __init__(self, iters: int):
        self.iters = max(1, int(iters))
        self.steps = float(self.iters)

    def nominal(self, step: float) -> float:
        """The step of the ``iters``-long schedule that ``step`` of this run stands for
        (``step * iters / steps``; ``step`` itself while the prediction is ``iters``)."""
        return float(step) * self.iters / self.steps

    def update(self, done: int, predicted: float) -> None:
        """Take the loop's prediction of the last step, clamped to ``[done + 1, iters]``
        (at least one step remains). It may rise again when steps get faster: a schedule
        then moves back slightly, which is smoother than a prediction held at its lowest."""
        self.steps = float(min(self.iters, max(float(done) + 1.0, float(predicted))))

    def state_dict(self) -> Dict[str, float]:
        return {"iters": self.iters, "steps": self.steps}

    def load_state_dict(self, state: Dict[str, float]) -> None:
        self.iters, self.steps = int(state["iters"]), float(state["steps"])
