"""What every task receives: output folder, device, seeded generator, logger, stopwatch."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, Optional

import torch

from l3d_app.runtime.files import write_json
from l3d_app.runtime.logger import RunLogger
from l3d_app.runtime.timer import Stopwatch


@dataclass
class RunContext:
    """The run's shared pieces. Tasks write artefacts with ``ctx.path(name)``."""

    out_dir: Path
    device: torch.device
    generator: torch.Generator
    logger: RunLogger
    stopwatch: Stopwatch = field(default_factory=Stopwatch)
    params: Dict[str, Any] = field(default_factory=dict)
    interrupted: bool = False  # set by the training loop on SIGINT/SIGTERM
    guard_stop_step: Optional[int] = None  # set by the training loop when its NaN guard stopped it (at that step)
    time_budget: float = 0.0  # > 0: wall seconds for the whole task (``time_budget=``); every training loop honours it
    precision: str = "fp32"  # fp32 | bf16: autocast of every training step's forward (``precision=``)
    reserve: float = 0.0  # seconds of ``time_budget`` kept for what follows the training loop (``reserve=``)

    def path(self, name: str) -> Path:
        """A path inside the run directory (parent folders created)."""
        p = self.out_dir / name
        p.parent.mkdir(parents=True, exist_ok=True)
        return p

    def seconds_left(self) -> Optional[float]:
        """Seconds of ``time_budget`` not yet spent (negative once overrun); None without a budget.
        A task writes its optional pictures (gifs) only where they still fit."""
        return self.time_budget - self.stopwatch.elapsed if self.time_budget > 0 else None

    def write_metrics(self, metrics: Dict[str, Any]) -> Dict[str, Any]:
        """Write ``metrics.json`` (final figures + wall-clock ``seconds``) atomically; under a
        ``time_budget`` the task overran, also ``over_budget_seconds`` (what its budget did not hold:
        the caller warns), and ``guard_stop_step`` where the NaN guard stopped training."""
        out = dict(metrics)
        out.setdefault("seconds", round(self.stopwatch.elapsed, 4))
        left = self.seconds_left()
        if left is not None and left < 0:
            out["over_budget_seconds"] = round(-left, 2)
        if self.interrupted:
            out["interrupted"] = True
        if self.guard_stop_step is not None:
            out["guard_stop_step"] = int(self.guard_stop_step)
        out["device"] = str(self.device)
        write_json(self.path("metrics.json"), out)
        return out
