"""Wall-clock timing: a stopwatch with named stages (seconds)."""

from __future__ import annotations

import time
from collections import defaultdict
from contextlib import contextmanager
from typing import Dict, Iterator

import torch


class Stopwatch:
    """Accumulates wall-clock seconds per named stage; ``elapsed`` since creation.

    With ``sync=True`` each stage waits for queued CUDA work so GPU times are honest.
    """

    def __init__(self, sync: bool = False):
        self.start = time.perf_counter()
        self.stages: Dict[str, float] = defaultdict(float)
        self.sync = sync and torch.cuda.is_available()

    @property
    def elapsed(self) -> float:
        return time.perf_counter() - self.start

    @contextmanager
    def stage(self, name: str) -> Iterator[None]:
        if self.sync:
            torch.cuda.synchronize()
        t0 = time.perf_counter()
        try:
            yield
        finally:
            if self.sync:
                torch.cuda.synchronize()
            self.stages[name] += time.perf_counter() - t0
