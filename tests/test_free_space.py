"""The occupied-volume priors (losses/free_space.py): against a ball's analytic depth integral and
volume share, and their analytic gradients (inside only; at the boundary only)."""

import math

import pytest
import torch

from l3d_app.losses.free_space import occupied_fraction, occupied_volume


def test_sphere_value_matches_the_analytic_integral():
    # f = |x| - r on the box [-1, 1]^3: integral over the ball of (r - |x|) = pi r^4 / 3,
    # so E[max(0, -f)] over the box = pi r^4 / (3 * 8)
    g = torch.Generator().manual_seed(0)
    x = torch.rand(2_000_000, 3, generator=g, dtype=torch.float64) * 2 - 1
    r = 0.6
    value = float(occupied_volume(x.norm(dim=-1) - r))
    expected = math.pi * r ** 4 / 24
    assert abs(value - expected) < 0.02 * expected      # about 8 standard errors of the mean (4.3e-5)


def test_gradient_only_inside_and_equal_per_point():
    f = torch.tensor([-0.3, -1e-3, 0.0, 0.2, 5.0], dtype=torch.float64, requires_grad=True)
    occupied_volume(f).backward()
    assert torch.equal(f.grad, torch.tensor([-0.2, -0.2, 0.0, 0.0, 0.0], dtype=torch.float64))
    assert float(occupied_volume(torch.tensor([0.0, 1.0, 3.0]))) == 0.0


def test_occupied_fraction_is_the_inside_share_and_pushes_at_the_boundary():
    g = torch.Generator().manual_seed(1)
    x = torch.rand(400_000, 3, generator=g, dtype=torch.float64) * 2 - 1
    r = 0.6
    share = float(occupied_fraction(x.norm(dim=-1) - r, softness=1e-4))
    expected = (4 / 3) * math.pi * r ** 3 / 8
    assert abs(share - expected) < 0.03 * expected                    # about 7 standard errors (5e-4)
    f = torch.tensor([-1.0, -0.01, 0.0, 0.01, 1.0], dtype=torch.float64, requires_grad=True)
    occupied_fraction(f, softness=0.01).backward()
    s = torch.sigmoid(torch.tensor([1.0, 0.0, -1.0], dtype=torch.float64))
    expect_mid = -(s * (1 - s)) / 0.01 / 5                            # d/df sigmoid(-f/h) / N
    assert torch.allclose(f.grad[1:4], expect_mid)
    assert abs(float(f.grad[0])) < 1e-40 and abs(float(f.grad[4])) < 1e-40   # far from the boundary: none
    with pytest.raises(ValueError):
        occupied_fraction(f, softness=0.0)
