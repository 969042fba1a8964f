"""VolSDF's linear quadrature (render/sdf/densities.py): the exact mean of Psi_beta(-f) along a linear SDF
against a float64 trapezoid rule, its gradients against autograd through that rule, the segment-end
interpolation by hand, and a ray through a plane whose optical depth no longer hinges on where its
samples fall when beta is below their spacing."""

import math

import pytest
import torch

from l3d_app.render.sdf.densities import LaplaceDensity, laplace_cdf, linear_segment_ends, mean_laplace_cdf

S = torch.linspace(0, 1, 100001, dtype=torch.float64)


def _dense_mean(a, b, beta):
    return torch.stack([torch.trapezoid(laplace_cdf(-(x + (y - x) * S), beta), S) for x, y in zip(a, b)])


CASES = [(0.02, -0.02), (0.01, 0.0), (-0.01, -0.02), (0.003, 0.0030001), (-0.5, -0.51), (0.5, 0.49), (0.001, 0.001),
         (0.0, 0.0), (-0.004, 0.006), (2.0, -2.0)]


@pytest.mark.parametrize("beta", [0.0025, 0.005, 0.1])
def test_mean_laplace_cdf_is_the_dense_integral(beta):
    a = torch.tensor([c[0] for c in CASES], dtype=torch.float64)
    b = torch.tensor([c[1] for c in CASES], dtype=torch.float64)
    got = mean_laplace_cdf(a, b, beta)
    torch.testing.assert_close(got, _dense_mean(a, b, beta), atol=2e-7, rtol=0)
    assert torch.all((got >= 0) & (got <= 1))


def test_mean_laplace_cdf_gradients_match_the_dense_rule_and_stay_finite():
    beta = 0.005
    a = torch.tensor([0.02, 0.004, -0.3, 0.001, 0.0], dtype=torch.float64, requires_grad=True)
    b = torch.tensor([-0.01, 0.0041, -0.31, 0.001, 0.0], dtype=torch.float64, requires_grad=True)
    ga, gb = torch.autograd.grad(mean_laplace_cdf(a, b, beta).sum(), (a, b))
    a2, b2 = a.detach().clone().requires_grad_(), b.detach().clone().requires_grad_()
    wa, wb = torch.autograd.grad(_dense_mean(a2, b2, beta).sum(), (a2, b2))
    torch.testing.assert_close(ga, wa, atol=1e-4, rtol=1e-3)
    torch.testing.assert_close(gb, wb, atol=1e-4, rtol=1e-3)
    # float32, huge and equal values: finite values and gradients (no 0/0, no overflow)
    x = torch.tensor([1e3, -1e3, 0.0, 1e-9], requires_grad=True)
    y = torch.tensor([1e3, -1e3 + 1.0, 0.0, -1e-9], requires_grad=True)
    out = mean_laplace_cdf(x, y, 1e-4)
    gx, gy = torch.autograd.grad(out.sum(), (x, y))
    assert torch.isfinite(out).all() and torch.isfinite(gx).all() and torch.isfinite(gy).all()
    torch.testing.assert_close(out[:3], torch.tensor([0.0, 1.0, 0.5]))


def test_segment_ends_interpolate_towards_the_next_sample_of_the_same_ray():
    sdf = torch.tensor([0.3, 0.1, -0.1, 0.5, 0.2])
    t0 = torch.tensor([1.0, 1.2, 1.4, 2.0, 2.5])
    t1 = torch.tensor([1.1, 1.4, 1.5, 2.5, 2.6])      # the first segment capped halfway to its next sample
    rays = torch.tensor([0, 0, 0, 1, 1])
    want = torch.tensor([0.2, -0.1, -0.1, 0.2, 0.2])  # 0.3 + (0.1 - 0.3) x 0.5; full; last of ray 0; full; last of ray 1
    torch.testing.assert_close(linear_segment_ends(sdf, t0, t1, rays), want)
    assert linear_segment_ends(sdf[:0], t0[:0], t1[:0], rays[:0]).numel() == 0


def test_a_plane_between_samples_is_integrated_exactly_at_any_phase():
    """f = 0.3 - t along a ray (a plane at t = 0.3), beta 0.0025, samples every 0.02 (8 beta) from a
    phase-shifted start: the linear rule's optical depth up to the last sample is the analytic one at
    every phase; the left rule's changes with the phase by more than 1 (a transmittance factor e)."""
    beta, h = 0.0025, 0.02
    g = lambda x: 0.5 * beta * math.exp(x / beta) if x <= 0 else x + 0.5 * beta * math.exp(-x / beta)  # noqa: E731
    lin = LaplaceDensity(beta, None, learnable=False, beta_min=0.0, quadrature="linear")
    left = LaplaceDensity(beta, None, learnable=False, beta_min=0.0, quadrature="left")
    left_totals = []
    for phase in (0.0, 0.2, 0.4, 0.6, 0.8):
        t0 = (torch.arange(40, dtype=torch.float64) + phase) * h
        t1 = t0 + h
        sdf, rays = 0.3 - t0, torch.zeros(40, dtype=torch.long)
        # exact optical depth from t0[0] to the last sample, alpha = 1 / beta (the last segment, with no next
        # sample, keeps its start value: deep inside, its density is alpha to exp(-0.4 / beta))
        want = (g(float(t0[-1]) - 0.3) - g(float(t0[0]) - 0.3)) / beta
        tau = lin.optical_depth(sdf, t0, t1, rays)
        assert float(tau[:-1].sum()) == pytest.approx(want, rel=1e-6)
        left_totals.append(float(left.optical_depth(sdf, t0, t1, rays)[:-1].sum()) - want)
    assert max(left_totals) - min(left_totals) > 1.0
    with pytest.raises(ValueError, match="quadrature"):
        LaplaceDensity(beta, None, quadrature="midpoint")
