"""The run logger: TensorBoard scalars, images, image sequences, text and hparams.

One :class:`RunLogger` per run writes into the run directory, so
``tensorboard --logdir outputs`` (or ``multirun``) shows every run and every sweep job.
Scalars are logged against the step; TensorBoard's "Relative" axis shows them against
wall time, and ``log_scalars`` also records ``time/seconds`` at each step.
"""

from __future__ import annotations

import os
import time
from pathlib import Path
from typing import Any, Mapping, Optional

import numpy as np
from torch.utils.tensorboard import SummaryWriter
from torch.utils.tensorboard.summary import hparams as hparams_summary

from l3d_app.runtime.media import to_uint8


def _hparam_value(value: Any):
    """TensorBoard hparams accept bool, int/float and str only."""
    if isinstance(value, (bool, int, float, str)):
        return value
    return str(value)


class RunLogger:
    """Thin wrapper over ``SummaryWriter`` for the things every task logs."""

    def __init__(self, log_dir: os.PathLike, enabled: bool = True):
        self.log_dir = str(log_dir)
        self.start = time.perf_counter()
        self._events_before = set(Path(self.log_dir).glob("events.out.tfevents.*"))
        self.writer: Optional[SummaryWriter] = SummaryWriter(self.log_dir) if enabled else None
        self.records = 0          # log calls so far (scalars, images, texts, hparams)
        self.watchers = []        # callables (tag, value, step) told of every scalar (the live viewer)

    def scalar(self, tag: str, value: float, step: int) -> None:
        self.records += 1
        if self.writer is not None:
            self.writer.add_scalar(tag, float(value), step)
        for watch in self.watchers:
            watch(tag, float(value), step)

    def log_scalars(self, values: Mapping[str, float], step: int) -> None:
        """Log several scalars at ``step`` plus the wall-clock seconds since the run began."""
        for tag, value in values.items():
            self.scalar(tag, value, step)
        self.scalar("time/seconds", time.perf_counter() - self.start, step)

    def image(self, tag: str, image, step: int = 0) -> None:
        """One (H, W, 3) float image in [0, 1]."""
        self.records += 1
        if self.writer is not None:
            self.writer.add_image(tag, to_uint8(image), step, dataformats="HWC")

    def image_sequence(self, tag: str, frames, start_step: int = 0) -> None:
        """(N, H, W, 3) frames as one image per step: scrub them with TensorBoard's slider."""
        self.records += 1
        if self.writer is None:
            return
        for i, frame in enumerate(to_uint8(frames)):
            self.writer.add_image(tag, frame, start_step + i, dataformats="HWC")

    def text(self, tag: str, text: str, step: int = 0) -> None:
        self.records += 1
        if self.writer is not None:
            self.writer.add_text(tag, text, step)

    def hparams(self, params: Mapping[str, Any], metrics: Mapping[str, float]) -> None:
        """Record this run's hyper-parameters and final metrics for the HPARAMS view.

        Written into this run's own event file (``SummaryWriter.add_hparams`` would create
        an extra timestamped run per call, which is what we avoid).
        """
        self.records += 1
        if self.writer is None:
            return
        metrics = {f"final/{k}": float(v) for k, v in metrics.items()
                   if isinstance(v, (int, float)) and not isinstance(v, bool) and np.isfinite(v)}
        params = {k: _hparam_value(v) for k, v in params.items()}
        exp, ssi, sei = hparams_summary(params, metrics)
        file_writer = self.writer._get_file_writer()
        for summary in (exp, ssi, sei):
            file_writer.add_summary(summary)
        for tag, value in metrics.items():
            self.writer.add_scalar(tag, value, 0)

    def discard_if_at_most(self, records: int) -> bool:
        """Close and delete this logger's own event file(s) when it recorded at most ``records``
        things (a run that failed on bad input before logging more than its config): no empty
        run in TensorBoard. Files that were in the directory before (a resumed run's) stay.
        Returns whether it deleted."""
        if self.records > records:
            return False
        self.close()
        for f in set(Path(self.log_dir).glob("events.out.tfevents.*")) - self._events_before:
            f.unlink(missing_ok=True)
        return True

    def close(self) -> None:
        if self.writer is not None:
            self.writer.flush()
            self.writer.close()
            self.writer = None
