"""Wall and CPU seconds of a loop's training steps alone (evaluations, checkpoints left out)."""

from __future__ import annotations

import time
from typing import Dict


class StepClock:
    """``start()`` before each step, ``stop()`` after it; ``state`` (a dict: ``train_seconds``, ``cpu_seconds``,
    ``steps``) is what a checkpoint keeps, so the rates cover a resumed run's earlier parts. CPU seconds are the
    process's (all threads): the per-step cost on a shared machine."""

    def __init__(self):
        self.state: Dict[str, float] = {"train_seconds": 0.0, "cpu_seconds": 0.0, "steps": 0}
        self._t0 = self._c0 = None

    def start(self, *_) -> None:
        self._t0, self._c0 = time.perf_counter(), time.process_time()

    def stop(self, *_) -> None:
        if self._t0 is not None:
            self.state["train_seconds"] += time.perf_counter() - self._t0
            self.state["cpu_seconds"] += time.process_time() - self._c0
        self.state["steps"] += 1
        self._t0 = self._c0 = None

    def state_dict(self) -> Dict[str, float]:
        return dict(self.state)

    def load_state_dict(self, state: Dict[str, float]) -> None:
        self.state.update(state)

    def rates(self, rays_per_step: int) -> Dict[str, float]:
        """``train_seconds``, ``rays_per_second``, ``seconds_per_step``, ``cpu_seconds_per_step`` for metrics.json."""
        s, steps = self.state, max(self.state["steps"], 1)
        return {"train_seconds": round(s["train_seconds"], 4),
                "rays_per_second": round(s["steps"] * rays_per_step / max(s["train_seconds"], 1e-9), 1),
                "seconds_per_step": round(s["train_seconds"] / steps, 4),
                "cpu_seconds_per_step": round(s["cpu_seconds"] / steps, 4)}
