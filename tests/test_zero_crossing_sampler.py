"""Fine samples at the field's own zero crossing (``sampler.anchor``, render/volume/estimators/zero_crossing.py):
the first crossing by hand, its refinement against the analytic ray-sphere intersection, and an estimator
whose coarse cache is too rough for a sharp transition that still puts its anchored samples inside it and
renders a head-on ray's optical depth to the surface close to the analytic 0.5."""

from types import SimpleNamespace

import pytest
import torch

from l3d_app.render.sdf.densities import LaplaceDensity
from l3d_app.render.volume.estimators import SDFCacheProposal
from l3d_app.render.volume.estimators.zero_crossing import first_crossing, refine_crossing
from l3d_app.render.sdf.volume import render_sdf_rays

D = torch.float64
BOX = ((-1.0, -1.0, -1.0), (1.0, 1.0, 1.0))


def test_first_crossing_by_hand():
    t = torch.tensor([[0.0, 1.0, 2.0, 3.0]] * 5, dtype=D)
    f = torch.tensor([[0.3, 0.1, -0.3, -0.5],      # between 1 and 2, a quarter of the way: 1.25
                      [-0.1, 0.2, -0.2, 0.4],      # starts inside: the first OUTSIDE-to-inside change, 1.5
                      [0.2, 0.0, -0.1, 0.3],       # lands on a sample: 1.0
                      [0.5, 0.4, 0.3, 0.2],        # never inside: not found, the first sample
                      [-0.5, -0.4, -0.3, -0.2]], dtype=D)
    t_cross, found = first_crossing(f, t)
    assert found.tolist() == [True, True, True, False, False]
    assert torch.allclose(t_cross, torch.tensor([1.25, 1.5, 1.0, 0.0, 0.0], dtype=D), rtol=0, atol=1e-15)


def _sphere_hits(o, d, radius):
    b = (o * d).sum(-1)
    return -b - torch.sqrt(b ** 2 - (o.norm(dim=-1) ** 2 - radius ** 2))


def test_refinement_finds_the_sphere_from_a_rough_guess():
    """Guesses 0.02 off the analytic entry; +-0.03 with 8 evaluations (chords of a sphere of radius 0.5):
    within 1e-4; a window that brackets nothing keeps the guess and says so."""
    torch.manual_seed(0)
    o = torch.nn.functional.normalize(torch.randn(32, 3, dtype=D), dim=-1) * 2.0
    d = torch.nn.functional.normalize(torch.randn(32, 3, dtype=D) * 0.1 - o, dim=-1)
    exact = _sphere_hits(o, d, 0.5)
    guess = exact + 0.04 * (torch.rand(32, dtype=D) - 0.5)
    sdf = lambda p: p.norm(dim=-1) - 0.5        # noqa: E731
    t, found = refine_crossing(sdf, o, d, guess, 0.03, 8)
    assert bool(found.all()) and float((t - exact).abs().max()) < 1e-4
    t, found = refine_crossing(sdf, o, d, exact + 0.2, 0.03, 8)
    assert not bool(found.any()) and torch.equal(t, exact + 0.2)


def test_anchored_samples_sit_in_a_transition_the_cache_cannot_resolve():
    """A sphere of radius 0.5, beta 0.001 (a transition 50 times narrower than the 16^3 cache's cells):
    with anchor=8 every ray has its 8 samples within [-4, 3] beta of the analytic entry, is opaque, and its
    expected depth lies within beta / 2 of it; the weights alone (anchor=0) leave most rays with at most
    one sample there, depths four times as far off, and a head-on ray that misses the surface."""
    beta, n = 0.001, 48
    torch.manual_seed(1)
    o = torch.nn.functional.normalize(torch.randn(n, 3, dtype=D), dim=-1) * 2.5
    d = -torch.nn.functional.normalize(o, dim=-1)            # head-on: the transition is beta wide in t
    exact = _sphere_hits(o, d, 0.5)
    sphere = SimpleNamespace(sdf=lambda p: p.norm(dim=-1) - 0.5)
    dens = LaplaceDensity(beta, None, learnable=False, beta_min=0.0)
    colour = lambda p, v: (sphere.sdf(p), torch.ones(p.shape[0], 3, dtype=D))  # noqa: E731

    def render(anchor, eval_anchor=None, grad=False, when="always"):
        est = SDFCacheProposal(BOX, n_coarse=64, n_fine=16, resolution=16, anchor=anchor, eval_anchor=eval_anchor,
                               anchor_when=when)
        est.update(0, sphere)
        with torch.set_grad_enabled(grad):
            out = render_sdf_rays(colour, o, d, est, dens, field=sphere, perturb=True,
                                  generator=torch.Generator().manual_seed(0))
        t = out["t"].reshape(n, 16)
        inside = ((t - exact[:, None] >= -4 * beta) & (t - exact[:, None] <= 3 * beta)).sum(-1)
        return inside, (out["depth"] - exact).abs(), out
    inside, err, out = render(8)
    assert int(inside.min()) >= 8 and float(err.max()) < 0.5 * beta and float(out["opacity"].min()) > 0.99
    assert float(out["samples_per_ray"]) == pytest.approx(64 + 16 + 8)
    inside0, err0, out0 = render(0)
    assert float((inside0 <= 1).float().mean()) > 0.5 and float(err0.median()) > 2 * float(err.median())
    assert float(err0.max()) > 10 * beta and float(out0["opacity"].min()) < 0.5    # a ray that misses the surface
    # eval_anchor: the evaluation renders (no grad) only
    inside_eval, err_eval, _ = render(0, eval_anchor=8)
    assert torch.equal(inside_eval, inside) and torch.equal(err_eval, err)
    inside_train, _, out_train = render(0, eval_anchor=8, grad=True)
    assert torch.equal(inside_train, inside0) and float(out_train["samples_per_ray"]) == pytest.approx(64 + 16)
    # anchor_when=narrow: the window (7 beta = 0.007) is narrower than a 16^3 cell (2 / 15): anchored as always;
    # at beta 0.05 (window 0.35) the cache resolves the transition and no field evaluation is spent
    inside_narrow, _, _ = render(8, when="narrow")
    assert torch.equal(inside_narrow, inside)
    dens.set_beta(0.05)
    _, _, wide = render(8, when="narrow")
    assert float(wide["samples_per_ray"]) == pytest.approx(64 + 16)
    _, _, wide_always = render(8, when="always")
    assert float(wide_always["samples_per_ray"]) == pytest.approx(64 + 16 + 8)


@pytest.mark.parametrize("kw", [dict(anchor=16), dict(anchor=-1), dict(anchor=4, anchor_window=(1.0, 1.0)),
                                dict(anchor=4, refine_evals=1), dict(eval_anchor=-1),
                                dict(anchor=4, anchor_when="sometimes")])
def test_bad_anchor_settings_are_refused(kw):
    with pytest.raises(ValueError, match="anchor"):
        SDFCacheProposal(BOX, n_fine=16, **kw)


def test_the_anchor_window_is_in_each_density_s_own_width():
    from l3d_app.render.sdf.densities import transition_width
    from l3d_app.render.sdf.neus import NeuSDensity
    assert transition_width(LaplaceDensity(0.01, None, learnable=False, beta_min=0.0)) == pytest.approx(0.01)
    assert transition_width(NeuSDensity(50.0)) == pytest.approx(0.02)
