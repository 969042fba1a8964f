"""The time budget: one policy that a run's training loop and its tasks consult.

``time_budget`` (> 0) is the wall seconds of the whole task, read on the task's clock
(``ctx.stopwatch``). A task builds one :class:`TimeBudget` (:meth:`TimeBudget.of`), DECLARES the
work that follows its training (the test views and other renders, in validations' worth; a
marching-cubes mesh; seconds for artefacts), hands it to
:func:`~l3d_app.runtime.training.train`, and after training asks it what still fits (turntable
frames, gifs). The policy prices everything from what it measured in this run, so a budget holds
on any machine and image size:

* the loop stops when one more step, the final validation and what follows training would pass
  the budget. What follows is priced at the latest validation's seconds (an evaluation's cost
  follows the model: a fuzzy surface renders slower than a sharp one; splats grow), times
  ``1 + evals_after``, plus ``reserve`` seconds;
* a validation's price is known before the first step: a task's own timed validation
  (``eval_price``, e.g. its picture before training) or a timed part of one
  (:meth:`TimeBudget.price_from_part`), a resumed run's saved price, or one validation the loop
  runs before its first step; a task's picture before training is drawn only when it fits
  (:meth:`TimeBudget.fits_before_training`);
* a stop rests on a price measured twice: before stopping, the loop validates again (once per
  validation, or once the price is ``max(1, eval_every // 5)`` steps old); at the same step the
  cheaper timing counts (a stall only adds time), later the new one. A price measured on a model
  trained fewer than that many steps does not stop the loop before that step while those steps
  and ``reserve`` fit (an untrained model's rendering says little of a trained one's, and one
  timing of it is one reading of a shared machine): the loop trains on and validates there;
* a :class:`~l3d_app.runtime.horizon.Horizon` (``horizon=``) is kept at the step the budget lets
  the loop reach, so schedules that read it end with the run;
* a stage before training gets a deadline (:meth:`TimeBudget.stage_deadline`), the gifs after it
  the frames that fit (:func:`frames_that_fit`).

Without a budget (``seconds`` <= 0) nothing stops the loop; the policy still times its steps and
evaluations (``TrainResult.train_seconds``).
"""

from __future__ import annotations

import sys
from typing import Callable, Dict, Optional, Sequence

from l3d_app.runtime.horizon import Horizon

GO, CONFIRM, STOP = "go", "confirm", "stop"      # :meth:`TimeBudget.check`'s verdicts
MESH_PRICED_AT = 128     # the marching-cubes resolution at which a task's configured mesh seconds hold


def renders_in_validations(work: float, per_validation: float, margin: float = 1.0) -> float:
    """Work after training in units of one validation: ``work`` (views x rays per pixel, points,
    objects, ... ) over what one validation processes in the same unit, times ``margin``."""
    return float(margin) * float(work) / max(1.0, float(per_validation))


def views_in_validations(n_eval_views: int, n_test_views: int, supersample: int = 1,
                         val_supersample: Optional[int] = None) -> float:
    """The test views at ``supersample``^2 rays per pixel in validations of ``n_eval_views`` views
    of the same size at ``val_supersample``^2 (None: ``supersample``)."""
    val_ss = supersample if val_supersample is None else int(val_supersample)
    return renders_in_validations(n_test_views * supersample ** 2, n_eval_views * val_ss ** 2)


def mesh_seconds_at(resolution: int, seconds_at_128: float, seconds_per_point: float) -> float:
    """Seconds to keep for a mesh step at ``resolution`` whose price at :data:`MESH_PRICED_AT` is
    ``seconds_at_128``: that price plus twice the grid's extra points at ``seconds_per_point`` (twice,
    like the price itself: the culling and colouring grow with the mesh too); fewer points, less
    time; never below 0 s."""
    extra_points = int(resolution) ** 3 - MESH_PRICED_AT ** 3
    return max(0.0, float(seconds_at_128) + 2.0 * float(seconds_per_point) * extra_points)


def frames_that_fit(frames: int, seconds_left: Optional[float], seconds_per_frame: float, least: int = 8,
                    already: int = 0, multiple: int = 1) -> int:
    """How many of ``frames`` preview frames to render: all without a budget (``seconds_left``
    None), else the ``already`` rendered ones plus as many as fit ``seconds_left`` at
    ``seconds_per_frame``, rounded down to a ``multiple``; 0 (no gif) when fewer than ``least`` fit
    (or fewer than ``frames`` when that is smaller). A preview no metric reads takes what is left."""
    frames = int(frames)
    if seconds_left is None or frames <= 0:
        return max(frames, 0)
    per_frame = max(float(seconds_per_frame), 0.0)
    fit = frames if per_frame <= 0 else int(already) + int(max(float(seconds_left), 0.0) // per_frame)
    fit = min(frames, fit)
    fit -= fit % max(int(multiple), 1)
    return fit if fit >= min(int(least), frames) else 0


class TimeBudget:
    """The time-budget policy of one run (see the module docstring).

    Args:
        seconds: the task's budget (s); <= 0: none.
        reserve: seconds kept after training (artefacts, a mesh: :meth:`keep_mesh`).
        clock: the task's elapsed wall seconds; steps and evaluations are timed on it.
        evals_after: rendering after training in validations' worth (:meth:`keep_renders`).
        eval_price: seconds of a validation the task has timed (None: the loop prices one).
        horizon: the schedules' horizon the loop keeps at the predicted last step.
        note: ``note(tag, text)`` for TensorBoard notes (``ctx.logger.text``).
    """

    def __init__(self, seconds: float = 0.0, reserve: float = 0.0, clock: Callable[[], float] = lambda: 0.0,
                 evals_after: float = 0.0, eval_price: Optional[float] = None, horizon: Optional[Horizon] = None,
                 note: Callable[[str, str], None] = lambda tag, text: None):
        self.seconds, self.reserve = float(seconds or 0.0), float(reserve or 0.0)
        self.clock, self.evals_after, self.eval_price = clock, float(evals_after or 0.0), eval_price
        self.horizon, self.note = horizon, note
        self.begin(0, 0, False, 0)

    @classmethod
    def of(cls, ctx, **kwargs) -> "TimeBudget":
        """The run's budget: ``ctx.time_budget``, ``ctx.reserve``, ``ctx.stopwatch``, ``ctx.logger``
        (``kwargs`` override or add)."""
        kwargs.setdefault("seconds", getattr(ctx, "time_budget", 0.0))
        kwargs.setdefault("reserve", getattr(ctx, "reserve", 0.0))
        return cls(clock=lambda: ctx.stopwatch.elapsed, note=ctx.logger.text, **kwargs)

    # ------------------------------------------------------------------ what the task declares
    def keep_renders(self, work: float, per_validation: float = 1.0, margin: float = 1.0) -> "TimeBudget":
        """Keep time for ``work`` after training, priced at the validations (:func:`renders_in_validations`)."""
        self.evals_after += renders_in_validations(work, per_validation, margin)
        return self

    def keep_mesh(self, resolution: int, seconds_at_128: float, seconds_per_point: Callable[[], float]) -> float:
        """Keep the seconds of a marching-cubes mesh at ``resolution`` (added to ``reserve``) and return
        them: ``seconds_at_128`` as configured at :data:`MESH_PRICED_AT` or without a budget, else
        :func:`mesh_seconds_at` with ``seconds_per_point()`` measured (noted under ``reserve``)."""
        seconds = float(seconds_at_128)
        if self.seconds > 0 and int(resolution) != MESH_PRICED_AT:
            per_point = float(seconds_per_point())
            seconds = mesh_seconds_at(resolution, seconds_at_128, per_point)
            self.note("reserve", f"{seconds:.1f} s kept for the mesh at mesh_resolution={int(resolution)} "
                                 f"({float(seconds_at_128):g} s at {MESH_PRICED_AT}; the field costs "
                                 f"{1e6 * per_point:.2f} us per grid point, measured)")
        self.reserve += seconds
        return seconds

    def time_validation(self, fn: Callable[[], object]) -> object:
        """Run a validation of the task's own before training (``fn``), timed: the loop's first price
        of a validation (``eval_price``); returns what ``fn`` returns."""
        t0 = self.clock()
        out = fn()
        self.eval_price = self.clock() - t0
        return out

    def price_from_part(self, fn: Callable[[], float]) -> float:
        """Time ``fn``, which does a part of one validation's work and returns that part's share in
        (0, 1]; the seconds over the share are the loop's first price of a validation
        (``eval_price``, until a whole one is timed), returned."""
        t0 = self.clock()
        share = float(fn())
        self.eval_price = max(self.clock() - t0, 0.0) / max(share, 1e-9)
        return self.eval_price

    def fits_before_training(self, seconds: float) -> bool:
        """Whether a stage of ``seconds`` before training ends by :meth:`stage_deadline` with the final
        work priced at ``seconds`` as one validation (a third of the budget at most, half of what the
        final work leaves); True without a budget."""
        return self.stage_deadline(float(seconds), minimum=float(seconds)) is not None

    # ------------------------------------------------------------------ before and after training
    def seconds_left(self) -> Optional[float]:
        """Seconds of the budget not yet spent (negative once overrun); None without a budget."""
        return self.seconds - self.clock() if self.seconds > 0 else None

    def stage_deadline(self, eval_seconds: Optional[float], minimum: float) -> Optional[float]:
        """The task's elapsed seconds at which a stage before training must stop: at most a third of
        the budget, and at most half of what the budget leaves after the final work priced at
        ``eval_seconds`` (one validation; None: unknown, only the third applies); 0.0 without a
        budget; None (skip the stage) when that leaves it under ``minimum`` seconds."""
        if self.seconds <= 0:
            return 0.0
        elapsed, deadline = self.clock(), self.seconds / 3.0
        if eval_seconds is not None:
            final = eval_seconds * (1.0 + self.evals_after) + self.reserve
            deadline = min(deadline, elapsed + 0.5 * (self.seconds - elapsed - final))
        return deadline if deadline - elapsed >= minimum else None

    def steps_that_fit(self, recent_step_seconds: Sequence[float]) -> Optional[int]:
        """Training steps that fit the seconds left before ``reserve`` at the mean of the recent
        steps' seconds; None without a budget or a step timed."""
        if self.seconds <= 0 or not recent_step_seconds:
            return None
        seconds = self.seconds - self.reserve - self.clock()
        return int(seconds * len(recent_step_seconds) / max(sum(recent_step_seconds), 1e-9))

    # ------------------------------------------------------------------ the loop's side
    def begin(self, start: int, iters: int, has_eval: bool, eval_every: int, counters: Optional[Dict] = None,
              desc: str = "train") -> bool:
        """Start timing a loop at step ``start`` of ``iters``; ``counters``: a resumed run's. True when
        the loop must validate now (:meth:`price`) to know what a validation costs."""
        self.start, self.iters, self.has_eval, self.eval_every, self.desc = start, iters, has_eval, eval_every, desc
        self.train_seconds, self.steps, self.last_step = 0.0, 0, 0.0
        self.evals, self.last_eval, self.outside_eval = 0, 0.0, 0.0
        self.stopped, self.confirmed, self.short_note = False, -1, ""
        if self.seconds <= 0 or start >= iters:
            return False
        if self.reserve + self.clock() >= self.seconds:
            note = (f"time_budget={self.seconds:g} s is spent before training ({self.clock():.1f} s of set-up, "
                    f"reserve={self.reserve:g} s kept for after it): {desc} runs one step")
            print(f"l3d_app: note: {note}", file=sys.stderr)
            self.note("train/budget", note)
        price = self.eval_price
        if price is None and "eval_seconds" in (counters or {}):        # resumed: the saved run's price
            price = float(counters["eval_seconds"])
        if has_eval and price is not None:
            self.outside_eval = max(float(price), 0.0)
        return has_eval and price is None

    def price(self, fn: Callable[[], Dict[str, float]]) -> Dict[str, float]:
        """Run the pricing validation ``fn`` before the first step, timed."""
        t0 = self.clock()
        out = fn()
        self.outside_eval = max(self.clock() - t0, 0.0)
        return out

    def add_step(self, seconds: float) -> None:
        self.train_seconds += seconds
        self.steps += 1
        self.last_step = seconds

    def timed_eval(self, fn: Callable[[], Dict[str, float]], same_model: bool = False) -> Dict[str, float]:
        """Run the validation ``fn``, timed: its price from now on (``same_model``: a repeat at the
        step of the latest one, whose cheaper timing counts)."""
        first, t0 = self.last_eval, self.clock()
        out = fn()
        self.last_eval = self.clock() - t0
        self.evals += 1
        if same_model:
            self.last_eval = min(self.last_eval, first)
        return out

    def eval_cost(self, has_eval: bool) -> float:
        """Seconds the next validation is expected to take: the latest one's (0 before the first)."""
        return self.last_eval if (has_eval and self.evals) else 0.0

    def after_loop_seconds(self, has_eval: bool) -> float:
        """What the budget keeps after the loop: the final validation, ``evals_after`` more at its
        price, and ``reserve`` seconds."""
        final_eval = self.eval_cost(has_eval) if (self.evals or not has_eval) else self.outside_eval
        return final_eval * (1.0 + self.evals_after) + self.reserve

    def out_of_time(self, has_eval: bool) -> bool:
        """True when one more step plus what follows the loop would pass the budget."""
        if self.seconds <= 0:
            return False
        step = self.train_seconds / max(1, self.steps)
        return self.clock() + step + self.after_loop_seconds(has_eval) >= self.seconds

    def predicted_steps(self, done: int, has_eval: bool) -> float:
        """The step count the budget allows: ``done`` plus the seconds left after the final
        validation and the reserve, over a step's mean seconds plus its share of the periodic
        validations (the latest one's cost / ``eval_every``)."""
        final_eval = self.eval_cost(has_eval)
        per_step = self.train_seconds / max(1, self.steps)
        if has_eval and self.eval_every:
            per_step += final_eval / int(self.eval_every)
        left = self.seconds - self.clock() - final_eval * (1.0 + self.evals_after) - self.reserve
        return done + max(0.0, left) / max(per_step, 1e-9)

    def check(self, done: int, last_eval: Optional[int]) -> str:
        """After step ``done`` (``last_eval``: the step of the latest validation, None: none): GO on,
        CONFIRM (validate again, then :meth:`confirm`) or STOP."""
        if self.seconds <= 0:
            return GO
        self._update_horizon(done, self.has_eval)
        if done >= self.iters or not self.out_of_time(self.has_eval):
            return GO
        if self._untrained_price_says_lost(done, last_eval):
            return GO        # stopping now cannot keep the budget at a price the training may lower
        if self._price_to_confirm(done, last_eval):
            return CONFIRM
        return self._stop(done)

    def confirm(self, done: int) -> str:
        """After the validation :meth:`check` asked for at step ``done``: GO or STOP."""
        self.confirmed = done
        self._update_horizon(done, True)
        return GO if not self.out_of_time(True) else self._stop(done)

    def report(self) -> None:
        """After the loop's bar: the one-line note of a budget that left training almost nothing."""
        if self.short_note:
            print(f"l3d_app: note: {self.short_note}", file=sys.stderr)

    def counters(self) -> Dict[str, float]:
        """This loop's steps, their seconds and (when known) the latest validation's seconds."""
        out = {"steps": self.steps, "seconds": self.train_seconds}
        price = self.last_eval if self.evals else self.outside_eval
        if price > 0:
            out["eval_seconds"] = price          # a resumed run's first price of a validation
        return out

    def _update_horizon(self, done: int, has_eval: bool) -> None:
        if self.horizon is not None:
            self.horizon.update(done, self.predicted_steps(done, has_eval))

    def _stop(self, done: int) -> str:
        self.stopped = True
        self.note("train/budget", f"time budget {self.seconds:g} s: stopped at step {done}")
        if done < max(1, self.iters // 10):    # a budget that leaves training almost nothing: say so
            self.short_note = (f"time_budget={self.seconds:g} s stopped {self.desc} at step {done} of {self.iters}: "
                               f"what follows training is priced at {self.after_loop_seconds(self.has_eval):.1f} s "
                               f"(final validation, {self.evals_after:g} more validations' worth, "
                               f"reserve={self.reserve:g} s)")
        return STOP

    def _price_to_confirm(self, done: int, last_eval: Optional[int]) -> bool:
        """Whether a stop at ``done`` validates again first: the latest validation was measured once
        (not itself the repeat at step ``confirmed``) or is ``max(1, eval_every // 5)`` steps old; with
        no validation of the loop's own, the price from before ``start`` once it is that old."""
        if not self.has_eval:
            return False
        stale = max(1, int(self.eval_every or 0) // 5)
        if last_eval is None:
            return done - self.start >= stale
        return last_eval != self.confirmed or done - last_eval >= stale

    def _untrained_price_says_lost(self, done: int, last_eval: Optional[int]) -> bool:
        """Whether a stop at ``done`` waits: the price was measured on a model trained fewer than
        ``max(1, eval_every // 5)`` steps, the loop has not trained that many yet, and those steps
        and ``reserve`` still fit."""
        if not self.has_eval or self.seconds <= 0:
            return False
        early = max(1, int(self.eval_every or 0) // 5)
        priced_at = last_eval if last_eval is not None else self.start
        if priced_at >= early or done >= early:
            return False
        steps_left = (early - done) * self.train_seconds / max(1, self.steps)
        return self.clock() + steps_left + self.reserve < self.seconds
