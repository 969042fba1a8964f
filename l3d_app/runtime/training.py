"""The shared training loop: progress bar, logging, evaluation, checkpoints, resume, NaN guard, time budget.

Every training task hands :func:`train` a :class:`Trainable` (its modules/tensors, optimiser and
LR schedulers), a step function and a :class:`LoopSpec`, and gets, for free:

* a tqdm bar and TensorBoard scalars of the step's logs (against step; wall time via
  ``time/seconds`` and TensorBoard's relative axis), and the step's wall time
  (``time/step_ms``; ``TrainResult.train_seconds`` sums the steps, evaluations excluded);
* LR schedulers (``Trainable.schedulers``) stepped after every applied step and checkpointed
  with the rest: tasks never step them by hand;
* VALIDATION every ``eval_every`` steps and at the end: ``eval_fn(step)`` must read the validation
  split only (the test split is read once, by the task, after :func:`train` returns;
  :func:`log_test` logs it). Its figures go to TensorBoard as ``val/<name>`` and into
  ``TrainResult.history``; images it returns under the key ``"images"`` (a dict of
  tag -> (H, W, 3) in [0, 1]) are logged as ``val/<tag>``. Evaluations are not autocast;
* the run's time budget (:class:`~l3d_app.runtime.budget.TimeBudget`): the loop asks the policy
  after every step whether to go on, validate again first, or stop;
* a NaN/Inf guard (:class:`~l3d_app.runtime.guard.NanGuard`): a non-finite step is skipped,
  repeated ones restore the last good state, and restores that keep failing stop the loop on
  that state with a warning;
* checkpoints (:mod:`~l3d_app.runtime.checkpoints`: ``checkpoint.pt``, written atomically, never
  with non-finite parameters) every ``checkpoint_every`` steps, at the end, and on SIGINT/SIGTERM,
  after which the loop stops cleanly and the task writes its metrics so far;
* resume: with ``resume=True`` the loop continues from ``checkpoint.pt`` in the run directory
  (same RNG state, so an interrupted and resumed CPU run ends like an uninterrupted one). For
  tests, ``L3D_STOP_AT_STEP=N`` in the environment acts as a signal arriving during step N.

``step_fn(step) -> {"loss": scalar tensor, other logs...}`` runs under
``autocast(ctx.precision, ctx.device)`` (``fp32`` does nothing, ``bf16`` autocasts the forward);
the loop calls ``zero_grad``, ``backward``, ``optimizer.step`` (outside autocast, on float32
parameters) and steps the schedulers; ``after_step(step)`` runs after each applied step.
"""

from __future__ import annotations

import math
import os
import signal
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any, Callable, Dict, Iterator, List, Optional

import torch

from l3d_app.runtime.budget import CONFIRM, STOP, TimeBudget
from l3d_app.runtime.checkpoints import CHECKPOINT, resume_from, save_checkpoint
from l3d_app.runtime.guard import NanGuard, tensors_finite
from l3d_app.runtime.precision import autocast
from l3d_app.runtime.progress import progress

__all__ = ["CHECKPOINT", "LoopSpec", "Trainable", "TrainResult", "log_test", "train"]


@dataclass
class LoopSpec:
    """How a training loop runs (the time budget is the :class:`TimeBudget` beside it).

    Args:
        iters: total number of steps (a resumed run continues up to the same total).
        eval_every: steps between validations (0: only the final one).
        checkpoint_every: steps between checkpoints (0: only at the end / on a signal); also the
            NaN guard's snapshot interval (0: a twentieth of ``iters``).
        resume: continue from ``checkpoint.pt`` in ``ctx.out_dir`` when it exists.
        desc: the progress bar's label.
        log_prefix: TensorBoard tag prefix of the step logs (a stage before a task's own training
            logs under its own name).
        log_every: steps between logged step scalars.
        checkpoint: False: no ``checkpoint.pt`` is written or read (a stage whose result the task
            keeps itself); ``resume`` and ``checkpoint_every`` are then ignored.
        max_bad_steps: consecutive non-finite steps before the last good state is restored.
        max_restores: restores in a row after which the loop stops on the last good state.
    """

    iters: int
    eval_every: int = 0
    checkpoint_every: int = 0
    resume: bool = False
    desc: str = "train"
    log_prefix: str = "train"
    log_every: int = 10
    checkpoint: bool = True
    max_bad_steps: int = 5
    max_restores: int = 3


@dataclass
class Trainable:
    """What a task trains: named modules (or ParameterDicts) and their optimiser.

    ``extra`` holds any other picklable state to checkpoint (e.g. an occupancy grid as a
    tensor, a scheduler, a list of progress frames); objects with ``state_dict`` /
    ``load_state_dict`` are handled; tensors, lists and dicts are restored in place (the task's
    own reference to them stays valid: e.g. a task's step counters and timings, which then cover
    the resumed parts of a run).
    """

    modules: Dict[str, torch.nn.Module]
    optimizer: torch.optim.Optimizer
    extra: Dict[str, Any] = field(default_factory=dict)
    schedulers: List[Any] = field(default_factory=list)  # stepped by the loop after each applied step

    def parameters(self) -> List[torch.nn.Parameter]:
        return [p for m in self.modules.values() for p in m.parameters()]

    def state_dict(self) -> Dict[str, Any]:
        return {
            "modules": {k: m.state_dict() for k, m in self.modules.items()},
            "optimizer": self.optimizer.state_dict(),
            "extra": {k: (v.state_dict() if hasattr(v, "state_dict") else v) for k, v in self.extra.items()},
            "schedulers": [s.state_dict() for s in self.schedulers],
        }

    def load_state_dict(self, state: Dict[str, Any]) -> None:
        for k, m in self.modules.items():
            m.load_state_dict(state["modules"][k])
        self.optimizer.load_state_dict(state["optimizer"])
        for sched, sd in zip(self.schedulers, state.get("schedulers", [])):
            if isinstance(sched, torch.optim.lr_scheduler.LambdaLR) and "lr_lambdas" not in sd:
                # a checkpoint of a torch scheduler (StepLR, ...): the factor is a closed form of
                # the step, so the step count is all that carries over
                sd = {**sd, "lr_lambdas": [None] * len(sched.lr_lambdas)}
            sched.load_state_dict(sd)
        for k, v in state.get("extra", {}).items():
            if k in self.extra and hasattr(self.extra[k], "load_state_dict"):
                self.extra[k].load_state_dict(v)
            elif k in self.extra and torch.is_tensor(self.extra[k]):
                self.extra[k].copy_(v)
            elif k in self.extra and isinstance(self.extra[k], list):
                self.extra[k][:] = v
            elif k in self.extra and isinstance(self.extra[k], dict):
                self.extra[k].clear()
                self.extra[k].update(v)
            else:
                self.extra[k] = v

    def all_finite(self) -> bool:
        return tensors_finite(list(self.parameters()))


@dataclass
class TrainResult:
    """Where the loop ended: last step done, last evaluation, and why it stopped."""

    step: int
    metrics: Dict[str, float]
    interrupted: bool
    skipped_steps: int
    restores: int
    history: List[Dict[str, float]] = field(default_factory=list)
    train_seconds: float = 0.0      # wall seconds of the steps run (evaluation excluded), resumed parts included
    steps_run: int = 0              # steps run, resumed parts included (not the steps of the schedule skipped)
    budget_stop: bool = False       # stopped by the time budget before ``iters``
    guard_stop: bool = False        # stopped by the NaN guard: ``max_restores`` restores in a row blew up again

    @property
    def seconds_per_step(self) -> float:
        return self.train_seconds / max(1, self.steps_run)

    def val_metrics(self, digits: int = 4) -> Dict[str, float]:
        """The last validation figures as ``val_<name>`` (``seconds`` left out)."""
        return {f"val_{k}": round(float(v), digits) for k, v in self.metrics.items() if k != "seconds"}

    def timing(self) -> Dict[str, float]:
        """``iters``, ``train_seconds`` and ``seconds_per_step`` for metrics.json."""
        return {"iters": self.step, "train_seconds": round(self.train_seconds, 3),
                "seconds_per_step": round(self.seconds_per_step, 5)}

    def history_rows(self, digits: int = 5) -> List[Dict[str, float]]:
        """Every evaluation of the run, resumed parts included, as {"step": s, metric: value}."""
        return [{"step": int(s), **{k: round(float(v), digits) for k, v in m.items()}}
                for s, m in self.history]


def train(ctx, trainable: Trainable, step_fn: Callable[[int], Dict[str, torch.Tensor]], spec: LoopSpec,
          eval_fn: Optional[Callable[[int], Dict[str, Any]]] = None, budget: Optional[TimeBudget] = None,
          after_step: Optional[Callable[[int], None]] = None) -> TrainResult:
    """Run ``spec.iters`` steps of ``step_fn`` on ``trainable`` (see the module docstring); validate
    with ``eval_fn``; stop where ``budget`` (None: the run's, :meth:`TimeBudget.of`) says."""
    budget = budget if budget is not None else TimeBudget.of(ctx)
    iters, every, ckpt_path = int(spec.iters), int(spec.eval_every or 0), ctx.out_dir / CHECKPOINT
    start, history = resume_from(ctx, trainable, spec.checkpoint and spec.resume)
    before = dict(history.get("counters", {}))      # the resumed parts' steps, seconds, skipped steps, restores
    guard = NanGuard(trainable, int(spec.checkpoint_every) or max(1, iters // 20), spec.max_bad_steps,
                     spec.max_restores, int(before.get("skipped", 0)), int(before.get("restores", 0)))
    metrics: Dict[str, float] = dict(history["eval"][-1][1]) if history["eval"] else {}
    step, stop, precision = start, _StopFlag(), getattr(ctx, "precision", "fp32")
    stop_at = int(os.environ["L3D_STOP_AT_STEP"]) if os.environ.get("L3D_STOP_AT_STEP") else None

    def evaluate(at: int) -> Dict[str, float]:
        return _evaluate(ctx, eval_fn, at, history)

    def counters() -> Dict[str, Any]:
        now = budget.counters()
        return {**now, "steps": int(before.get("steps", 0)) + now["steps"],
                "seconds": float(before.get("seconds", 0.0)) + now["seconds"],
                "skipped": guard.skipped, "restores": guard.restores}

    if budget.begin(start, iters, eval_fn is not None, every, before, spec.desc):
        metrics = budget.price(lambda: evaluate(start))      # what a validation costs, before the first step
    with stop.installed():
        bar = progress(range(start, iters), desc=spec.desc, total=iters, initial=start)
        for step in bar:
            t0 = budget.clock()
            trainable.optimizer.zero_grad(set_to_none=True)
            with autocast(precision, ctx.device):
                logs = step_fn(step)
            ok = guard.apply(logs["loss"], step, ctx.logger)
            if ok:
                for sched in trainable.schedulers:
                    sched.step()
                if after_step is not None:
                    after_step(step)
            budget.add_step(budget.clock() - t0)
            if ok and (step % spec.log_every == 0 or step == iters - 1):
                _log_step(ctx, spec.log_prefix, logs, step, budget.last_step)
                bar.set_postfix(loss=f"{float(logs['loss'].detach()):.4g}")
            done = step + 1
            if eval_fn is not None and every and done % every == 0 and done < iters:
                metrics = budget.timed_eval(lambda: evaluate(done))
            if ok:
                guard.snapshot(done)
            if spec.checkpoint and spec.checkpoint_every and done % int(spec.checkpoint_every) == 0:
                history["counters"] = counters()
                save_checkpoint(ckpt_path, trainable, done, ctx.generator, history)
            if stop_at is not None and done == stop_at:
                stop.signal = signal.SIGINT  # test hook: behave as if interrupted here
            if stop.signal is not None or guard.stop:
                break
            verdict = budget.check(done, history["eval"][-1][0] if history["eval"] else None)
            if verdict == CONFIRM:      # validate now: the final validation if the stop stands
                same = bool(history["eval"]) and history["eval"][-1][0] == done
                if same:
                    history["eval"].pop()     # a repeat at the same step replaces its entry
                metrics = budget.timed_eval(lambda: evaluate(done), same_model=same)
                verdict = budget.confirm(done)
            if verdict == STOP:
                break
        bar.close()
    budget.report()
    done = step + 1 if iters > start else start
    interrupted = stop.signal is not None and done < iters
    if eval_fn is not None and (not history["eval"] or history["eval"][-1][0] != done):
        metrics = budget.timed_eval(lambda: evaluate(done))
    totals = history["counters"] = counters()
    if spec.checkpoint:
        save_checkpoint(ckpt_path, trainable, done, ctx.generator, history)
    guard.report(ctx, done, iters, totals["steps"])
    if interrupted:
        ctx.interrupted = True
        ctx.logger.text("train/interrupted", f"stopped by signal {stop.signal} at step {done}")
    return TrainResult(step=done, metrics=metrics, interrupted=interrupted, skipped_steps=guard.skipped,
                       restores=guard.restores, history=list(history["eval"]), train_seconds=totals["seconds"],
                       steps_run=totals["steps"], budget_stop=budget.stopped, guard_stop=guard.stop)


def _log_step(ctx, prefix: str, logs: Dict[str, Any], step: int, seconds: float) -> None:
    """The step's scalar logs under ``prefix/`` and its wall time in ms."""
    values = {f"{prefix}/{k}": float(v.detach()) for k, v in logs.items() if torch.is_tensor(v) and v.numel() == 1}
    values["time/step_ms" if prefix == "train" else f"{prefix}/step_ms"] = 1000.0 * seconds
    ctx.logger.log_scalars(values, step)


class _StopFlag:
    """Turns SIGINT/SIGTERM into a flag the loop checks after each step."""

    def __init__(self):
        self.signal: Optional[int] = None

    @contextmanager
    def installed(self) -> Iterator["_StopFlag"]:
        previous = {}

        def handler(signum, _frame):
            self.signal = signum

        try:
            for sig in (signal.SIGINT, signal.SIGTERM):
                previous[sig] = signal.signal(sig, handler)
        except ValueError:  # not the main thread: no handlers, no clean stop
            previous = {}
        try:
            yield self
        finally:
            for sig, old in previous.items():
                signal.signal(sig, old)


def _evaluate(ctx, eval_fn, step: int, history: Dict[str, Any]) -> Dict[str, float]:
    with torch.no_grad():
        out = dict(eval_fn(step))
    images = out.pop("images", None) or {}
    metrics = {k: float(v) for k, v in out.items()}
    metrics["seconds"] = ctx.stopwatch.elapsed
    history["eval"].append((step, metrics))
    ctx.logger.log_scalars({f"val/{k}": v for k, v in metrics.items()
                            if math.isfinite(v) and k != "seconds"}, step)
    for tag, image in images.items():
        ctx.logger.image(f"val/{tag}", image, step)
    return metrics


def log_test(ctx, metrics: Dict[str, Any], step: int, images: Optional[Dict[str, Any]] = None) -> None:
    """Log the once-only test figures (``test/<name>``) and pictures at the final ``step``."""
    ctx.logger.log_scalars({f"test/{k}": float(v) for k, v in metrics.items()
                            if isinstance(v, (int, float)) and not isinstance(v, bool)
                            and math.isfinite(float(v))}, step)
    for tag, image in (images or {}).items():
        ctx.logger.image(f"test/{tag}", image, step)
