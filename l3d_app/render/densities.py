"""SDF -> density/opacity conversions, written so that no exponential can overflow.

VolSDF (Yariv et al. 2021) turns a signed distance ``d`` into a density
``sigma = alpha * Psi_beta(-d)`` where ``Psi_beta`` is the CDF of a zero-mean Laplace
distribution with scale ``beta``::

    Psi_beta(x) = 0.5 * exp(x / beta)          for x <= 0
                = 1 - 0.5 * exp(-x / beta)     for x > 0

Each branch is evaluated on an argument clamped to its own half-line, so the exponent is
always <= 0: nothing overflows for any ``beta > 0`` and ``|x|`` (1e3 / 1e-4 = 1e7 is just
``exp(-1e7) = 0``), and the branch that ``torch.where`` discards has a finite value and a
finite gradient, so no NaN leaks into autograd.
"""

from __future__ import annotations

from typing import Union

import torch

Scalar = Union[float, torch.Tensor]


def laplace_cdf(x: torch.Tensor, beta: Scalar) -> torch.Tensor:
    """CDF of a Laplace(0, beta) distribution, elementwise, values in [0, 1].

    Args:
        x: any shape (e.g. world units when ``x = -sdf``).
        beta: scale > 0 (same units as ``x``); a float or a tensor broadcastable to ``x``
            (it may require grad).
    Returns:
        tensor of ``x``'s shape: ``0.5 exp(x/beta)`` for ``x <= 0``, ``1 - 0.5 exp(-x/beta)``
        for ``x > 0``. Derivative ``0.5 exp(-|x|/beta) / beta`` everywhere (also at 0).
    """
    neg = 0.5 * torch.exp(x.clamp_max(0.0) / beta)          # exponent <= 0
    pos = 1.0 - 0.5 * torch.exp(-x.clamp_min(0.0) / beta)   # exponent <= 0
    return torch.where(x <= 0, neg, pos)


def volsdf_density(sdf: torch.Tensor, alpha: Scalar, beta: Scalar) -> torch.Tensor:
    """VolSDF density ``alpha * Psi_beta(-sdf)`` (same shape as ``sdf``).

    ``alpha`` is the density inside the surface (1 / world units when used as sigma),
    ``beta`` the smoothing length (world units). The box task uses this value directly as
    a per-sample opacity (the course's rule), see ``l3d_app/tasks/box.py``.
    """
    return alpha * laplace_cdf(-sdf, beta)
