"""Rectified stereo: disparity <-> depth and the propagation of disparity errors."""

import pytest
import torch

from l3d_app.errors import UserError
from l3d_app.geometry.stereo import (depth_error_from_disparity_error, depth_to_disparity,
                                     disparity_to_depth)

F, B = 720.0, 0.12  # pixels, metres


def test_known_value():
    # f B = 86.4: disparity 86.4 px is 1 m, 8.64 px is 10 m
    d = torch.tensor([86.4, 8.64, 43.2], dtype=torch.float64)
    assert torch.allclose(disparity_to_depth(d, F, B), torch.tensor([1.0, 10.0, 2.0], dtype=torch.float64))


def test_round_trips():
    g = torch.Generator().manual_seed(0)
    depth = torch.rand(1000, generator=g, dtype=torch.float64) * 50 + 0.1
    assert torch.allclose(disparity_to_depth(depth_to_disparity(depth, F, B), F, B), depth, rtol=1e-12)
    disp = torch.rand(1000, generator=g, dtype=torch.float64) * 200 + 0.01
    assert torch.allclose(depth_to_disparity(disparity_to_depth(disp, F, B), F, B), disp, rtol=1e-12)
    # tensor calibration, broadcast per image of a batch
    f = torch.tensor([[500.0], [900.0]], dtype=torch.float64)
    d2 = disp.reshape(2, 500)
    assert torch.allclose(depth_to_disparity(disparity_to_depth(d2, f, B), f, B), d2, rtol=1e-12)


def test_invalid_disparities():
    d = torch.tensor([0.0, -3.0, float("nan"), float("inf"), 10.0], requires_grad=True)
    depth, valid = disparity_to_depth(d, F, B, return_valid=True)
    assert valid.tolist() == [False, False, False, False, True]
    assert torch.isinf(depth[:4]).all() and bool((depth[:4] > 0).all())
    assert not torch.isnan(depth).any()
    depth[valid].sum().backward()
    assert torch.isfinite(d.grad).all()
    assert d.grad[:4].abs().sum() == 0
    assert torch.isclose(d.grad[4], torch.tensor(-F * B / 100))


def test_invalid_depths():
    z = torch.tensor([float("inf"), 0.0, -1.0, float("nan"), 2.0])
    disp, valid = depth_to_disparity(z, F, B, return_valid=True)
    assert valid.tolist() == [False, False, False, False, True]
    assert disp[:4].tolist() == [0.0, 0.0, 0.0, 0.0]  # inf depth is disparity 0 exactly
    assert torch.isinf(disparity_to_depth(disp[:4], F, B)).all()


def test_bad_calibration_is_a_user_error():
    with pytest.raises(UserError):
        disparity_to_depth(torch.ones(3), 0.0, B)
    with pytest.raises(UserError):
        depth_to_disparity(torch.ones(3), F, -0.1)
    with pytest.raises(UserError):
        depth_error_from_disparity_error(torch.ones(3), F, float("nan"), 0.5)


def test_error_grows_quadratically_with_depth():
    z = torch.tensor([1.0, 2.0, 5.0, 10.0], dtype=torch.float64)
    err = depth_error_from_disparity_error(z, F, B, 0.25)
    assert torch.allclose(err, z ** 2 / (F * B) * 0.25)
    two = depth_error_from_disparity_error(2 * z, F, B, 0.25)
    assert torch.allclose(two / err, torch.full_like(z, 4.0))
    # halving the error needs twice the baseline (or focal length)
    assert torch.allclose(depth_error_from_disparity_error(z, F, 2 * B, 0.25), err / 2)
    assert torch.allclose(depth_error_from_disparity_error(z, 2 * F, B, 0.25), err / 2)


def test_exact_matches_first_order_for_small_errors():
    z = torch.linspace(0.5, 20.0, 50, dtype=torch.float64)
    for dd in (1e-3, -1e-3, 1e-2):
        first = depth_error_from_disparity_error(z, F, B, dd)
        exact = depth_error_from_disparity_error(z, F, B, dd, exact=True)
        # the exact error is Z^2 dd / (fB - Z dd): relative gap = Z dd / (fB - Z dd)
        gap = (z * dd / (F * B - z * dd)).abs()
        assert torch.allclose(exact, first * (1 + z * dd / (F * B - z * dd)), rtol=1e-9)
        assert bool(((exact - first).abs() <= 1.01 * gap * first.abs()).all())
        assert float(gap.max()) < 5e-3
    # and differ at large errors: under-estimated disparity grows depth more than linearly
    big_first = depth_error_from_disparity_error(z, F, B, 2.0)
    big_exact = depth_error_from_disparity_error(z, F, B, 2.0, exact=True)
    assert bool((big_exact > big_first).all())


def test_exact_error_beyond_infinity_and_invalid_depth():
    # true disparity at 86.4 m is 1 px; an error of 1 px or more puts it at infinity
    z = torch.tensor([86.4, 86.4, 1.0, 0.0, float("inf"), float("nan")], dtype=torch.float64)
    dd = torch.tensor([1.0, 1.5, 0.0, 0.1, 0.1, 0.1], dtype=torch.float64)
    exact = depth_error_from_disparity_error(z, F, B, dd, exact=True)
    first = depth_error_from_disparity_error(z, F, B, dd)
    assert torch.isinf(exact[:2]).all()
    assert exact[2] == 0
    assert torch.isinf(exact[3:]).all() and torch.isinf(first[3:]).all()
    assert not torch.isnan(exact).any() and not torch.isnan(first).any()
