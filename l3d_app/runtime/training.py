"""The shared training loop: progress bar, logging, evaluation, checkpoints, resume, NaN guard.

Every training task hands :func:`train` a :class:`Trainable` (its modules/tensors,
optimiser and LR schedulers) and two callbacks, and gets, for free:

* a tqdm bar and TensorBoard scalars of the step's logs (against step; wall time via
  ``time/seconds`` and TensorBoard's relative axis), and the step's wall time
  (``time/step_ms``; ``TrainResult.train_seconds`` sums the steps, evaluations excluded);
* LR schedulers (``Trainable.schedulers``) stepped after every applied step and
  checkpointed with the rest: tasks never step them by hand;
* VALIDATION every ``eval_every`` steps and at the end: ``eval_fn`` must read the
  validation split only (the test split is read once, by the task, after :func:`train`
  returns; :func:`log_test` logs it). Its figures go to TensorBoard as ``val/<name>`` and
  into ``TrainResult.history``; images it returns under the key ``"images"`` (a dict of
  tag -> (H, W, 3) in [0, 1]) are logged as ``val/<tag>``;
* a time budget: with ``time_budget`` > 0 (seconds of the task's wall time, measured by
  ``ctx.stopwatch``) the loop stops early enough that the final validation and the
  ``reserve`` seconds the task needs afterwards (test evaluation, artefacts) still fit,
  and keeps a task's :class:`~l3d_app.runtime.horizon.Horizon` (``horizon=``) at the step
  it expects to stop at, so schedules that read it end with the run;
* a NaN/Inf guard: a non-finite loss or gradient skips the step (nothing is applied) and
  is logged; after ``max_bad_steps`` consecutive failures the last good state is restored
  (a snapshot taken every ``checkpoint_every`` steps, or every twentieth of ``iters``, that a
  whole interval of clean steps followed: not the state a blow-up to huge finite values left);
  a restore that fails again before a clean interval goes one good state further back, and
  after ``max_restores`` such restores in a row the loop stops on the last good state with a
  warning (every try from it blew up: nothing more to gain, e.g. a learning rate of 1e30);
* checkpoints (``checkpoint.pt``, written atomically, never with non-finite parameters)
  every ``checkpoint_every`` steps, at the end, and on SIGINT/SIGTERM, after which the
  loop stops cleanly and the task writes its metrics so far;
* resume: with ``resume=True`` the loop continues from ``checkpoint.pt`` in the run
  directory (same RNG state, so an interrupted and resumed CPU run ends like an
  uninterrupted one). For tests, ``L3D_STOP_AT_STEP=N`` in the environment acts as a
  signal arriving during step N.
"""

from __future__ import annotations

import copy
import math
import os
import signal
import sys
import time
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Dict, Iterator, List, Optional

import torch

from l3d_app.errors import UserError
from l3d_app.runtime.files import atomic_path
from l3d_app.runtime.horizon import Horizon
from l3d_app.runtime.precision import autocast
from l3d_app.runtime.progress import progress
from l3d_app.runtime.torch_files import read_torch_file

CHECKPOINT = "checkpoint.pt"


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
                # a checkpoint from before the schedules were LambdaLR factors (StepLR, ...): the
                # factor is a closed form of the step, so the step count is all that carries over
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
    budget_stop: bool = False       # stopped by ``time_budget`` before ``iters``
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


def _rng_state(generator: torch.Generator) -> Dict[str, Any]:
    return {"generator": generator.get_state(), "torch": torch.get_rng_state()}


def _set_rng_state(generator: torch.Generator, state: Dict[str, Any]) -> None:
    generator.set_state(state["generator"])
    torch.set_rng_state(state["torch"])


def save_checkpoint(path: Path, trainable: Trainable, step: int, generator: torch.Generator,
                    history: Dict[str, Any]) -> bool:
    """Write a checkpoint atomically; refuses (returns False) if any parameter is non-finite."""
    if not trainable.all_finite():
        return False
    state = {"step": step, "trainable": trainable.state_dict(), "rng": _rng_state(generator),
             "history": history}
    with atomic_path(path) as tmp:
        torch.save(state, tmp)
    return True


def read_checkpoint(path: Path) -> Dict[str, Any]:
    """The dict of a ``checkpoint.pt`` written by :func:`save_checkpoint` (on the CPU); a file
    that is not one (empty, truncated, another format, no ``trainable``) is a :class:`UserError`."""
    state = read_torch_file(path, "checkpoint")
    if not isinstance(state, dict) or "trainable" not in state:
        raise UserError(f"{path} is not a checkpoint of this app (no 'trainable' state)")
    return state


def load_checkpoint(path: Path, trainable: Trainable, generator: torch.Generator) -> Dict[str, Any]:
    """Restore a checkpoint written by :func:`save_checkpoint`; returns its dict. One written by
    another task, or by a model of other sizes, is a :class:`UserError` that says which, before
    anything of the run is touched on disk."""
    state = read_checkpoint(path)
    saved = sorted(state["trainable"].get("modules", {}))
    if saved != sorted(trainable.modules):
        raise UserError(f"{path} holds {', '.join(saved) or 'no modules'}, this run trains "
                        f"{', '.join(sorted(trainable.modules))}: a checkpoint of another task? "
                        "Resume with the task that wrote it, or give this run its own hydra.run.dir")
    try:
        trainable.load_state_dict(state["trainable"])
    except (RuntimeError, ValueError, KeyError) as err:
        lines = [line.strip() for line in str(err).splitlines() if line.strip()]
        detail = lines[1] if len(lines) > 1 else (lines[0] if lines else type(err).__name__)  # torch: a header, then one line per key
        raise UserError(f"{path} does not fit this run's model ({detail}): "
                        "resume with the settings that wrote it, or give this run its own hydra.run.dir") from err
    _set_rng_state(generator, state["rng"])
    return state


def tensors_finite(tensors: List[Optional[torch.Tensor]]) -> bool:
    """True when every element of every tensor (None skipped) is finite.

    One sum per tensor first: a NaN or an infinity makes a sum non-finite, so a finite sum
    proves its tensor finite in one pass (``isfinite(x).all()`` makes five: in a profile of gs_train
    at 63 609 Gaussians those passes over the SH coefficients alone took about 11 ms per step, for
    the guard's two checks). Only when a sum is not
    finite (which an overflow of huge finite values also gives) does the exact test decide.
    """
    ts = [t for t in tensors if t is not None]
    if not ts:
        return True
    if bool(torch.isfinite(torch.stack([t.detach().sum().float() for t in ts])).all()):
        return True
    return all(bool(torch.isfinite(t).all()) for t in ts)


def _grads_finite(params: List[torch.nn.Parameter]) -> bool:
    return tensors_finite([p.grad for p in params])


def train(ctx, trainable: Trainable, step_fn: Callable[[int], Dict[str, torch.Tensor]],
          iters: int, eval_fn: Optional[Callable[[int], Dict[str, Any]]] = None,
          eval_every: int = 0, checkpoint_every: int = 0, resume: bool = False,
          max_bad_steps: int = 5, max_restores: int = 3, desc: str = "train", log_every: int = 10,
          after_step: Optional[Callable[[int], None]] = None,
          time_budget: Optional[float] = None, reserve: Optional[float] = None,
          reserve_evals: float = 0.0, horizon: Optional[Horizon] = None, log_prefix: str = "train",
          checkpoint: bool = True, eval_price: Optional[float] = None) -> TrainResult:
    """Run ``iters`` optimisation steps.

    Args:
        ctx: the run's :class:`~l3d_app.runtime.context.RunContext`.
        trainable: modules + optimiser (+ schedulers, extra state) to train and checkpoint.
        step_fn: ``step_fn(step) -> {"loss": scalar tensor, other logs...}``; computes the
            loss (the loop calls ``zero_grad``, ``backward``, ``optimizer.step`` and steps
            the schedulers).
        iters: total number of steps (a resumed run continues up to the same total).
        eval_fn: ``eval_fn(step) -> {metric: float, "images": {tag: (H, W, 3)}}`` on the
            VALIDATION split, called every ``eval_every`` steps and after the last step;
            logged under ``val/`` with ``time/seconds``.
        checkpoint_every: steps between checkpoints (0: only at the end / on a signal).
        resume: continue from ``checkpoint.pt`` in ``ctx.out_dir`` when it exists.
        max_bad_steps: consecutive non-finite steps before the last good state is restored.
        max_restores: restores in a row (no whole snapshot interval of clean steps between them) after which
            the loop stops on the last good state; from the second such restore on, the state
            restored is the good state before the latest one (which may hold the start of a
            blow-up that stayed finite for a whole interval).
        after_step: called after each applied step (e.g. to update an occupancy grid).
        time_budget: > 0: wall seconds for the whole task (``ctx.stopwatch.elapsed``); the
            loop stops when the next step, the final validation and ``reserve`` would not fit.
            None: the run's ``ctx.time_budget`` (the top-level ``time_budget=`` knob), so every
            task that trains through this loop honours it.
        reserve: seconds the task needs after the loop (test evaluation, artefacts); None:
            ``ctx.reserve``.
        reserve_evals: more time kept after the loop, in units of one validation evaluation
            as timed in this run, the latest one (e.g. 20 test views + 36 turntable frames after 4-view
            evaluations: 14): what follows the loop is mostly rendering, whose cost the loop
            measures, so the budget holds on any machine and image size. A budget stop rests on a
            price measured twice: before stopping on a validation's price the loop validates again
            (once per validation) and stops only if the price still says so. At the step of that
            validation the cheaper of the two counts (the same model: a stall only adds time; one
            volsdf step-250 validation several times slower than in every other run once stopped a
            run at step 250 of 1500 with 230 s of its budget unused); later, or
            once the price is ``eval_every // 5`` or more steps old, the new one (volsdf's step-250
            validation of a fuzzy surface priced its 256 px test views 2.4x too dear on a slow
            machine).
        horizon: a :class:`~l3d_app.runtime.horizon.Horizon` the loop updates after every
            step with its prediction of the last step the budget lets it run (periodic
            evaluations, the final one, ``reserve_evals`` and ``reserve`` included), so the
            task's schedules can end where the run ends. Untouched without a budget.
        log_prefix: TensorBoard tag prefix of the step logs (a stage before the task's own
            training logs under its own name).
        checkpoint: False: no ``checkpoint.pt`` is written or read (a stage whose result the
            task keeps itself); ``resume`` and ``checkpoint_every`` are then ignored.
        eval_price: seconds of one validation the task has already timed (a validation before
            training). Under a time budget the loop must know what a validation costs before its
            first budget test (the final validation and ``reserve_evals`` are priced by it): without
            ``eval_price`` it validates once before its first step (logged at that step). Until the
            loop has timed a validation of its own, only the stop test reads this price, not the
            ``horizon``; before a stop it is validated again once ``eval_every // 5`` steps old, and
            a price measured on a model trained fewer steps than that which loses the budget even
            if the loop stops at once does not stop it before that step
            (:func:`_untrained_price_says_lost`).

    ``step_fn`` runs under ``autocast(ctx.precision, ctx.device)`` (the ``precision=`` knob:
    ``fp32`` does nothing, ``bf16`` autocasts the forward); backward and the optimiser step
    run outside it, on float32 parameters. Evaluations are not autocast.
    """
    params = trainable.parameters()
    ckpt_path = ctx.out_dir / CHECKPOINT
    history: Dict[str, Any] = {"eval": []}
    start = 0
    if checkpoint and resume and ckpt_path.exists():
        state = load_checkpoint(ckpt_path, trainable, ctx.generator)
        start, history = int(state["step"]), state["history"]
        ctx.logger.text("train/resume", f"resumed from step {start}")
    elif checkpoint and resume:
        note = f"resume=true, but there is no {ckpt_path}: training starts at step 0"
        print(f"l3d_app: note: {note}", file=sys.stderr)
        ctx.logger.text("train/resume", note)
    before = dict(history.get("counters", {}))      # the resumed parts' steps, seconds, skipped steps, restores
    # the guard's restore point, promoted from the latest snapshot only once a whole snapshot
    # interval after it ran clean: a step that blows the parameters up to huge but finite values
    # passes the finite test, and the snapshot after it must not become what a restore brings back
    good_states = [copy.deepcopy(trainable.state_dict())]     # the last two restore points, oldest first
    pending_state: Optional[Dict[str, Any]] = None
    restores_in_a_row, clean_in_a_row, guard_stop = 0, 0, False
    snapshot_every = checkpoint_every or max(1, iters // 20)
    bad_in_a_row = 0
    skipped, restores = int(before.get("skipped", 0)), int(before.get("restores", 0))
    metrics: Dict[str, float] = dict(history["eval"][-1][1]) if history["eval"] else {}
    confirmed = -1                  # the step of the loop's latest re-validation before a budget stop
    step = start
    stop = _StopFlag()
    stop_at = int(os.environ["L3D_STOP_AT_STEP"]) if os.environ.get("L3D_STOP_AT_STEP") else None
    if time_budget is None:
        time_budget = getattr(ctx, "time_budget", 0.0)
    if reserve is None:
        reserve = getattr(ctx, "reserve", 0.0)
    clock = _LoopClock(float(time_budget or 0.0), float(reserve or 0.0), float(reserve_evals or 0.0),
                       now=lambda: ctx.stopwatch.elapsed)
    precision = getattr(ctx, "precision", "fp32")
    short_note = ""
    if clock.budget > 0 and start < iters:
        if clock.reserve + ctx.stopwatch.elapsed >= clock.budget:
            note = (f"time_budget={clock.budget:g} s is spent before training ({ctx.stopwatch.elapsed:.1f} s of "
                    f"set-up, reserve={clock.reserve:g} s kept for after it): {desc} runs one step")
            print(f"l3d_app: note: {note}", file=sys.stderr)
            ctx.logger.text("train/budget", note)
        if eval_price is None and "eval_seconds" in before:          # resumed: the saved run's price
            eval_price = float(before["eval_seconds"])
        if eval_fn is not None:         # price the final validation and the test views from the start
            if eval_price is not None:
                clock.price_eval(float(eval_price))
            else:
                t0 = clock.now()
                metrics = _evaluate(ctx, eval_fn, start, history)
                clock.price_eval(clock.now() - t0)
    with stop.installed():
        bar = progress(range(start, iters), desc=desc, total=iters, initial=start)
        for step in bar:
            t0 = time.perf_counter()
            trainable.optimizer.zero_grad(set_to_none=True)
            with autocast(precision, ctx.device):
                logs = step_fn(step)
            loss = logs["loss"]
            ok = bool(torch.isfinite(loss).all())
            if ok:
                loss.backward()
                ok = _grads_finite(params)
            if ok:
                _optimizer_step(trainable, step)
                ok = trainable.all_finite()
            if not ok:
                skipped += 1
                bad_in_a_row += 1
                clean_in_a_row = 0
                pending_state = None            # the latest snapshot may hold the start of the blow-up
                trainable.optimizer.zero_grad(set_to_none=True)
                ctx.logger.scalar("guard/skipped_steps", skipped, step)
                if bad_in_a_row >= max_bad_steps or not trainable.all_finite():
                    restores_in_a_row += 1
                    if restores_in_a_row >= 2 and len(good_states) > 1:
                        good_states.pop()       # the latest restore point blew up again: one further back
                    trainable.load_state_dict(copy.deepcopy(good_states[-1]))
                    restores += 1
                    bad_in_a_row = 0
                    ctx.logger.scalar("guard/restores", restores, step)
                    guard_stop = restores_in_a_row >= max(1, int(max_restores))
            else:
                bad_in_a_row = 0
                clean_in_a_row += 1
                if clean_in_a_row >= snapshot_every:     # a whole interval ran clean: the restores worked
                    restores_in_a_row = 0
                for sched in trainable.schedulers:
                    sched.step()
                if after_step is not None:
                    after_step(step)
            clock.add_step(time.perf_counter() - t0)
            if ok and (step % log_every == 0 or step == iters - 1):
                values = {f"{log_prefix}/{k}": float(v.detach()) for k, v in logs.items()
                          if torch.is_tensor(v) and v.numel() == 1}
                values["time/step_ms" if log_prefix == "train" else f"{log_prefix}/step_ms"] = 1000.0 * clock.last_step
                ctx.logger.log_scalars(values, step)
                bar.set_postfix(loss=f"{float(loss.detach()):.4g}")
            done = step + 1
            if eval_fn is not None and eval_every and done % eval_every == 0 and done < iters:
                metrics = clock.timed_eval(lambda: _evaluate(ctx, eval_fn, done, history))
            if ok and done % snapshot_every == 0:
                if pending_state is not None:
                    good_states = [good_states[-1], pending_state]
                pending_state = copy.deepcopy(trainable.state_dict())
            if checkpoint and checkpoint_every and done % checkpoint_every == 0:
                history["counters"] = _counters(before, clock, skipped, restores)
                save_checkpoint(ckpt_path, trainable, done, ctx.generator, history)
            if stop_at is not None and done == stop_at:
                stop.signal = signal.SIGINT  # test hook: behave as if interrupted here
            if stop.signal is not None or guard_stop:
                break
            if horizon is not None and clock.budget > 0:
                horizon.update(done, clock.predicted_steps(ctx.stopwatch.elapsed, done, eval_fn is not None,
                                                           eval_every))
            if done < iters and clock.out_of_time(ctx.stopwatch.elapsed, eval_fn is not None):
                if _untrained_price_says_lost(clock, ctx.stopwatch.elapsed, history, start, done, eval_fn, eval_every):
                    continue        # stopping now cannot keep the budget at a price the training may lower
                if _price_to_confirm(history, done, eval_fn, eval_every, confirmed, start):
                    # validate now: the final validation if the stop stands, a periodic one with the
                    # new price if it does not (_price_to_confirm says why)
                    metrics = _revalidate(ctx, clock, eval_fn, done, history)
                    confirmed = done
                    if horizon is not None:
                        horizon.update(done, clock.predicted_steps(ctx.stopwatch.elapsed, done, True, eval_every))
                    if not clock.out_of_time(ctx.stopwatch.elapsed, True):
                        continue
                clock.budget_stop = True
                ctx.logger.text("train/budget", f"time budget {time_budget:g} s: stopped at step {done}")
                if done < max(1, iters // 10):    # a budget that leaves training almost nothing: say so
                    after = clock.after_loop_seconds(eval_fn is not None)
                    short_note = (f"time_budget={time_budget:g} s stopped {desc} at step {done} of {iters}: what "
                                  f"follows training is priced at {after:.1f} s (final validation, "
                                  f"{clock.reserve_evals:g} more validations' worth, reserve={clock.reserve:g} s)")
                break
        bar.close()
    if short_note:                          # after the bar, on a line of its own
        print(f"l3d_app: note: {short_note}", file=sys.stderr)
    done = step + 1 if iters > start else start
    interrupted = stop.signal is not None and done < iters
    if eval_fn is not None and (not history["eval"] or history["eval"][-1][0] != done):
        metrics = clock.timed_eval(lambda: _evaluate(ctx, eval_fn, done, history))
    counters = history["counters"] = _counters(before, clock, skipped, restores)
    if checkpoint:
        save_checkpoint(ckpt_path, trainable, done, ctx.generator, history)
    if guard_stop:
        warning = (f"training stopped at step {done} of {iters}: {restores_in_a_row} restores in a row of the last good "
                   f"state blew up again ({skipped} steps skipped as non-finite, guard/* in TensorBoard); the result "
                   "is that good state: a learning rate too large?")
        print(f"l3d_app: warning: {warning}", file=sys.stderr)
        ctx.logger.text("train/guard", warning)
        ctx.guard_stop_step = done
    elif skipped > int(before.get("skipped", 0)):
        warning = (f"{skipped} of {counters['steps']} steps were skipped as non-finite, {restores} restores of the "
                   "last good state (guard/* in TensorBoard): a learning rate too large?")
        print(f"l3d_app: warning: {warning}", file=sys.stderr)
        ctx.logger.text("train/guard", warning)
    if interrupted:
        ctx.interrupted = True
        ctx.logger.text("train/interrupted", f"stopped by signal {stop.signal} at step {done}")
    return TrainResult(step=done, metrics=metrics, interrupted=interrupted,
                       skipped_steps=skipped, restores=restores, history=list(history["eval"]),
                       train_seconds=counters["seconds"], steps_run=counters["steps"],
                       budget_stop=clock.budget_stop, guard_stop=guard_stop)


def _counters(before: Dict[str, Any], clock: "_LoopClock", skipped: int, restores: int) -> Dict[str, Any]:
    """The run's step counters, its resumed parts included (kept in the checkpoint's history):
    steps run, their wall seconds, steps skipped as non-finite, restores of the good state, and
    the latest validation's seconds (a resumed run's price of a validation under a budget)."""
    out = {"steps": int(before.get("steps", 0)) + clock.steps,
           "seconds": float(before.get("seconds", 0.0)) + clock.train_seconds,
           "skipped": skipped, "restores": restores}
    price = clock.last_eval if clock.evals else clock.outside_eval
    if price > 0:
        out["eval_seconds"] = price          # a resumed run's first price of a validation
    return out


def _optimizer_step(trainable: Trainable, step: int) -> None:
    """``optimizer.step()``; an update that overflows float32 inside the optimiser (Adam's step
    size at a learning rate near 1e38) is a :class:`UserError`, not a traceback."""
    try:
        trainable.optimizer.step()
    except RuntimeError as err:
        if "overflow" not in str(err):
            raise
        raise UserError(f"the optimiser's update overflowed at step {step} ({err}): a learning rate too large?") from err


def _price_to_confirm(history: Dict[str, Any], done: int, eval_fn, eval_every: int, confirmed: int,
                      start: int = 0) -> bool:
    """Whether a budget stop at step ``done`` should validate again first: there is a validation
    to repeat, and the latest one was measured once (not itself the re-validation made at step
    ``confirmed``: one stall must not end a run) or is at least ``max(1, eval_every // 5)``
    steps old (it priced an earlier model: a fuzzy surface renders several times slower than
    the sharp one). At most one re-validation per validation and per that many steps, so a loop
    near its budget does not validate at every step. With no validation of the loop's own, the
    price is the task's (``eval_price``, a validation before step ``start``): validated again once
    it is that many steps old."""
    if eval_fn is None:
        return False
    stale = max(1, int(eval_every or 0) // 5)
    if not history["eval"]:
        return done - start >= stale
    last = history["eval"][-1][0]
    return last != confirmed or done - last >= stale


def _untrained_price_says_lost(clock: "_LoopClock", elapsed: float, history: Dict[str, Any], start: int, done: int,
                               eval_fn, eval_every: int) -> bool:
    """Whether a budget stop at step ``done`` waits: the validation's price was measured on a model
    trained fewer than ``max(1, eval_every // 5)`` steps, the loop has not yet trained that many,
    and even stopping now would pass the budget at that price. An untrained model's rendering
    cost says little of a trained one's (train_nerf's occupancy grid is all occupied during its
    warm-up: ``ground``'s 4 validation views took ~53 s before training, which priced what follows
    training at 319 s under a 200 s budget, stopped the run at step 1 and overran it by 152 s on the
    untrained model's test views: docs/measured/time_budget.md). Stopping cannot keep the budget then; training on to that step and validating
    there (:func:`_price_to_confirm`) can, where the price falls, and waits only while those steps
    and ``reserve`` still fit the budget (a budget spent before training stops at once)."""
    if eval_fn is None or clock.budget <= 0:
        return False
    early = max(1, int(eval_every or 0) // 5)
    priced_at = history["eval"][-1][0] if history["eval"] else start
    if priced_at >= early or done >= early:
        return False
    steps_left = (early - done) * clock.train_seconds / max(1, clock.steps)
    return (elapsed + clock.after_loop_seconds(True) >= clock.budget
            and elapsed + steps_left + clock.reserve < clock.budget)


def _revalidate(ctx, clock: "_LoopClock", eval_fn, done: int, history: Dict[str, Any]) -> Dict[str, float]:
    """Validate at step ``done`` again, timed. A repeat at the step of the latest validation (the
    same model) replaces that entry, and the cheaper of the two timings is the price: a machine's
    stall only ever adds time. After later steps the new timing is the price."""
    same_step = bool(history["eval"]) and history["eval"][-1][0] == done
    first_price = clock.last_eval
    if same_step:
        history["eval"].pop()
    metrics = clock.timed_eval(lambda: _evaluate(ctx, eval_fn, done, history))
    if same_step:
        clock.last_eval = min(clock.last_eval, first_price)
    return metrics


class _LoopClock:
    """Step and evaluation timings, and the time-budget test."""

    def __init__(self, budget: float, reserve: float, reserve_evals: float = 0.0,
                 now: Callable[[], float] = time.perf_counter):
        self.budget, self.reserve, self.reserve_evals, self.now = budget, reserve, reserve_evals, now
        self.train_seconds, self.steps, self.last_step = 0.0, 0, 0.0
        self.evals, self.last_eval, self.outside_eval = 0, 0.0, 0.0
        self.budget_stop = False

    def add_step(self, seconds: float) -> None:
        self.train_seconds += seconds
        self.steps += 1
        self.last_step = seconds

    def timed_eval(self, fn: Callable[[], Dict[str, float]]) -> Dict[str, float]:
        t0 = self.now()
        out = fn()
        self.last_eval = self.now() - t0
        self.evals += 1
        return out

    def price_eval(self, seconds: float) -> None:
        """A validation's cost timed outside the loop (a task's validation before training): the
        budget test's price until the loop has timed one of its own. The horizon
        (:meth:`predicted_steps`) keeps reading the loop's own validations only, so the schedules
        of a run whose budget holds are not changed by it."""
        self.outside_eval = max(float(seconds), 0.0)

    def eval_cost(self, has_eval: bool) -> float:
        """Seconds the next validation is expected to take: the latest one's (0 before the first;
        under a budget :func:`train` prices one before its first step).

        The latest, not the mean: an evaluation's cost follows the model (a neural surface
        that is still fuzzy skips no empty space, so volsdf's step-250 validation with a
        starting beta of 0.3 took several times its later ones, and the loop kept 39 of them
        for the final validation, the test views and gifs (`dev`: 20 test views at 2 x 2 rays and
        72 gif frames against 4 one-ray views; 21 since the gifs take what is left at the end), so
        the mean stopped a 1500-step run at step 750; 3DGS evaluations grow with densification)."""
        return self.last_eval if (has_eval and self.evals) else 0.0

    def after_loop_seconds(self, has_eval: bool) -> float:
        """What the budget keeps after the loop: the final validation, ``reserve_evals`` more at its
        price, and ``reserve`` seconds."""
        final_eval = self.eval_cost(has_eval) if (self.evals or not has_eval) else self.outside_eval
        return final_eval * (1.0 + self.reserve_evals) + self.reserve

    def out_of_time(self, elapsed: float, has_eval: bool) -> bool:
        """True when one more step plus the final validation and the reserve (seconds + evaluations'
        worth of rendering) would pass the budget."""
        if self.budget <= 0:
            return False
        step = self.train_seconds / max(1, self.steps)
        return elapsed + step + self.after_loop_seconds(has_eval) >= self.budget

    def predicted_steps(self, elapsed: float, done: int, has_eval: bool, eval_every: int) -> float:
        """The step count the budget allows: ``done`` plus the seconds left after the final
        validation and the reserve, over a step's seconds (its mean so far) plus its share of
        the periodic evaluations (the latest one's cost / ``eval_every``)."""
        final_eval = self.eval_cost(has_eval)
        per_step = self.train_seconds / max(1, self.steps)
        if has_eval and eval_every:
            per_step += final_eval / int(eval_every)
        left = self.budget - elapsed - final_eval * (1.0 + self.reserve_evals) - self.reserve
        return done + max(0.0, left) / max(per_step, 1e-9)


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
