"""The free-space stage under a time budget: it runs until the budget's stage deadline, or is skipped when that
leaves it under MIN_STAGE_SECONDS (a fake clock; hand-computed deadlines: ``final`` = a validation x (1 + the test
views in validations) + the mesh reserve)."""

from types import SimpleNamespace

import pytest

from l3d_app.runtime.budget import TimeBudget
from l3d_app.stages.free_space import MIN_STAGE_SECONDS, FreeSpaceStage


class Notes:
    def __init__(self):
        self.texts = []

    def text(self, tag, text):
        self.texts.append((tag, text))


def _before_training(budget: TimeBudget):
    """The deadline the stage fits until (its fit replaced by a recorder), or None when it skipped itself."""
    stage, seen = FreeSpaceStage(steps=10), []
    stage.fit = lambda state, ctx, deadline: seen.append(deadline) or "free rays"
    ctx = SimpleNamespace(logger=Notes(), stopwatch=SimpleNamespace(stage=lambda name: _Null(), stages={}),
                          path=lambda name: None)
    assert stage.before_training(SimpleNamespace(needed={"free_rays"}, resuming=False, products={}), ctx, budget)
    assert stage.skipped == (not seen)
    return seen[0] if seen else None


class _Null:
    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False


def _budget(seconds, elapsed, price, evals_after=38.0, reserve=35.0):
    return TimeBudget(seconds, reserve, clock=lambda: elapsed, evals_after=evals_after, eval_price=price)


def test_no_budget_means_no_limit():
    assert _before_training(_budget(0.0, 12.0, 5.0)) == 0.0


def test_unknown_evaluation_cost_keeps_the_third():
    assert _before_training(_budget(590.0, 10.0, None)) == pytest.approx(590.0 / 3.0)


def test_a_dear_evaluation_takes_half_of_what_it_leaves():
    # final = 4.7 x 39 + 35 = 218.3; 10 + (590 - 10 - 218.3) / 2 = 190.85
    assert _before_training(_budget(590.0, 10.0, 4.7)) == pytest.approx(190.85)


def test_the_stage_is_skipped_when_its_share_is_too_short():
    assert MIN_STAGE_SECONDS == 90.0
    # final = 17 x 25.5 + 35 = 468.5; 20 + (590 - 20 - 468.5) / 2 = 70.75: 50.75 s of stage
    assert _before_training(_budget(590.0, 20.0, 17.0, evals_after=24.5)) is None
    assert _before_training(_budget(590.0, 15.0, 40.0, evals_after=24.5)) is None   # the final work alone is over
