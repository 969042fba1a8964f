"""gather_rows (index_select forward, bincount backward) against a naive float64 sum, and the grid
SDF's parameter gradients through its analytic spatial gradient against autograd's double backward."""

import torch

from l3d_app.losses.eikonal import eikonal_loss, sdf_gradient
from l3d_app.models.sdf_grid import SDFGridField
from l3d_app.models.table_gather import gather_rows

D = torch.float64


def test_gather_rows_values_and_gradient_against_a_naive_sum():
    torch.manual_seed(0)
    table = torch.randn(7, 3, requires_grad=True)
    index = torch.tensor([0, 3, 3, 6, 0, 3, 2, 2, 2, 2])              # repeats; rows 1, 4 and 5 never read
    upstream = torch.randn(len(index), 3)
    out = gather_rows(table, index)
    torch.testing.assert_close(out, table.detach()[index], atol=0, rtol=0)
    (grad,) = torch.autograd.grad((out * upstream).sum(), table)
    naive = [[0.0] * 3 for _ in range(7)]                              # plain Python sums in float64
    for m, r in enumerate(index.tolist()):
        for f in range(3):
            naive[r][f] += float(upstream[m, f])
    torch.testing.assert_close(grad, torch.tensor(naive, dtype=torch.float32), atol=1e-6, rtol=0)
    assert grad.dtype == table.dtype and bool((grad[[1, 4, 5]] == 0).all())


def test_gather_rows_without_gradients_is_a_plain_index_select():
    table = torch.arange(12.0).reshape(6, 2)
    out = gather_rows(table, torch.tensor([5, 0, 5]))
    assert out.grad_fn is None and out.tolist() == [[10.0, 11.0], [0.0, 1.0], [10.0, 11.0]]
    with torch.no_grad():
        assert gather_rows(table.requires_grad_(True), torch.tensor([1])).grad_fn is None


def test_grid_sdf_parameter_gradients_through_its_analytic_gradient_match_double_backward():
    """The eikonal loss and a term linear in grad f backpropagate through sdf_features_gradient's
    hand-made spatial gradient; autograd's create_graph path through model.sdf is the independent reference."""
    torch.manual_seed(1)
    field = SDFGridField(scene_box=((-1.0,) * 3, (1.0,) * 3), n_levels=4, base_resolution=3, max_resolution=30,
                         log2_hashmap_size=9, hidden=16, n_layers=2, sdf_features=3, color_hidden=8,
                         color_layers=1).double()
    assert bool(field.encoding.hashed.any()) and not bool(field.encoding.hashed.all())
    with torch.no_grad():
        field.encoding.table.uniform_(-0.3, 0.3)
        field.layers[0].weight[:, 3:].normal_(0, 0.5)              # the grid's columns switched on
    field.set_active_levels(3)                                       # a masked level too
    x = torch.rand(300, 3, dtype=D) * 1.8 - 0.9
    params = [p for p in field.parameters()]

    f, _, g = field.sdf_features_gradient(x)
    ours = torch.autograd.grad(eikonal_loss(g) + (f ** 2).mean() + g[:, 0].mean(), params, allow_unused=True)
    f_ref = field.sdf(x)
    g_ref = sdf_gradient(field.sdf, x, create_graph=True)
    ref = torch.autograd.grad(eikonal_loss(g_ref) + (f_ref ** 2).mean() + g_ref[:, 0].mean(), params,
                              allow_unused=True)
    compared = 0
    for a, b in zip(ours, ref):
        if b is None:
            assert a is None or bool((a == 0).all())
            continue
        # (torch's Softplus is exactly linear beyond beta z > 20, where its derivative is 1 - 2e-9)
        torch.testing.assert_close(a, b, atol=1e-7, rtol=1e-6)
        compared += 1
    assert compared >= 5 and float(ours[0].abs().sum()) > 0        # the table's gradient is not empty
