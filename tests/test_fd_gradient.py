"""The finite-difference SDF gradient (models/sdf_grid.py ``finite_difference_gradient`` and
``SDFGridField(gradient="fd")``) against autograd and hand-derived derivatives, never
against itself."""

from __future__ import annotations

import pytest
import torch

from l3d_app.models.sdf_grid import SDFGridField, finite_difference_gradient

D = torch.float64


def _cubic(p: torch.Tensor) -> torch.Tensor:
    x, y, z = p.unbind(-1)
    return x ** 3 + x * y * z + 2 * y ** 2 * z - z ** 3


def _cubic_grad(p: torch.Tensor) -> torch.Tensor:
    """By hand."""
    x, y, z = p.unbind(-1)
    return torch.stack([3 * x ** 2 + y * z, x * z + 4 * y * z, x * y + 2 * y ** 2 - 3 * z ** 2], -1)


@pytest.mark.parametrize("h", [1e-2, 1e-3])
def test_central_differences_have_the_exact_h2_error_term_on_a_cubic(h):
    """Central differences of a cubic: error exactly h^2 / 6 * d^3f/dx_a^3 per axis
    (6 for x, 0 for y, -6 for z), so the O(h^2) order and the step are both checked."""
    x = torch.rand(64, 3, generator=torch.Generator().manual_seed(0), dtype=D) * 2 - 1
    g_fd = finite_difference_gradient(_cubic, x, h)
    exact = _cubic_grad(x)
    xr = x.clone().requires_grad_(True)
    (g_auto,) = torch.autograd.grad(_cubic(xr).sum(), xr)
    torch.testing.assert_close(g_auto, exact, atol=1e-14, rtol=0)
    err = torch.tensor([6.0, 0.0, -6.0], dtype=D) * h * h / 6
    torch.testing.assert_close(g_fd - exact, err.expand_as(exact), atol=1e-10, rtol=0)


def _smooth_sdf_net():
    torch.manual_seed(0)
    return torch.nn.Sequential(torch.nn.Linear(3, 16), torch.nn.Softplus(beta=5), torch.nn.Linear(16, 16),
                               torch.nn.Softplus(beta=5), torch.nn.Linear(16, 1)).double()


def test_fd_gradient_and_its_parameter_gradient_match_autograd_on_a_smooth_network():
    """Spatial gradient: FD = autograd + O(h^2). The eikonal loss built on the FD gradient is
    differentiable in the network's parameters, and that parameter gradient is the autograd
    one (double backward) + O(h^2)."""
    net = _smooth_sdf_net()
    sdf = lambda p: net(p)[:, 0]  # noqa: E731
    x = torch.rand(50, 3, generator=torch.Generator().manual_seed(1), dtype=D) * 2 - 1
    xr = x.clone().requires_grad_(True)
    (g_auto,) = torch.autograd.grad(sdf(xr).sum(), xr, create_graph=True)
    h = 1e-4
    g_fd = finite_difference_gradient(sdf, x, h)
    torch.testing.assert_close(g_fd, g_auto, atol=1e-6, rtol=1e-6)
    params = list(net.parameters())[:-1]                     # the output bias does not move the gradient
    eik = lambda g: ((g.norm(dim=-1) - 1) ** 2).mean()  # noqa: E731
    p_auto = torch.autograd.grad(eik(g_auto), params)
    p_fd = torch.autograd.grad(eik(g_fd), params)
    for a, b in zip(p_auto, p_fd):
        assert float(a.abs().max()) > 0
        torch.testing.assert_close(b, a, atol=1e-6, rtol=1e-5)


def test_grid_field_fd_mode_matches_autograd_of_the_field_inside_cells():
    """SDFGridField(gradient="fd") against autograd of the same field's sdf. The grid is
    trilinear per cell, so central differences whose stencil stays in one cell at every level
    are exact up to the MLP's O(h^2); with h = 1e-6 almost every point qualifies."""
    torch.manual_seed(0)
    box = ((-1.0, -1.0, -1.0), (1.0, 1.0, 1.0))
    field = SDFGridField(scene_box=box, n_levels=4, base_resolution=4, max_resolution=40, log2_hashmap_size=12,
                         hidden=16, n_layers=2, sdf_features=3, color_hidden=8, color_layers=1, gradient="fd",
                         fd_step=1e-6).double()
    with torch.no_grad():
        field.encoding.table.uniform_(-0.3, 0.3)
        field.layers[0].weight.normal_(0.0, 0.5)
    x = torch.rand(300, 3, generator=torch.Generator().manual_seed(2), dtype=D) * 1.8 - 0.9
    g_fd = field.sdf_features_gradient(x)[2]
    xr = x.clone().requires_grad_(True)
    (g_auto,) = torch.autograd.grad(field.sdf(xr).sum(), xr)
    assert float(g_auto.norm(dim=-1).mean()) > 0.1
    err = (g_fd - g_auto).norm(dim=-1) / (1 + g_auto.norm(dim=-1))
    assert float((err < 1e-5).double().mean()) > 0.97, float(err.max())
