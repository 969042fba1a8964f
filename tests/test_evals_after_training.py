"""The rendering after a field task's loop, in units of one validation evaluation: ray
counts written out by hand (test views at their supersampling, turntable frames at one ray
per pixel) over the validation's rays at its own supersampling."""
import pytest

from l3d_app.tasks.field_common import evals_after_training


def test_same_supersampling_counts_views_and_frames():
    # 20 test views of 128x128 at 2x2 + 72 frames of 128^2, over 4 val views of 128x128 at 2x2
    expected = (20 * 128 * 128 * 4 + 72 * 128 * 128) / (4 * 128 * 128 * 4)
    assert evals_after_training(4, 20, 72, 128, (128, 128), 2) == pytest.approx(expected)
    assert expected == pytest.approx(9.5)


def test_cheaper_validation_scales_the_reserve_by_the_ray_ratio():
    # val at 1 ray per pixel, test at 2x2: each test view costs 4 val views' worth of one view
    expected = (20 * 256 * 256 * 4 + 72 * 128 * 128) / (4 * 256 * 256 * 1)
    got = evals_after_training(4, 20, 72, 128, (256, 256), supersample=2, val_supersample=1)
    assert got == pytest.approx(expected) and got == pytest.approx(24.5)


def test_no_val_supersample_means_the_test_one():
    assert evals_after_training(4, 20, 0, 0, (64, 64), 3) == evals_after_training(4, 20, 0, 0, (64, 64), 3, 3)
