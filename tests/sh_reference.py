"""Test support: real spherical harmonics in the 3DGS convention, built independently of
``l3d_app.render.gaussians.sh`` (no shared constants or polynomials).

Convention (the one of 3DGS / gsplat, documented and checked in test_sh_reference.py):
with the complex ``Y_l^m`` INCLUDING the Condon-Shortley phase ``(-1)^m`` (as
``scipy.special.lpmv`` / ``sph_harm_y`` have it), coefficient index ``k = l^2 + l + m`` is

* ``m > 0``: ``sqrt(2) Re Y_l^m  = sqrt(2) N_lm P_l^m(cos t) cos(m p)``
* ``m = 0``: ``Y_l^0             = N_l0 P_l(cos t)``
* ``m < 0``: ``sqrt(2) Im Y_l^|m| = sqrt(2) N_l|m| P_l^|m|(cos t) sin(|m| p)``

with ``N_lm = sqrt((2l + 1) / (4 pi) (l - m)! / (l + m)!)``, polar angle ``t`` from +z and
azimuth ``p`` from +x towards +y. (It is the "Wikipedia" real basis times ``(-1)^m``:
band 1 reads ``-c y, c z, -c x``.)

Here the basis is evaluated differentiably in torch by recurrences:
``sin^m(t) e^{i m p} = (x + i y)^m`` and ``P_l^m(z) = sin^m(t) Q_l^m(z)`` with the
polynomial ``Q`` from the standard three-term recurrence in ``l``, so it is finite at the poles.
"""

from __future__ import annotations

import math

import torch


def _norm(l: int, m: int) -> float:
    return math.sqrt((2 * l + 1) / (4 * math.pi) * math.factorial(l - m) / math.factorial(l + m))


def real_sh_3dgs(degree: int, dirs: torch.Tensor) -> torch.Tensor:
    """(..., (degree+1)^2) real SH at unit directions (..., 3), 3DGS order and signs."""
    x, y, z = dirs[..., 0], dirs[..., 1], dirs[..., 2]
    one = torch.ones_like(z)
    # Q[l][m]: P_l^m(z) / sin^m(t), Condon-Shortley phase included
    Q = [[None] * (degree + 1) for _ in range(degree + 1)]
    for m in range(degree + 1):
        dfact = math.prod(range(2 * m - 1, 0, -2)) if m > 0 else 1       # (2m - 1)!!
        Q[m][m] = ((-1) ** m * dfact) * one
        if m + 1 <= degree:
            Q[m + 1][m] = (2 * m + 1) * z * Q[m][m]
        for l in range(m + 2, degree + 1):
            Q[l][m] = ((2 * l - 1) * z * Q[l - 1][m] - (l + m - 1) * Q[l - 2][m]) / (l - m)
    # (x + i y)^m = re[m] + i im[m]
    re, im = [one], [torch.zeros_like(z)]
    for m in range(1, degree + 1):
        r, i = re[-1], im[-1]
        re.append(r * x - i * y)
        im.append(r * y + i * x)
    out = []
    for l in range(degree + 1):
        for m in range(-l, l + 1):
            a = abs(m)
            if m == 0:
                out.append(_norm(l, 0) * Q[l][0])
            elif m > 0:
                out.append(math.sqrt(2) * _norm(l, a) * Q[l][a] * re[a])
            else:
                out.append(math.sqrt(2) * _norm(l, a) * Q[l][a] * im[a])
    return torch.stack(out, -1)


def sh_colour(degree: int, coeffs: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
    """(..., 3) 3DGS colour ``max(sum_k Y_k(dir) c_k + 0.5, 0)``; coeffs (..., K >= (degree+1)^2, 3)."""
    k = (degree + 1) ** 2
    return (torch.einsum("...k,...kc->...c", real_sh_3dgs(degree, dirs), coeffs[..., :k, :]) + 0.5).clamp_min(0)
