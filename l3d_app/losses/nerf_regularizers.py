"""Regularisers of a radiance field optimised by score distillation (DreamFusion / Ref-NeRF).

* :func:`opacity_entropy`: the binary entropy of each ray's opacity, in bits,
  ``H(a) = -a log2 a - (1 - a) log2 (1 - a)``: 0 at a = 0 or 1, 1 at a = 1/2. It pushes
  rays to be either empty or opaque (no semi-transparent fog around the object).
* :func:`orientation_penalty`: Ref-NeRF's orientation loss per sample,
  ``max(0, n . d)^2`` with ``n`` the unit normal and ``d`` the unit ray direction (from the
  camera into the scene): 0 for normals facing the camera (``n . d <= 0``), up to 1 for
  normals facing away. Summed along a ray with the compositing weights,
  ``sum_i w_i max(0, n_i . d)^2``, it penalises visible back-facing geometry.
* :func:`density_normals`: unit normals ``-grad sigma / |grad sigma|`` by autograd.
"""

from __future__ import annotations

import torch


def opacity_entropy(opacity: torch.Tensor, eps: float = 1e-5) -> torch.Tensor:
    """Mean binary entropy (bits) of opacities in [0, 1] (any shape) -> scalar.

    ``opacity`` is clamped to [eps, 1 - eps] so the value and gradient stay finite at the
    minima 0 and 1.
    """
    a = opacity.clamp(eps, 1.0 - eps)
    return (-(a * torch.log2(a)) - (1.0 - a) * torch.log2(1.0 - a)).mean()


def orientation_penalty(normals: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
    """(...,) ``max(0, n . d)^2`` for unit normals and ray directions (..., 3)."""
    return (normals * dirs).sum(-1).clamp_min(0.0) ** 2


def density_normals(sigma: torch.Tensor, points: torch.Tensor, create_graph: bool = True,
                    eps: float = 1e-12) -> torch.Tensor:
    """Unit outward normals ``-grad sigma / |grad sigma|`` (N, 3) at ``points`` (N, 3).

    ``sigma`` (N,) must have been computed from ``points`` (which requires grad) with
    autograd enabled. With ``create_graph`` the normals are differentiable w.r.t. the
    field's parameters (needed to train through shading and the orientation penalty).
    Where the gradient vanishes the normal is 0.
    """
    (grad,) = torch.autograd.grad(sigma.sum(), points, create_graph=create_graph)
    return -grad / grad.norm(dim=-1, keepdim=True).clamp_min(eps)
