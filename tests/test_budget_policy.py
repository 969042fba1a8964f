"""The time-budget policy's own arithmetic (runtime/budget.py), on a fake clock: what it keeps for the
work after training, the steps that still fit, a stage's deadline, the seconds left. Figures by hand."""

import pytest

from l3d_app.runtime.budget import CONFIRM, GO, STOP, TimeBudget, renders_in_validations


class Clock:
    def __init__(self, now=0.0):
        self.now = now

    def __call__(self):
        return self.now


def test_declared_work_is_priced_in_validations():
    timer = TimeBudget(100.0, reserve=5.0)
    timer.keep_renders(20 * 4, 4)                   # 20 test views at 2 x 2 rays over 4 one-ray val views
    timer.keep_renders(96 ** 3, 1000, margin=1.25)  # a grid's points over 1000 val points, with a margin
    assert timer.evals_after == pytest.approx(20.0 + 1.25 * 884.736)
    assert renders_in_validations(5, 0) == 5.0      # nothing per validation counts as one unit
    clock = Clock(10.0)
    timer = TimeBudget(100.0, reserve=5.0, clock=clock, evals_after=3.0)
    timer.begin(0, 50, True, 10)
    timer.add_step(2.0)
    timer.timed_eval(lambda: (setattr(clock, "now", clock.now + 4.0), {})[1])
    # what follows the loop: the final validation (4 s) and 3 more at its price, and 5 s
    assert timer.after_loop_seconds(True) == pytest.approx(4.0 * 4 + 5.0)
    assert timer.counters() == {"steps": 1, "seconds": 2.0, "eval_seconds": 4.0}


def test_the_steps_that_fit_follow_the_recent_pace():
    clock = Clock(40.0)
    assert TimeBudget(0.0, clock=clock).steps_that_fit([1.0, 1.0]) is None          # no budget
    assert TimeBudget(100.0, clock=clock).steps_that_fit([]) is None                # no step timed
    # 100 s - 10 s reserve - 40 s spent = 50 s at a mean of 0.5 s a step: 100 steps
    assert TimeBudget(100.0, reserve=10.0, clock=clock).steps_that_fit([0.4, 0.6]) == 100


def test_a_stage_before_training_gets_a_deadline():
    clock = Clock(10.0)
    assert TimeBudget(0.0, clock=clock).stage_deadline(5.0, 20.0) == 0.0             # no budget: no limit
    assert TimeBudget(590.0, clock=clock).stage_deadline(None, 20.0) == pytest.approx(590.0 / 3)
    # final work 4.7 x (1 + 38) + 35 = 218.3 s: half of what it leaves, 10 + (590 - 10 - 218.3) / 2 = 190.85
    timer = TimeBudget(590.0, reserve=35.0, clock=clock, evals_after=38.0)
    assert timer.stage_deadline(4.7, 20.0) == pytest.approx(190.85)
    assert timer.stage_deadline(17.0, 20.0) is None                                   # under 20 s left for it


def test_seconds_left_and_a_validation_timed_by_the_task():
    clock = Clock(30.0)
    timer = TimeBudget(100.0, clock=clock)
    assert timer.seconds_left() == 70.0 and TimeBudget(0.0, clock=clock).seconds_left() is None

    def validate():
        clock.now += 7.0
        return "picture"
    assert timer.time_validation(validate) == "picture" and timer.eval_price == 7.0
    # the loop then needs no pricing validation of its own
    assert timer.begin(0, 10, True, 5) is False and timer.after_loop_seconds(True) == 7.0


def test_a_validation_priced_on_a_part_and_a_picture_before_training_that_fits_or_not():
    clock = Clock(10.0)
    timer = TimeBudget(590.0, reserve=5.0, clock=clock, evals_after=1.75)

    def part():
        clock.now += 3.0
        return 1.0 / 16                              # a 16th of a validation's rays in 3 s
    assert timer.price_from_part(part) == pytest.approx(48.0) and timer.eval_price == pytest.approx(48.0)
    assert timer.begin(0, 10, True, 5) is False      # the loop takes that price: no pricing validation
    # at 13 s: a 48 s picture ends by min(590 / 3, 13 + (590 - 13 - 48 x 2.75 - 5) / 2) = 196.67: it fits
    assert timer.fits_before_training(48.0)
    # 200 s: final work 200 x 2.75 + 5 = 555 s leaves 13 + (590 - 13 - 555) / 2 = 24 s: it does not
    assert not timer.fits_before_training(200.0)
    # the largest that fits: 13 + (572 - 2.75 p) / 2 >= 13 + p  <=>  p <= 572 / 4.75 = 120.4 s
    assert timer.fits_before_training(120.0) and not timer.fits_before_training(121.0)
    assert TimeBudget(0.0, clock=clock).fits_before_training(1e9)       # no budget: always


def test_the_verdicts_of_a_loop_near_its_budget():
    """Steps of 10 s, budget 100 s, no validation: GO while one more step fits, then STOP; a
    validated loop first asks to CONFIRM its price, then stops on it."""
    clock = Clock()
    timer = TimeBudget(100.0, clock=clock)
    timer.begin(0, 50, False, 0)
    verdicts = []
    for done in range(1, 11):
        clock.now += 10.0
        timer.add_step(10.0)
        verdicts.append(timer.check(done, None))
        if verdicts[-1] == STOP:
            break
    assert verdicts == [GO] * 8 + [STOP] and timer.stopped        # 90 s + 10 s >= 100 s at step 9
    clock = Clock()
    timer = TimeBudget(100.0, clock=clock, eval_price=5.0)
    assert timer.begin(0, 50, True, 5) is False
    clock.now, timer.steps, timer.train_seconds = 90.0, 8, 80.0
    assert timer.check(8, None) == CONFIRM                        # 90 + 10 + 5 >= 100, a price never repeated
    clock.now += 5.0
    timer.timed_eval(lambda: {}, same_model=False)
    assert timer.confirm(8) == STOP and timer.short_note == ""    # 8 of 50: not under a tenth
