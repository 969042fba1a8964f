"""Real SH basis (degrees 0-3) of l3d_app.render.gaussians.sh against an independent construction from
scipy.special's associated Legendre functions, value AND sign per coefficient, at many
directions including both poles.

The convention (3DGS / gsplat; see tests/sh_reference.py): index ``k = l^2 + l + m``;
``m > 0``: ``sqrt(2) N_lm P_l^m(cos t) cos(m p)``, ``m = 0``: ``N_l0 P_l(cos t)``,
``m < 0``: ``sqrt(2) N_l|m| P_l^|m|(cos t) sin(|m| p)``, with scipy's ``lpmv`` (which
includes the Condon-Shortley phase ``(-1)^m``). That is the textbook real basis (without
the phase) times ``(-1)^m``; e.g. band 1 is ``(-c y, c z, -c x)``, ``c = sqrt(3 / 4 pi)``.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.special import lpmv, sph_harm_y

from l3d_app.render.gaussians.sh import eval_sh, sh_basis, sh_to_color
from sh_reference import real_sh_3dgs, sh_colour

D = torch.float64


def _directions() -> np.ndarray:
    """(M, 3) unit directions: a Fibonacci sphere, the six axes (both poles), points near the
    poles (1e-3 away: closer, scipy's lpmv loses digits in sqrt(1 - x^2)) and on the equator."""
    n = 300
    i = np.arange(n) + 0.5
    zf = 1 - 2 * i / n
    pf = math.pi * (1 + 5 ** 0.5) * i
    fib = np.stack([np.sqrt(1 - zf ** 2) * np.cos(pf), np.sqrt(1 - zf ** 2) * np.sin(pf), zf], -1)
    axes = np.concatenate([np.eye(3), -np.eye(3)])
    eps = 1e-3
    near = np.array([[eps, 0, 1], [0, eps, 1], [-eps, eps, -1], [eps, -eps, -1], [1, 1, 0], [-1, 2, 0]], float)
    d = np.concatenate([fib, axes, near])
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


def _scipy_basis(degree: int, d: np.ndarray) -> np.ndarray:
    """(M, K) from lpmv: polar angle t from +z, azimuth p from +x towards +y."""
    t = np.arccos(np.clip(d[:, 2], -1, 1))
    p = np.arctan2(d[:, 1], d[:, 0])
    cols = []
    for l in range(degree + 1):
        for m in range(-l, l + 1):
            a = abs(m)
            N = math.sqrt((2 * l + 1) / (4 * math.pi) * math.factorial(l - a) / math.factorial(l + a))
            P = lpmv(a, l, np.cos(t))
            if m == 0:
                cols.append(N * P)
            elif m > 0:
                cols.append(math.sqrt(2) * N * P * np.cos(a * p))
            else:
                cols.append(math.sqrt(2) * N * P * np.sin(a * p))
    return np.stack(cols, -1)


def _scipy_complex_basis(degree: int, d: np.ndarray) -> np.ndarray:
    """The same from scipy's complex Y_l^m (sph_harm_y(l, m, polar, azimuth)): sqrt(2) Re / Im."""
    t = np.arccos(np.clip(d[:, 2], -1, 1))
    p = np.arctan2(d[:, 1], d[:, 0])
    cols = []
    for l in range(degree + 1):
        for m in range(-l, l + 1):
            Y = sph_harm_y(l, abs(m), t, p)
            cols.append(Y.real if m == 0 else math.sqrt(2) * (Y.real if m > 0 else Y.imag))
    return np.stack(cols, -1)


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_basis_matches_scipy_values_and_signs(degree):
    d = _directions()
    ref = _scipy_basis(degree, d)
    np.testing.assert_allclose(_scipy_complex_basis(degree, d), ref, atol=1e-12, rtol=0)
    ours = sh_basis(degree, torch.from_numpy(d)).numpy()
    assert ours.shape == ref.shape == (d.shape[0], (degree + 1) ** 2)
    np.testing.assert_allclose(ours, ref, atol=1e-12, rtol=0)
    # sign per coefficient wherever the value is clearly non-zero (a sign or order error in any
    # single coefficient flips these)
    big = np.abs(ref) > 1e-3
    assert big.sum(0).min() > 100
    assert (np.sign(ours[big]) == np.sign(ref[big])).all()
    # the torch recurrence used as the independent reference elsewhere agrees with scipy too,
    # and with ours a hair (1e-9) from the poles, where both are exact polynomials
    np.testing.assert_allclose(real_sh_3dgs(degree, torch.from_numpy(d)).numpy(), ref, atol=1e-12, rtol=0)
    hair = torch.nn.functional.normalize(torch.tensor([[1e-9, 0, 1], [0, -1e-9, 1], [1e-9, 1e-9, -1]], dtype=D), dim=-1)
    torch.testing.assert_close(sh_basis(degree, hair), real_sh_3dgs(degree, hair), atol=1e-15, rtol=0)


def test_band_one_and_pole_values_spelled_out():
    """A few values by hand: band 1 = sqrt(3/4pi) (-y, z, -x); at the poles only m = 0 survives,
    Y_l0(+-z) = (+-1)^l sqrt((2l + 1) / 4 pi)."""
    c = math.sqrt(3 / (4 * math.pi))
    d = torch.tensor([[0.6, 0.0, 0.8], [0.0, 0.6, -0.8]], dtype=D)
    torch.testing.assert_close(sh_basis(1, d)[:, 1:], torch.tensor([[0.0, 0.8 * c, -0.6 * c],
                                                                    [-0.6 * c, -0.8 * c, 0.0]], dtype=D))
    poles = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0]], dtype=D)
    Y = sh_basis(3, poles)
    for l in range(4):
        for m in range(-l, l + 1):
            k = l * l + l + m
            want = 0.0 if m else math.sqrt((2 * l + 1) / (4 * math.pi))
            assert float(Y[0, k]) == pytest.approx(want, abs=1e-14)
            assert float(Y[1, k]) == pytest.approx((-1) ** l * want, abs=1e-14)


@pytest.mark.parametrize("degree", [1, 3])
def test_eval_sh_uses_each_coefficient_in_its_slot(degree):
    """One-hot coefficients per slot and channel pick that basis function (order of the
    contraction), and the colour is max(value + 0.5, 0)."""
    d = torch.from_numpy(_directions())
    ref = torch.from_numpy(_scipy_basis(degree, d.numpy()))
    K = (degree + 1) ** 2
    for k in range(K):
        for ch in range(3):
            c = torch.zeros(d.shape[0], 16, 3, dtype=D)
            c[:, k, ch] = 1.0
            v = eval_sh(degree, c, d)
            torch.testing.assert_close(v[:, ch], ref[:, k], atol=1e-12, rtol=0)
            assert float(v[:, [j for j in range(3) if j != ch]].abs().max()) == 0.0
    g = torch.Generator().manual_seed(0)
    coeffs = torch.randn(d.shape[0], 16, 3, generator=g, dtype=D)
    torch.testing.assert_close(sh_to_color(degree, coeffs, d), sh_colour(degree, coeffs, d), atol=1e-12, rtol=0)


def test_direction_gradients_match_the_independent_construction():
    """d(colour)/d(dir) of ours equals the recurrence's autograd along the sphere, poles
    included. (Off the sphere the two are different polynomials, e.g. 2z^2 - x^2 - y^2 vs
    3z^2 - 1, so only the tangential part is defined by the basis; the radial part is
    removed by the normalisation of a direction in every use.)"""
    d = torch.from_numpy(_directions())
    g = torch.Generator().manual_seed(1)
    coeffs = torch.randn(d.shape[0], 16, 3, generator=g, dtype=D)
    w = torch.randn(d.shape[0], 3, generator=g, dtype=D)
    grads = []
    for fn in (eval_sh, lambda deg, c, x: torch.einsum("...k,...kc->...c", real_sh_3dgs(deg, x), c[..., :16, :])):
        x = d.clone().requires_grad_(True)
        (fn(3, coeffs, x) * w).sum().backward()
        grads.append(x.grad)
    assert torch.isfinite(grads[0]).all()
    tangential = [g - (g * d).sum(-1, keepdim=True) * d for g in grads]
    assert float(tangential[1].abs().max()) > 1.0
    torch.testing.assert_close(tangential[0], tangential[1], atol=1e-11, rtol=1e-11)


@pytest.mark.parametrize("degree", [0, 1, 3])
def test_coefficient_and_basis_gradients_match_plain_autograd(degree):
    """BasisDot's hand-written backward against autograd through an einsum (float64): the
    gradients to the coefficients (only the first (degree+1)^2 receive any) and to the
    directions, for per-splat coefficients and for coefficients broadcast over a batch."""
    from l3d_app.render.gaussians.sh import sh_basis

    g = torch.Generator().manual_seed(3)
    d = torch.nn.functional.normalize(torch.randn(2, 40, 3, generator=g, dtype=D), dim=-1)
    w = torch.randn(2, 40, 3, generator=g, dtype=D)
    for shape in ((2, 40, 16, 3), (40, 16, 3), (16, 3)):          # per splat, broadcast over batch dims
        coeffs = torch.randn(*shape, generator=g, dtype=D)
        grads = []
        for fn in (eval_sh, lambda deg, c, x: torch.einsum("...k,...kc->...c", sh_basis(deg, x),
                                                          c[..., :(deg + 1) ** 2, :])):
            c = coeffs.clone().requires_grad_(True)
            x = d.clone().requires_grad_(True)
            out = fn(degree, c, x)
            assert out.shape == (2, 40, 3)
            (out * w).sum().backward()
            grads.append((out.detach(), c.grad, x.grad))
        (o0, c0, x0), (o1, c1, x1) = grads
        torch.testing.assert_close(o0, o1, atol=1e-12, rtol=0)
        torch.testing.assert_close(c0, c1, atol=1e-12, rtol=0)
        torch.testing.assert_close(x0, x1, atol=1e-12, rtol=0)
        assert float(c0[..., (degree + 1) ** 2:, :].abs().sum()) == 0.0
        assert float(c0.abs().max()) > 0.1
