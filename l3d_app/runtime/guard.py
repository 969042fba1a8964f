"""The training loop's NaN/Inf guard: a non-finite step is skipped, repeated ones restore a good state.

A step whose loss, gradients or updated parameters are not finite is skipped (nothing is applied)
and logged (``guard/skipped_steps``). After ``max_bad_steps`` consecutive failures, or at once when
the parameters themselves went non-finite, the last good state is restored (``guard/restores``): a
snapshot taken every ``snapshot_every`` steps that a whole interval of clean steps followed, so
not the state a blow-up to huge finite values left. A restore that fails again before a clean
interval goes one good state further back, and after ``max_restores`` such restores in a row the
guard says stop (every try from that state blew up: a learning rate of 1e30, say).
"""

from __future__ import annotations

import copy
import sys
from typing import Any, Dict, List, Optional

import torch

from l3d_app.errors import UserError


def tensors_finite(tensors: List[Optional[torch.Tensor]]) -> bool:
    """True when every element of every tensor (None skipped) is finite.

    One sum per tensor first: a NaN or an infinity makes a sum non-finite, so a finite sum proves
    its tensor finite in one pass (``isfinite(x).all()`` makes five). Only when a sum is not finite
    (which an overflow of huge finite values also gives) does the exact test decide.
    """
    ts = [t for t in tensors if t is not None]
    if not ts:
        return True
    if bool(torch.isfinite(torch.stack([t.detach().sum().float() for t in ts])).all()):
        return True
    return all(bool(torch.isfinite(t).all()) for t in ts)


class NanGuard:
    """Applies a step's loss to a :class:`~l3d_app.runtime.training.Trainable` unless something in
    it is not finite, and keeps the restore points.

    Args:
        trainable: what is trained (its ``optimizer``, ``parameters()``, ``state_dict``).
        snapshot_every: steps between snapshots of the state (a restore point once a whole such
            interval of clean steps followed it).
        max_bad_steps: consecutive non-finite steps before the last good state is restored.
        max_restores: restores in a row (no clean interval between them) after which :attr:`stop`.
        skipped, restores: the counts of a resumed run so far.
    """

    def __init__(self, trainable, snapshot_every: int, max_bad_steps: int = 5, max_restores: int = 3,
                 skipped: int = 0, restores: int = 0):
        self.trainable, self.params = trainable, trainable.parameters()
        self.snapshot_every, self.max_bad_steps, self.max_restores = snapshot_every, max_bad_steps, max_restores
        self.skipped, self.restores, self.skipped_before = int(skipped), int(restores), int(skipped)
        self.good_states = [copy.deepcopy(trainable.state_dict())]     # the last two restore points, oldest first
        self.pending: Optional[Dict[str, Any]] = None
        self.bad_in_a_row = self.clean_in_a_row = self.restores_in_a_row = 0
        self.stop = False

    def apply(self, loss: torch.Tensor, step: int, logger) -> bool:
        """Backward and the optimiser's step when ``loss``, then the gradients, then the updated
        parameters are finite; True when the step was applied, False when it was skipped (and
        maybe a good state restored)."""
        ok = bool(torch.isfinite(loss).all())
        if ok:
            loss.backward()
            ok = tensors_finite([p.grad for p in self.params])
        if ok:
            _optimizer_step(self.trainable, step)
            ok = self.trainable.all_finite()
        if ok:
            self.bad_in_a_row = 0
            self.clean_in_a_row += 1
            if self.clean_in_a_row >= self.snapshot_every:     # a whole interval ran clean: the restores worked
                self.restores_in_a_row = 0
            return True
        self._skip(step, logger)
        return False

    def _skip(self, step: int, logger) -> None:
        self.skipped += 1
        self.bad_in_a_row += 1
        self.clean_in_a_row = 0
        self.pending = None            # the latest snapshot may hold the start of the blow-up
        self.trainable.optimizer.zero_grad(set_to_none=True)
        logger.scalar("guard/skipped_steps", self.skipped, step)
        if self.bad_in_a_row >= self.max_bad_steps or not self.trainable.all_finite():
            self.restores_in_a_row += 1
            if self.restores_in_a_row >= 2 and len(self.good_states) > 1:
                self.good_states.pop()       # the latest restore point blew up again: one further back
            self.trainable.load_state_dict(copy.deepcopy(self.good_states[-1]))
            self.restores += 1
            self.bad_in_a_row = 0
            logger.scalar("guard/restores", self.restores, step)
            self.stop = self.restores_in_a_row >= max(1, int(self.max_restores))

    def snapshot(self, done: int) -> None:
        """After an applied step ``done`` (1-based): every ``snapshot_every`` steps the state is kept,
        and the one before it becomes a restore point."""
        if done % self.snapshot_every == 0:
            if self.pending is not None:
                self.good_states = [self.good_states[-1], self.pending]
            self.pending = copy.deepcopy(self.trainable.state_dict())

    def report(self, ctx, done: int, iters: int, steps: int) -> None:
        """The warning after the loop (stderr and TensorBoard): why the guard stopped it at ``done`` of
        ``iters``, or how many of the ``steps`` run were skipped."""
        if self.stop:
            warning = (f"training stopped at step {done} of {iters}: {self.restores_in_a_row} restores in a row of "
                       f"the last good state blew up again ({self.skipped} steps skipped as non-finite, guard/* in "
                       "TensorBoard); the result is that good state: a learning rate too large?")
            ctx.guard_stop_step = done
        elif self.skipped > self.skipped_before:
            warning = (f"{self.skipped} of {steps} steps were skipped as non-finite, {self.restores} restores of the "
                       "last good state (guard/* in TensorBoard): a learning rate too large?")
        else:
            return
        print(f"l3d_app: warning: {warning}", file=sys.stderr)
        ctx.logger.text("train/guard", warning)


def _optimizer_step(trainable, step: int) -> None:
    """``optimizer.step()``; an update that overflows float32 inside the optimiser (Adam's step
    size at a learning rate near 1e38) is a :class:`UserError`, not a traceback."""
    try:
        trainable.optimizer.step()
    except RuntimeError as err:
        if "overflow" not in str(err):
            raise
        raise UserError(f"the optimiser's update overflowed at step {step} ({err}): a learning rate too large?") from err
