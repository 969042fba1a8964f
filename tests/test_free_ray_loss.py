"""The ray form of known free space (``losses.free_rays``): the opacity a render accumulates before each
ray's free-stretch end, against a naive loop, against the closed form of a VolSDF plane (value and
gradient in the plane's depth, float64), the training-ray bookkeeping of the stretch ends, and a thin
sheet in front of the end thinned away by the loss alone."""

import math

import pytest
import torch

from l3d_app.losses.free_space import opacity_before
from l3d_app.render.volume.free_space import FreeRays
from l3d_app.render.volume.rendering import render_rays

BOX = ((-1.0, -1.0, -1.0), (1.0, 1.0, 1.0))


def test_opacity_before_matches_a_naive_loop():
    g = torch.Generator().manual_seed(1)
    counts = [0, 2, 5, 9, 4]
    t = [torch.sort(torch.rand(c, generator=g, dtype=torch.float64) * 3)[0] for c in counts]
    w = [torch.rand(c, generator=g, dtype=torch.float64) / max(c, 1) for c in counts]
    idx = torch.cat([torch.full((c,), r) for r, c in enumerate(counts)])
    ends = torch.tensor([1.0, 1.5, -math.inf, math.inf, 0.7], dtype=torch.float64)
    got = opacity_before(torch.cat(w), torch.cat(t), idx, ends, len(counts))
    want = [sum(wi for ti, wi in zip(tr.tolist(), wr.tolist()) if ti < e) for tr, wr, e in zip(t, w, ends.tolist())]
    torch.testing.assert_close(got, torch.tensor(want, dtype=torch.float64), rtol=0, atol=1e-15)
    assert got[2] == 0 and torch.isclose(got[3], w[3].sum())        # no claim; the whole ray


def _psi(s, beta):     # the Laplace CDF at s (VolSDF's Psi_beta), written out here
    return torch.where(s <= 0, 0.5 * torch.exp(s / beta), 1 - 0.5 * torch.exp(-s / beta))


def _plane_depth(p, e, alpha, beta):
    """integral_0^e alpha Psi_beta(t - p) dt: the optical depth in front of e of a ray from t = 0 that
    meets a plane (inside beyond it) head-on at depth p (closed form)."""
    if e <= p:
        return 0.5 * alpha * beta * (math.exp((e - p) / beta) - math.exp(-p / beta))
    return (0.5 * alpha * beta * (1 - math.exp(-p / beta))
            + alpha * ((e - p) - 0.5 * beta * (1 - math.exp(-(e - p) / beta))))


def _plane_opacity(p, e, alpha, beta):
    """1 - exp(-depth): the opacity in front of e (closed form)."""
    return 1 - math.exp(-_plane_depth(p, e, alpha, beta))


def _rendered_plane(p, alpha, beta, n=100_000, length=2.0):
    """(weights, t_starts, ray_indices) of one head-on ray, n left-rule segments on [0, length]."""
    t0 = torch.linspace(0, length, n + 1, dtype=torch.float64)
    t_starts, t_ends = t0[:-1], t0[1:]
    idx = torch.zeros(n, dtype=torch.long)

    def fn(ts, te, ri):
        tau = alpha * _psi(ts - p, beta) * (te - ts)
        return {"rgb": torch.zeros(ts.shape[0], 3, dtype=ts.dtype), "tau": tau}
    out = render_rays(t_starts, t_ends, idx, 1, fn)
    return out["weights"], t_starts, idx


@pytest.mark.parametrize("p, e", [(1.2, 1.0), (1.0, 1.0), (0.9, 1.0), (0.3, 0.45)])
def test_a_plane_gives_the_closed_form_and_its_gradient(p, e):
    """Value and d/dp against the closed form (float64; the gradient by a central difference of it):
    a plane behind the end costs its Laplace tail, one in front nearly its whole opacity; the
    gradient always asks the plane to recede (d/dp < 0)."""
    alpha, beta = 20.0, 0.05
    depth = torch.tensor(p, dtype=torch.float64, requires_grad=True)
    w, t, idx = _rendered_plane(depth, alpha, beta)
    got = opacity_before(w, t, idx, torch.tensor([e], dtype=torch.float64), 1)
    got.sum().backward()
    want = _plane_opacity(p, e, alpha, beta)
    h = 1e-6
    want_grad = (_plane_opacity(p + h, e, alpha, beta) - _plane_opacity(p - h, e, alpha, beta)) / (2 * h)
    assert float(got.detach()) == pytest.approx(want, rel=2e-3, abs=1e-6)
    assert float(depth.grad) == pytest.approx(want_grad, rel=2e-3, abs=1e-6)
    assert float(depth.grad) < 0


def test_ends_per_ray_map_the_kept_rays_and_drop_a_covered_open_end():
    """Rays 0-3 read off (as training rays 2, 5, 7, 9 of 10): ray 0 ends at its distance less the
    margin, ray 1 (never opaque) at the box exit unless the images cover it, ray 2 has nothing left
    (its surface is at the box entry), ray 3 misses the box; every other training ray: -inf."""
    o = torch.tensor([[-3.0, 0.0, 0.0], [-3.0, 0.2, 0.0], [-3.0, 0.0, 0.3], [-3.0, 5.0, 0.0]])
    d = torch.tensor([[1.0, 0.0, 0.0]] * 4)
    dist = torch.tensor([3.5, math.inf, 2.02, 1.0])
    index = torch.tensor([2, 5, 7, 9])
    free = FreeRays.from_distances(o, d, dist, BOX, margin=0.05, index=index)
    ninf = -math.inf
    torch.testing.assert_close(free.ends_per_ray(10), torch.tensor([ninf, ninf, 3.45, ninf, ninf, 4.0, ninf,
                                                                     ninf, ninf, ninf]))
    covered = torch.zeros(10, dtype=torch.bool)
    covered[[2, 5]] = True                     # ray 0's end is the field's, kept; ray 1's open end is dropped
    ends = free.ends_per_ray(10, covered)
    assert float(ends[2]) == pytest.approx(3.45) and ends[5] == ninf


def test_a_sheet_in_front_of_the_end_is_thinned_away():
    """An SDF sheet (f = |t - 0.6| - c along the ray: solid within c of depth 0.6, c = 0.01 at the
    start) on a ray known free up to 1.0: moving the sheet inside the stretch would not change the
    loss, so its gradient falls on the sheet's SDF; steps on the ray loss alone raise f until no
    solid is left (c < 0) and the ray is nearly clear."""
    alpha, beta = 50.0, 0.02
    c = torch.nn.Parameter(torch.tensor(0.01, dtype=torch.float64))
    opt = torch.optim.SGD([c], lr=0.01)
    t0 = torch.linspace(0, 2.0, 4001, dtype=torch.float64)
    idx = torch.zeros(4000, dtype=torch.long)
    end = torch.tensor([1.0], dtype=torch.float64)

    def fn(ts, te, ri):
        f = (ts - 0.6).abs() - c
        return {"rgb": torch.zeros(ts.shape[0], 3, dtype=ts.dtype), "tau": alpha * _psi(-f, beta) * (te - ts)}
    start = None
    for _ in range(300):
        opt.zero_grad()
        out = render_rays(t0[:-1], t0[1:], idx, 1, fn)
        loss = opacity_before(out["weights"], t0[:-1], idx, end, 1).mean()
        start = float(loss.detach()) if start is None else start
        loss.backward()
        opt.step()
    assert start > 0.5 and float(c.detach()) < 0 and float(loss.detach()) < 0.2


def test_termination_distance_of_two_samples_and_its_gradient_by_hand():
    """Two samples (alphas a1 at t1, a2 at t2), a miss counted at the exit T: E = a1 t1 + (1 - a1) a2 t2 +
    (1 - a1)(1 - a2) T - near, written out here in float64; dE/da1 = t1 - a2 t2 - (1 - a2) T < 0 (density at
    the front lowers it) and dE/da2 = (1 - a1)(t2 - T)."""
    from l3d_app.losses.free_space import termination_distance
    from l3d_app.render.volume.renderer import composite

    a = torch.tensor([[0.3, 0.6]], dtype=torch.float64, requires_grad=True)
    t = torch.tensor([[1.0, 1.5]], dtype=torch.float64)
    near, far = torch.tensor([0.5], dtype=torch.float64), torch.tensor([2.5], dtype=torch.float64)
    out = composite(torch.zeros(1, 2, 3, dtype=torch.float64), t, alphas=a)
    e = termination_distance(out["depth"], out["opacity"], near, far)
    a1, a2, t1, t2, T = 0.3, 0.6, 1.0, 1.5, 2.5
    want = a1 * t1 + (1 - a1) * a2 * t2 + (1 - a1) * (1 - a2) * T - 0.5
    torch.testing.assert_close(e, torch.tensor([want], dtype=torch.float64))
    e.sum().backward()
    torch.testing.assert_close(a.grad, torch.tensor([[t1 - a2 * t2 - (1 - a2) * T, (1 - a1) * (t2 - T)]],
                                                    dtype=torch.float64))


def test_termination_distance_of_a_uniform_fog_matches_its_integral():
    """Constant density s over a box stretch of length L: E = (1 - exp(-s L)) / s (the integral of the
    transmittance), rendered with 2000 stratified samples."""
    from l3d_app.losses.free_space import termination_distance
    from l3d_app.render.volume.renderer import composite

    s, L, n = 1.7, 2.0, 2000
    t = (torch.arange(n, dtype=torch.float64) * L / n + 3.0)[None]
    out = composite(torch.zeros(1, n, 3, dtype=torch.float64), t, sigmas=torch.full((1, n), s, dtype=torch.float64),
                    deltas=torch.full((1, n), L / n, dtype=torch.float64))
    e = termination_distance(out["depth"], out["opacity"], torch.tensor([3.0], dtype=torch.float64),
                             torch.tensor([3.0 + L], dtype=torch.float64))
    torch.testing.assert_close(e, torch.tensor([(1 - math.exp(-s * L)) / s], dtype=torch.float64), atol=L / n, rtol=0)
