"""coverage_bce: BCE of a ray's opacity against the image's alpha, written in optical depth.
References: the textbook BCE on the opacity in float64, and its analytic gradients."""

import math

import torch

from l3d_app.losses.occupancy import coverage_bce
from l3d_app.render.volume.renderer import composite


def naive_bce(tau, m, eps):
    """Float64 BCE on p = 1 - exp(-tau) (the positive term at tau + eps), term by term."""
    out = []
    for t, y in zip(tau.tolist(), m.tolist()):
        p_pos = 1.0 - math.exp(-(t + eps))
        out.append(-y * math.log(p_pos) - (1.0 - y) * math.log(math.exp(-t)))
    return sum(out) / len(out)


def test_matches_the_textbook_bce_where_it_is_representable():
    tau = torch.tensor([0.0, 1e-3, 0.1, 1.0, 3.0, 10.0], dtype=torch.float64)
    for m in (torch.zeros(6), torch.ones(6), torch.tensor([0.0, 0.25, 0.5, 0.75, 1.0, 0.3])):
        got = coverage_bce(tau, m.double(), eps=1e-3)
        assert abs(float(got) - naive_bce(tau, m.double(), 1e-3)) < 1e-12


def test_a_saturated_ray_that_should_be_empty_still_gets_gradient_one():
    # tau = 50 or 1e4: opacity is exactly 1.0 in float32, a BCE on it has no gradient; here
    # d loss / d tau = (1 - m) / R exactly, and ~0 for rays that should be covered
    tau = torch.tensor([50.0, 1e4, 50.0, 1e4], requires_grad=True)
    m = torch.tensor([0.0, 0.0, 1.0, 1.0])
    assert float(1 - torch.exp(-tau[0].detach())) == 1.0
    loss = coverage_bce(tau, m)
    (g,) = torch.autograd.grad(loss, tau)
    assert torch.isfinite(loss)
    torch.testing.assert_close(g, torch.tensor([0.25, 0.25, 0.0, 0.0]), atol=1e-12, rtol=0)
    # through the compositor: densities of an empty-target ray get d/d sigma_i = delta_i / R
    sigma = torch.full((1, 4), 1e3, requires_grad=True)
    out = composite(torch.zeros(1, 4, 3), torch.arange(4.0)[None], sigmas=sigma, deltas=torch.full((1, 4), 0.5))
    (gs,) = torch.autograd.grad(coverage_bce(out["optical_depth"], torch.zeros(1)), sigma)
    torch.testing.assert_close(gs, torch.full((1, 4), 0.5))


def test_an_empty_ray_that_should_be_covered_is_pushed_hard_and_stays_finite():
    tau = torch.tensor([0.0], requires_grad=True)
    loss = coverage_bce(tau, torch.ones(1), eps=1e-3)
    (g,) = torch.autograd.grad(loss, tau)
    # d/dtau -log(1 - e^-(tau+eps)) = -e^-eps / (1 - e^-eps) at tau = 0
    expected = -math.exp(-1e-3) / (1 - math.exp(-1e-3))
    assert abs(float(loss.detach()) + math.log(1 - math.exp(-1e-3))) < 1e-4
    assert abs(float(g) - expected) < 1e-3 * abs(expected)
