"""Real spherical harmonics of degree 0-3 for view-dependent colour (standard 3DGS form).

Coefficients are stored per Gaussian as ``(N, K, 3)`` with ``K = (degree + 1) ** 2`` in
the order of the 3DGS reference implementation (band 0, then band 1 as -y, z, -x, ...).
The colour is ``max(SH(dir) + 0.5, 0)``; :func:`rgb_to_sh` / :func:`sh_to_rgb` convert the
DC term. All functions are plain polynomials in the unit direction, so they are finite and
smooth everywhere, poles included.
"""

from __future__ import annotations

import torch

from l3d_app.errors import UserError

SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005,
         -1.0925484305920792, 0.5462742152960396)
SH_C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
         -0.4570457994644658, 1.445305721320277, -0.5900435899266435)


def num_sh_coeffs(degree: int) -> int:
    """Number of coefficients per colour channel up to ``degree`` (0-3): (degree + 1)^2."""
    if not 0 <= int(degree) <= 3:
        raise UserError(f"SH degree must be in 0..3, got {degree}")
    return (int(degree) + 1) ** 2


def sh_basis(degree: int, dirs: torch.Tensor) -> torch.Tensor:
    """(..., K) real SH basis values up to ``degree`` (0-3) at unit directions (..., 3),
    ``K = (degree + 1)^2``, in the 3DGS order and sign convention."""
    k = num_sh_coeffs(degree)
    x, y, z = dirs.movedim(-1, 0).contiguous()      # contiguous rows: the polynomial runs vectorised
    terms = [torch.full_like(x, SH_C0)]
    if degree >= 1:
        terms += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    if degree >= 2:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        terms += [SH_C2[0] * xy, SH_C2[1] * yz, SH_C2[2] * (2.0 * zz - xx - yy), SH_C2[3] * xz,
                  SH_C2[4] * (xx - yy)]
    if degree >= 3:
        terms += [SH_C3[0] * y * (3.0 * xx - yy), SH_C3[1] * xy * z, SH_C3[2] * y * (4.0 * zz - xx - yy),
                  SH_C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy), SH_C3[4] * x * (4.0 * zz - xx - yy),
                  SH_C3[5] * z * (xx - yy), SH_C3[6] * x * (xx - 3.0 * yy)]
    assert len(terms) == k
    return torch.stack(terms, -1)


def eval_sh(degree: int, coeffs: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
    """Evaluate SH up to ``degree`` (0-3).

    Args:
        coeffs: (..., K, C) with K >= (degree + 1)^2 (extra coefficients are ignored).
        dirs: (..., 3) unit viewing directions (camera -> point, world frame).
    Returns:
        (..., C) raw SH value (add 0.5 and clamp for a colour, see :func:`sh_to_color`):
        ``sum_k basis_k coeffs_k`` by :class:`BasisDot`.
    """
    k = num_sh_coeffs(degree)
    if coeffs.shape[-2] < k:
        raise ValueError(f"degree {degree} needs {k} SH coefficients, got {coeffs.shape[-2]}")
    basis = sh_basis(degree, dirs)
    return BasisDot.apply(basis, coeffs[..., :k, :])


class BasisDot(torch.autograd.Function):
    """``out[..., c] = sum_k basis[..., k] coeffs[..., k, c]`` with a hand-written backward.

    forward(basis (..., K), coeffs (..., K, C)) -> (..., C): one batched (1, K) @ (K, C) product.
    Its autograd backward would be two more batched products of tiny matrices, slow on CPU
    (forward + backward 20-21 ms at 63 609 Gaussians, K = 16, C = 3, 2 cores, the forward 2.4-2.7
    of it); here the coefficients' gradient is one outer product ``basis[..., k] g[..., c]`` and the
    basis' gradient C fused multiply-adds ``sum_c coeffs[..., k, c] g[..., c]`` (13-15 ms in all).
    """

    @staticmethod
    def forward(ctx, basis, coeffs):
        ctx.save_for_backward(basis, coeffs)
        return torch.matmul(basis.unsqueeze(-2), coeffs).squeeze(-2)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, g):
        basis, coeffs = ctx.saved_tensors
        g_basis = g_coeffs = None
        if ctx.needs_input_grad[0]:
            g_basis = coeffs[..., 0] * g[..., None, 0]
            for c in range(1, coeffs.shape[-1]):
                g_basis.addcmul_(coeffs[..., c], g[..., None, c])     # the first product has the full shape
            g_basis = g_basis.sum_to_size(basis.shape)
        if ctx.needs_input_grad[1]:
            g_coeffs = (basis.unsqueeze(-1) * g.unsqueeze(-2)).sum_to_size(coeffs.shape)
        return g_basis, g_coeffs        # summed over the dimensions an input was broadcast along


def sh_to_color(degree: int, coeffs: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
    """(..., C) colour ``max(eval_sh + 0.5, 0)`` as in 3DGS."""
    return (eval_sh(degree, coeffs, dirs) + 0.5).clamp_min(0.0)


def rgb_to_sh(rgb: torch.Tensor) -> torch.Tensor:
    """DC coefficient giving colour ``rgb`` (any shape)."""
    return (rgb - 0.5) / SH_C0


def sh_to_rgb(dc: torch.Tensor) -> torch.Tensor:
    """Inverse of :func:`rgb_to_sh`."""
    return dc * SH_C0 + 0.5
