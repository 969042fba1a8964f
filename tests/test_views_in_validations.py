"""The rendering a field task keeps time for after its loop, in units of one validation evaluation:
ray counts written out by hand (test views at their supersampling) over the validation's rays at
its own supersampling; the turntables are not kept for (tests/test_turntable_budget.py)."""
import pytest

from l3d_app.runtime.budget import views_in_validations


def test_same_supersampling_counts_views():
    # 20 test views of 128x128 at 2x2 over 4 val views of 128x128 at 2x2
    expected = (20 * 128 * 128 * 4) / (4 * 128 * 128 * 4)
    assert views_in_validations(4, 20, 2) == pytest.approx(expected)
    assert expected == pytest.approx(5.0)


def test_cheaper_validation_scales_the_reserve_by_the_ray_ratio():
    # val at 1 ray per pixel, test at 2x2: each test view costs 4 val views' worth of one view
    expected = (20 * 256 * 256 * 4) / (4 * 256 * 256 * 1)
    got = views_in_validations(4, 20, supersample=2, val_supersample=1)
    assert got == pytest.approx(expected) and got == pytest.approx(20.0)


def test_no_val_supersample_means_the_test_one():
    assert views_in_validations(4, 20, 3) == views_in_validations(4, 20, 3, 3)
    assert views_in_validations(4, 20, 3, 1) == pytest.approx(45.0)
