"""Chamfer distance vs a brute-force float64 reference; duplicates, coincidences, gradients."""

import pytest
import torch

from l3d_app.errors import UserError
from l3d_app.metrics.chamfer import chamfer_distance, chamfer_distance_batched, nearest_neighbors


def brute_force(x, y, squared=True):
    d = ((x.double()[:, None] - y.double()[None]) ** 2).sum(-1)
    if not squared:
        d = d.sqrt()
    return d.min(1).values.mean() + d.min(0).values.mean()


@pytest.mark.parametrize("backend", ["torch", "kdtree"])
@pytest.mark.parametrize("squared", [True, False])
def test_matches_brute_force(backend, squared):
    g = torch.Generator().manual_seed(0)
    x, y = torch.randn(300, 3, generator=g), torch.rand(517, 3, generator=g)
    got = chamfer_distance(x, y, squared=squared, chunk_size=7, backend=backend)
    assert torch.allclose(got.double(), brute_force(x, y, squared), rtol=1e-5, atol=1e-7)


def test_parts_and_asymmetry():
    x = torch.tensor([[0.0, 0, 0]])
    y = torch.tensor([[1.0, 0, 0], [3.0, 0, 0]])
    total, xy, yx = chamfer_distance(x, y, return_parts=True)
    assert xy.item() == pytest.approx(1.0) and yx.item() == pytest.approx((1 + 9) / 2)
    assert total.item() == pytest.approx(6.0)
    assert chamfer_distance(x, y, squared=False).item() == pytest.approx(1.0 + 2.0)


@pytest.mark.parametrize("squared", [True, False])
def test_self_and_duplicates_are_zero_with_finite_gradients(squared):
    g = torch.Generator().manual_seed(1)
    base = torch.rand(50, 3, generator=g, dtype=torch.float64)
    x = torch.cat([base, base[:10], base[:10]]).requires_grad_(True)   # duplicated points
    y = base[torch.randperm(50, generator=g)].clone().requires_grad_(True)  # coincident, shuffled
    cd = chamfer_distance(x, y, squared=squared)
    assert cd.item() == 0.0
    cd.backward()
    assert torch.isfinite(x.grad).all() and torch.isfinite(y.grad).all()
    assert chamfer_distance(base, base, squared=squared).item() == 0.0


def test_gradient_matches_float64_reference():
    g = torch.Generator().manual_seed(2)
    x = torch.rand(40, 3, generator=g, dtype=torch.float64, requires_grad=True)
    y = torch.rand(60, 3, generator=g, dtype=torch.float64)
    x2 = x.detach().clone().requires_grad_(True)
    for squared in (True, False):
        x.grad = x2.grad = None
        chamfer_distance(x, y, squared=squared).backward()
        brute_force(x2, y, squared).backward()
        assert torch.allclose(x.grad, x2.grad, atol=1e-10)
        assert torch.isfinite(x.grad).all()


def test_batched_and_nearest_neighbors():
    x = torch.rand(2, 20, 3)
    y = torch.rand(2, 30, 3)
    got = chamfer_distance_batched(x, y)
    assert torch.allclose(got.double(), torch.stack([brute_force(a, b) for a, b in zip(x, y)]), rtol=1e-5)
    idx = nearest_neighbors(x[0], y[0])
    assert torch.equal(idx, torch.cdist(x[0].double(), y[0].double()).argmin(1))


def test_bad_inputs_are_user_errors():
    with pytest.raises(UserError):
        chamfer_distance(torch.zeros(0, 3), torch.zeros(4, 3))
    with pytest.raises(UserError):
        chamfer_distance(torch.zeros(3, 3), torch.zeros(4, 2))
    with pytest.raises(UserError):
        chamfer_distance(torch.zeros(3, 3), torch.zeros(4, 3), backend="faiss")


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_both_directions_match_brute_force_across_tiles_and_chunks(dtype):
    from l3d_app.metrics.chamfer import nearest_neighbors_both

    g = torch.Generator().manual_seed(3)
    x = (torch.rand(1037, 3, generator=g) * 2 - 1).to(dtype)  # several chunks
    y = (torch.rand(613, 3, generator=g) * 2 - 1).to(dtype)   # several tiles + padding
    ixy, iyx = nearest_neighbors_both(x, y, chunk_size=100)
    d = ((x.double()[:, None] - y.double()[None]) ** 2).sum(-1)
    # same neighbour, or one at the same distance up to float rounding
    tol = 1e-6 if dtype == torch.float32 else 1e-12
    assert (d.gather(1, ixy[:, None]).squeeze(1) - d.min(1).values).abs().max() <= tol
    assert (d.gather(0, iyx[None]).squeeze(0) - d.min(0).values).abs().max() <= tol
    assert (ixy == d.argmin(1)).float().mean() == 1.0 and (iyx == d.argmin(0)).float().mean() == 1.0


def test_half_precision_and_far_offset_inputs():
    g = torch.Generator().manual_seed(4)
    x, y = torch.rand(200, 3, generator=g), torch.rand(300, 3, generator=g)
    ref = brute_force(x, y)
    assert torch.allclose(chamfer_distance(x.half(), y.half()).double(), brute_force(x.half(), y.half()), rtol=1e-2)
    off = torch.tensor([1000.0, -500.0, 250.0], dtype=torch.float64)  # centring keeps it exact
    got = chamfer_distance(x.double() + off, y.double() + off)
    assert torch.allclose(got, ref, rtol=1e-6)
