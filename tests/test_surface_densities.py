"""VolSDF (Laplace CDF) and NeuS (logistic, sigmoid form) densities: float64 hard cases vs mpmath."""

import itertools

import mpmath
import pytest
import torch

from l3d_app.render.sdf.densities import laplace_cdf, volsdf_density
from l3d_app.render.sdf.neus import logistic_density, neus_alpha, neus_optical_depth

mpmath.mp.dps = 50

BETAS = [1e-4, 1e-3, 0.05, 1.0]
SDFS = [-1e3, -10.0, -0.3, -1e-3, -1e-5, 0.0, 1e-5, 1e-3, 0.3, 10.0, 1e3]


def _mp_laplace_cdf(x, beta):
    x, beta = mpmath.mpf(x), mpmath.mpf(beta)
    return 0.5 * mpmath.exp(x / beta) if x <= 0 else 1 - 0.5 * mpmath.exp(-x / beta)


def _mp_laplace_pdf(x, beta):
    x, beta = mpmath.mpf(x), mpmath.mpf(beta)
    return 0.5 * mpmath.exp(-abs(x) / beta) / beta


def _close(value, ref, rtol=1e-12, atol=1e-300):
    return abs(value - float(ref)) <= atol + rtol * abs(float(ref))


@pytest.mark.parametrize("beta", BETAS)
def test_volsdf_density_values_and_gradients_vs_mpmath(beta):
    alpha = 10.0
    sdf = torch.tensor(SDFS, dtype=torch.float64, requires_grad=True)
    beta_t = torch.tensor(beta, dtype=torch.float64, requires_grad=True)
    sigma = volsdf_density(sdf, alpha, beta_t)
    assert torch.isfinite(sigma).all()
    g_sdf, g_beta = torch.autograd.grad(sigma.sum(), [sdf, beta_t])
    assert torch.isfinite(g_sdf).all() and torch.isfinite(g_beta)
    ref_dbeta = mpmath.mpf(0)
    for i, f in enumerate(SDFS):
        assert _close(float(sigma[i].detach()), alpha * _mp_laplace_cdf(-f, beta)), (f, beta)
        # d sigma / d sdf = -alpha * pdf(-sdf)
        assert _close(float(g_sdf[i]), -alpha * _mp_laplace_pdf(-f, beta), rtol=1e-10), (f, beta)
        ref_dbeta += mpmath.diff(lambda b: alpha * _mp_laplace_cdf(-f, b), mpmath.mpf(beta))
    assert _close(float(g_beta), ref_dbeta, rtol=1e-8, atol=1e-12)


def test_laplace_cdf_float32_extremes_are_finite():
    x = torch.tensor([-1e3, -1.0, 0.0, 1.0, 1e3], requires_grad=True)
    y = laplace_cdf(x, 1e-4)
    (g,) = torch.autograd.grad(y.sum(), x)
    assert torch.isfinite(y).all() and torch.isfinite(g).all()
    assert y.tolist() == [0.0, 0.0, 0.5, 1.0, 1.0]


def _mp_log_sigmoid(z):
    return -mpmath.log1p(mpmath.exp(-z))


S_VALUES = [1.0, 64.0, 1e3, 1e4]


@pytest.mark.parametrize("s", S_VALUES)
def test_logistic_density_vs_mpmath(s):
    x = torch.tensor(SDFS, dtype=torch.float64, requires_grad=True)
    phi = logistic_density(x, s)
    (g,) = torch.autograd.grad(phi.sum(), x)
    assert torch.isfinite(phi).all() and torch.isfinite(g).all()
    for i, f in enumerate(SDFS):
        z = mpmath.mpf(s) * f
        ref = s * mpmath.exp(-z) / (1 + mpmath.exp(-z)) ** 2
        assert _close(float(phi[i].detach()), ref, rtol=1e-12), (f, s)
        dref = mpmath.diff(lambda u: s * mpmath.exp(-s * u) / (1 + mpmath.exp(-s * u)) ** 2, mpmath.mpf(f))
        assert _close(float(g[i]), dref, rtol=1e-7, atol=1e-290), (f, s)


PAIRS = [(a, b) for a, b in itertools.product(SDFS, SDFS) if a != b]


@pytest.mark.parametrize("s", S_VALUES)
def test_neus_alpha_and_optical_depth_vs_mpmath(s):
    a = torch.tensor([p[0] for p in PAIRS], dtype=torch.float64, requires_grad=True)
    b = torch.tensor([p[1] for p in PAIRS], dtype=torch.float64, requires_grad=True)
    s_t = torch.tensor(s, dtype=torch.float64, requires_grad=True)
    tau = neus_optical_depth(a, b, s_t)
    alpha = neus_alpha(a, b, s_t)
    ga, gb, gs = torch.autograd.grad(alpha.sum() + tau.sum(), [a, b, s_t])
    for t in (tau, alpha, ga, gb, gs):
        assert torch.isfinite(t).all()
    assert ((alpha >= 0) & (alpha <= 1)).all() and (tau >= 0).all()
    for i, (fa, fb) in enumerate(PAIRS):
        za, zb = mpmath.mpf(s) * fa, mpmath.mpf(s) * fb
        ref_tau = max(_mp_log_sigmoid(za) - _mp_log_sigmoid(zb), 0)
        # (Phi(a) - Phi(b)) / Phi(a) = 1 - Phi(b) / Phi(a) = -expm1(-tau), in 50 digits (the
        # textbook quotient itself would need thousands of digits when both sigmoids are ~1)
        ref_alpha = -mpmath.expm1(-ref_tau)
        # tau is a difference of two logs: accurate to rounding of the larger log (cancellation
        # when f_a ~ f_b is inherent to the form and harmless: the error is absolute and tiny)
        scale = float(abs(_mp_log_sigmoid(za)) + abs(_mp_log_sigmoid(zb)))
        assert _close(float(tau[i].detach()), ref_tau, rtol=1e-12, atol=4e-16 * scale), (fa, fb, s)
        assert _close(float(alpha[i].detach()), ref_alpha, rtol=1e-12, atol=4e-16 * scale + 1e-300), (fa, fb, s)
        if fa > fb:   # entering: d tau / d f_a = -s sigmoid(-s f_a) ... exact derivative of logsigmoid
            d_a = mpmath.mpf(s) / (1 + mpmath.exp(za))
            d_tau_a = float(d_a)
            # alpha = 1 - exp(-tau): d alpha / d a = exp(-tau) d tau / d a
            ref_ga = d_tau_a * (1 + float(mpmath.exp(-ref_tau)))
            assert _close(float(ga[i]), ref_ga, rtol=1e-9, atol=1e-290), (fa, fb, s)


def test_neus_raw_exponential_form_would_fail_but_ours_does_not():
    # s f = -1e7: exp(-s f) overflows; the sigmoid form still gives the exact alpha
    a = torch.tensor([-1e3, 5e-4], dtype=torch.float64)
    b = torch.tensor([-1e3 - 1e-3, -5e-4], dtype=torch.float64)
    s = 1e4
    raw = (torch.sigmoid(s * a) - torch.sigmoid(s * b)) / torch.sigmoid(s * a)
    assert not torch.isfinite(raw[0])                   # 0/0 in the textbook form
    alpha = neus_alpha(a, b, s)
    assert float(alpha[0]) == pytest.approx(-mpmath.expm1(-10.0), rel=1e-9)   # s * 1e-3 = 10
    assert float(alpha[1]) == pytest.approx(float(1 - (1 / (1 + mpmath.exp(5))) / (1 / (1 + mpmath.exp(-5)))),
                                            rel=1e-12)


# ------------------------------------------------------------ the DENSITIES modules (what tasks run)
def _packed(values, dtype):
    """Three rays of two segments each: sdf at the starts, unit segments."""
    f = torch.tensor(values, dtype=dtype, requires_grad=True)
    t0 = torch.tensor([0.0, 1.0] * (len(values) // 2), dtype=dtype)
    return f, t0, t0 + 1.0, torch.arange(len(values) // 2).repeat_interleave(2)


@pytest.mark.parametrize("sdf", [-1e3, -1e-3, 0.0, 2e-4, 1e3])
def test_volsdf_module_at_beta_1e4_matches_mpmath_in_float32(sdf):
    from l3d_app.registry import DENSITIES
    import l3d_app.render.sdf.densities  # noqa: F401  (registers)

    beta = 1e-4
    dens = DENSITIES.build({"name": "volsdf", "beta": beta, "mode": "fixed", "beta_end": beta, "beta_min": 0.0,
                            "alpha": 10.0})
    f, t0, t1, rays = _packed([sdf, -sdf], torch.float32)
    tau = dens.optical_depth(f, t0, t1, rays)             # forward() is the code path: sigma * (t1 - t0)
    (g,) = torch.autograd.grad(tau.sum(), f)
    assert torch.isfinite(tau).all() and torch.isfinite(g).all()
    b = float(dens.beta)                  # beta as the module holds it (float32 of beta_min + exp(rho))
    assert b == pytest.approx(beta, rel=1e-6)
    for i, x in enumerate([sdf, -sdf]):
        xf = float(torch.tensor(x, dtype=torch.float32))
        ref = 10.0 * _mp_laplace_cdf(-xf, b)
        # float32: the exponent x / beta (up to 10 here) carries a relative rounding of ~1e-7
        assert abs(float(tau[i].detach()) - float(ref)) <= 1e-5 * abs(float(ref)) + 1e-30
        ref_g = -10.0 * _mp_laplace_pdf(-xf, b)
        assert abs(float(g[i]) - float(ref_g)) <= 2e-3 * abs(float(ref_g)) + 1e-30


def test_volsdf_module_beta_gradient_and_anneal_schedule():
    from l3d_app.registry import DENSITIES
    import l3d_app.render.sdf.densities  # noqa: F401

    dens = DENSITIES.build({"name": "volsdf", "beta": 0.1, "mode": "learnable", "beta_end": 0.01, "beta_min": 1e-4})
    f, t0, t1, rays = _packed([-0.05, 0.02], torch.float32)
    (g,) = torch.autograd.grad(dens.optical_depth(f.detach(), t0, t1, rays).sum(), dens.rho)
    # alpha = 1/beta: tau = Psi_b(-f)/b; d/d rho = d/d beta * (beta - beta_min), in float64 by mpmath
    b = mpmath.mpf(float(dens.beta.detach()))
    ref = sum(mpmath.diff(lambda bb: _mp_laplace_cdf(-x, bb) / bb, b)
              for x in (float(torch.tensor(-0.05)), float(torch.tensor(0.02)))) * (b - mpmath.mpf(1e-4))
    assert abs(float(g) - float(ref)) < 1e-4 * abs(float(ref))
    ann = DENSITIES.build({"name": "volsdf", "beta": 0.1, "mode": "anneal", "beta_end": 0.001,
                           "anneal_fraction": 0.5, "beta_min": 1e-4})
    for step, expected in ((0, 0.1), (25, 0.01), (50, 0.001), (99, 0.001)):
        ann.schedule(step, 100)
        assert float(ann.beta) == pytest.approx(expected, rel=1e-5)
    with pytest.raises(ValueError):
        DENSITIES.build({"name": "volsdf", "beta": 0.1, "mode": "sideways"})


@pytest.mark.parametrize("s", [64.0, 1e4])
def test_neus_module_at_s_1e4_matches_mpmath_and_ends_each_ray(s):
    from l3d_app.registry import DENSITIES
    import l3d_app.render.sdf.neus  # noqa: F401

    dens = DENSITIES.build({"name": "neus", "s": s})
    vals = [1e3, -1e3, 2e-4, -1e-4, -0.5, 0.5]             # rays: (1e3 -> -1e3), (2e-4 -> -1e-4), (-0.5 -> 0.5)
    f, t0, t1, rays = _packed(vals, torch.float64)
    tau = dens.optical_depth(f, t0, t1, rays)
    (g,) = torch.autograd.grad(tau.sum(), f)
    tau = tau.detach()
    assert torch.isfinite(tau).all() and torch.isfinite(g).all()
    assert float(tau[1]) == float(tau[3]) == float(tau[5]) == 0.0      # last segment of every ray
    for i in (0, 2, 4):
        za, zb = mpmath.mpf(s) * vals[i], mpmath.mpf(s) * vals[i + 1]
        ref = max(_mp_log_sigmoid(za) - _mp_log_sigmoid(zb), 0)
        assert abs(float(tau[i].detach()) - float(ref)) <= 1e-12 * max(1.0, abs(float(ref)))
        if vals[i] > vals[i + 1]:     # d tau / d f_start = + s sigmoid(-s f_start) (it ends no segment)
            assert abs(float(g[i]) - float(mpmath.mpf(s) / (1 + mpmath.exp(za)))) <= 1e-12 * s
    f32, t0, t1, rays = _packed(vals, torch.float32)
    tau32 = dens.optical_depth(f32, t0, t1, rays)
    (g32,) = torch.autograd.grad(tau32.sum(), f32)
    tau32 = tau32.detach()
    assert torch.isfinite(tau32).all() and torch.isfinite(g32).all()
    assert float(tau32[0]) == pytest.approx(float(tau[0]), rel=1e-6)
