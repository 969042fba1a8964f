"""Under a time budget the turntables take what is left after the test views: counts by hand."""

from types import SimpleNamespace

import pytest
from omegaconf import OmegaConf

from l3d_app.tasks.field_common import evals_after_training, gif_frames_in_budget, turntable_frames_that_fit


def test_all_frames_without_a_budget():
    assert turntable_frames_that_fit(36, None, 1.0, 128, gifs=2) == 36
    assert turntable_frames_that_fit(0, 5.0, 1e-4, 128) == 0


@pytest.mark.parametrize("left,expected", [(100.0, 36), (10.0, 36), (5.0, 24), (2.0, 9), (1.5, 0), (-3.0, 0)])
def test_frames_that_fit_the_time_left(left, expected):
    """1e-4 s per ray, 32 px frames, two gifs: 2 x 1024 x 1e-4 = 0.2048 s per frame; fewer than 8: none."""
    assert turntable_frames_that_fit(36, left, 1e-4, 32, gifs=2) == expected


def test_a_short_turntable_is_kept_whole_when_it_fits():
    assert turntable_frames_that_fit(4, 1.0, 1e-4, 32, gifs=2) == 4      # 4 asked, 4 fit (0.82 s)
    assert turntable_frames_that_fit(4, 0.5, 1e-4, 32, gifs=2) == 0      # 2 fit: fewer than asked and than 8


class _Log:
    def __init__(self):
        self.notes = []

    def text(self, tag, value):
        self.notes.append((tag, value))


def _ctx(test_seconds, elapsed):
    return SimpleNamespace(stopwatch=SimpleNamespace(stages={"test": test_seconds}, elapsed=elapsed), logger=_Log())


def test_the_task_helper_reads_the_test_views_cost_and_the_budget():
    cfg = OmegaConf.create({"gif_frames": 36, "time_budget": 590})
    # 20 test views of 64 x 64 at 2 x 2 rays = 327680 rays in 32.768 s: 1e-4 s per ray; 32 px frames
    ctx = _ctx(32.768, 585.0)                             # 5 s left: 24 frames of two gifs
    assert gif_frames_in_budget(cfg, ctx, 2, 327680, 32) == 24
    assert ctx.logger.notes and ctx.logger.notes[0][0] == "gifs" and "24 of 36" in ctx.logger.notes[0][1]
    ctx = _ctx(32.768, 100.0)                             # plenty left: all, no note
    assert gif_frames_in_budget(cfg, ctx, 2, 327680, 32) == 36 and not ctx.logger.notes
    ctx = _ctx(32.768, 600.0)                             # over budget already: none
    assert gif_frames_in_budget(cfg, ctx, 2, 327680, 32) == 0 and "no gif" in ctx.logger.notes[0][1]
    no_budget = OmegaConf.create({"gif_frames": 36, "time_budget": 0})
    assert gif_frames_in_budget(no_budget, _ctx(32.768, 10_000.0), 2, 327680, 32) == 36


def test_the_loop_reserve_holds_the_test_views_only():
    """4 val views at one ray, 20 test views at 2 x 2 rays: 20 x 4 / 4 = 20 validations (no gif frames)."""
    assert evals_after_training(4, 20, 0, 0, (128, 128), 2, 1) == pytest.approx(20.0)
    assert evals_after_training(4, 20, 72, 128, (128, 128), 2, 1) == pytest.approx(38.0)
