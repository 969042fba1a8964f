"""StageBudget.deadline: where a stage before training (volsdf's free-space fit) must stop under a time budget
(hand-computed; ``final`` = the last validation x (1 + the test views in validations) + the reserve)."""

import pytest

from l3d_app.stages.base import MIN_STAGE_SECONDS, StageBudget


def test_no_budget_means_no_limit():
    assert StageBudget(0.0, 5.0 * 41 + 35).deadline(12.0) == 0.0


def test_unknown_evaluation_cost_keeps_the_third():
    assert StageBudget(590.0, None).deadline(10.0) == pytest.approx(590.0 / 3.0)


def test_a_cheap_evaluation_leaves_the_third():
    # final = 1 x (1 + 38) + 35 = 74; half of 590 - 10 - 74 = 253 -> 263 > 196.67
    assert StageBudget(590.0, 74.0).deadline(10.0) == pytest.approx(590.0 / 3.0)


def test_a_dear_evaluation_takes_half_of_what_it_leaves():
    # 128 px with a fuzzy start: final = 4.7 x 39 + 35 = 218.3; 10 + (590 - 10 - 218.3) / 2 = 190.85
    assert StageBudget(590.0, 218.3).deadline(10.0) == pytest.approx(190.85)


def test_the_stage_is_skipped_when_its_share_is_too_short():
    assert MIN_STAGE_SECONDS == 90.0
    # final = 17 x 25.5 + 35 = 468.5; 20 + (590 - 20 - 468.5) / 2 = 70.75: 50.75 s of stage
    assert StageBudget(590.0, 468.5).deadline(20.0) is None
    assert StageBudget(590.0, 468.5).deadline(20.0, minimum=30.0) == pytest.approx(70.75)
    # final = 19 x 25.5 + 35 = 519.5; 15 + (590 - 15 - 519.5) / 2 = 42.75, only 27.75 s of stage
    assert StageBudget(590.0, 519.5).deadline(15.0) is None
    assert StageBudget(590.0, 519.5).deadline(15.0, minimum=27.0) == pytest.approx(42.75)
    assert StageBudget(590.0, 40.0 * 25.5 + 35).deadline(15.0) is None      # the final work alone is over budget
