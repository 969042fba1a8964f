"""EWA projection of 3D Gaussians into one camera, with a hand-written backward.

Same forward as :func:`l3d_app.render.gaussians.rasterize.project_gaussians` (its plain-autograd
reference, which the tests compare with), as one :class:`torch.autograd.Function` so that
the ~100 small per-Gaussian ops do not each record an autograd node. Per Gaussian:

* ``p = R m + t``; ``u = fx x/z + cx``, ``v = fy y/z + cy``; ``J`` with ``x/z``, ``y/z``
  clamped to 1.3x the frustum;
* ``M = R_q diag(exp(log_scale))`` (quaternion normalised; zero -> identity),
  ``T = J R``, ``Sigma_2D = (T M)(T M)^T + 0.3 I = [[a, b], [b, c]]``;
* conic ``(A, B, C) = (c, -b, a) / (a c - b^2)``, computed on the matrix normalised by
  ``max(a, c)`` so that huge covariances do not overflow.

Backward, with ``(A, B, C)`` the conic: ``dA/da = -A^2``, ``dA/db = -2AB``, ``dA/dc = -B^2``,
``dB/da = -AB``, ``dB/db = -(AC + B^2)``, ``dB/dc = -BC``, ``dC/da = -B^2``, ``dC/db = -2BC``,
``dC/dc = -C^2`` (no determinant squared: nothing overflows), then the chain through
``T M``, the quaternion rotation and its normalisation, the clamped Jacobian and ``p``.

Both passes work attribute-major: every per-Gaussian quantity is a row of N contiguous
values (a 3-vector is (3, N), a 3x3 matrix (3, 3, N)), so each of the ~100 small ops is one
vectorised pass and the 3x3 products reduce over leading dimensions; on CPU this is several
times faster than the same ops on (N, 3) / (N, 3, 3) arrays.
"""

from __future__ import annotations

import torch

LOW_PASS = 0.3


def _quat_rows(q: torch.Tensor, eps: float = 1e-12):
    """(4, N) any-norm quaternions (rows w, x, y, z) -> unit quaternions (4, N), norms (1, N),
    ok (1, N), rotations (3, 3, N)."""
    sq = (q * q).sum(0, keepdim=True)
    ok = sq > eps * eps
    n = torch.sqrt(sq.clamp_min(eps * eps))
    ident = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=q.dtype, device=q.device)[:, None]
    qn = torch.where(ok, q / n, ident)
    w, x, y, z = qn
    R = torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ]).reshape(3, 3, -1)
    return qn, n, ok, R


def quat_rotation(q: torch.Tensor, eps: float = 1e-12):
    """(N, 4) any-norm quaternions -> unit quaternions (N, 4), norms (N, 1), ok (N, 1), R (N, 3, 3)."""
    qn, n, ok, R = _quat_rows(q.t(), eps)
    return qn.t(), n.t(), ok.t(), R.permute(2, 0, 1)


def _quat_backward(dR: torch.Tensor, qn: torch.Tensor, n: torch.Tensor, ok: torch.Tensor) -> torch.Tensor:
    """dL/dq (4, N) from dL/dR (3, 3, N) through the rotation of the normalised quaternion
    (qn (4, N), n and ok (1, N) from :func:`_quat_rows`)."""
    w, x, y, z = qn
    r00, r01, r02, r10, r11, r12, r20, r21, r22 = dR.reshape(9, -1)
    dw = 2 * (-z * r01 + y * r02 + z * r10 - x * r12 - y * r20 + x * r21)
    dx = 2 * (y * r01 + z * r02 + y * r10 - 2 * x * r11 - w * r12 + z * r20 + w * r21 - 2 * x * r22)
    dy = 2 * (-2 * y * r00 + x * r01 + w * r02 + x * r10 + z * r12 - w * r20 + z * r21 - 2 * y * r22)
    dz = 2 * (-2 * z * r00 - w * r01 + x * r02 + w * r10 - 2 * z * r11 + y * r12 + x * r20 + y * r21)
    dqn = torch.stack([dw, dx, dy, dz])
    dq = (dqn - qn * (qn * dqn).sum(0, keepdim=True)) / n
    return torch.where(ok, dq, torch.zeros_like(dq))


class ProjectFunction(torch.autograd.Function):
    """forward(means (N, 3), log_scales (N, 3), quats (N, 4), R (3, 3), t (3,), intrinsics
    (fx, fy, cx, cy floats), width, height, near) -> means2d (N, 2) px, conic (N, 3),
    depth (N,) camera z, and (no gradient) the covariance diagonal ``(a, c)`` (N, 2) px^2,
    ``lam_max`` (N,) px^2 and ``in_front`` (N,) bool."""

    @staticmethod
    def forward(ctx, means, log_scales, quats, R, t, fx, fy, cx, cy, width, height, near):
        p = R @ means.t() + t[:, None]                                          # (3, N)
        x, y, z = p
        in_front = z > near
        zs = torch.where(in_front, z, torch.ones_like(z))
        inv = 1.0 / zs
        xr, yr = x * inv, y * inv
        lo_x, hi_x = (-0.15 * width - cx) / fx, (1.15 * width - cx) / fx
        lo_y, hi_y = (-0.15 * height - cy) / fy, (1.15 * height - cy) / fy
        xz, yz = xr.clamp(lo_x, hi_x), yr.clamp(lo_y, hi_y)
        means2d = torch.stack([fx * xr + cx, fy * yr + cy], -1)
        # T = J R: rows fx/z R0 - fx xz/z R2 and fy/z R1 - fy yz/z R2, each (3, N)
        T0 = R[0][:, None] * (fx * inv) - R[2][:, None] * (fx * xz * inv)
        T1 = R[1][:, None] * (fy * inv) - R[2][:, None] * (fy * yz * inv)
        qn, n, ok, Rq = _quat_rows(quats.t())
        s = torch.exp(log_scales.t())                                           # (3, N)
        M = Rq * s                                                              # (3, 3, N): R_q diag(s)
        TM0 = (T0[:, None] * M).sum(0)                                          # (3, N) = T0 @ M
        TM1 = (T1[:, None] * M).sum(0)
        a = (TM0 * TM0).sum(0) + LOW_PASS
        b = (TM0 * TM1).sum(0)
        c = (TM1 * TM1).sum(0) + LOW_PASS
        k = torch.maximum(a, c)
        an, bn, cn = a / k, b / k, c / k
        det_n = (an * cn - bn * bn).clamp_min(1e-20)
        conic = torch.stack([cn, -bn, an], -1) / (det_n * k)[:, None]
        mid = 0.5 * (an + cn)
        lam_max = k * (mid + torch.sqrt((mid * mid - det_n).clamp_min(0.0)))
        clamp_x = (xr >= lo_x) & (xr <= hi_x)
        clamp_y = (yr >= lo_y) & (yr <= hi_y)
        ctx.save_for_backward(R, x, y, inv, xz, yz, in_front, clamp_x, clamp_y, T0, T1, qn, n, ok, Rq, s, M,
                              TM0, TM1, conic)
        ctx.intr = (fx, fy)
        diag = torch.stack([a, c], -1)
        ctx.mark_non_differentiable(diag, lam_max, in_front)
        return means2d, conic, z, diag, lam_max, in_front

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, g_m2, g_conic, g_z, _g_diag, _g_lam, _g_front):
        (R, x, y, inv, xz, yz, in_front, clamp_x, clamp_y, T0, T1, qn, n, ok, Rq, s, M,
         TM0, TM1, conic) = ctx.saved_tensors
        fx, fy = ctx.intr
        A, B, C = conic.t()
        gA, gB, gC = g_conic.t()
        ga = -(gA * A * A + gB * A * B + gC * B * B)
        gb = -(2 * gA * A * B + gB * (A * C + B * B) + 2 * gC * B * C)
        gc = -(gA * B * B + gB * B * C + gC * C * C)
        dTM0 = 2 * ga * TM0 + gb * TM1                                          # (3, N)
        dTM1 = 2 * gc * TM1 + gb * TM0
        dT0 = (M * dTM0).sum(1)                                                 # dTM0 @ M^T
        dT1 = (M * dTM1).sum(1)
        dM = T0[:, None] * dTM0 + T1[:, None] * dTM1                            # (3, 3, N)
        g_ls = (dM * Rq).sum(0) * s
        g_q = _quat_backward(dM * s, qn, n, ok)
        r0, r1 = (dT0 * R[0][:, None]).sum(0), (dT1 * R[1][:, None]).sum(0)
        e0, e1 = (dT0 * R[2][:, None]).sum(0), (dT1 * R[2][:, None]).sum(0)
        g_inv = fx * r0 - fx * xz * e0 + fy * r1 - fy * yz * e1
        g_xr = torch.where(clamp_x, -fx * inv * e0, torch.zeros_like(e0)) + fx * g_m2[:, 0]
        g_yr = torch.where(clamp_y, -fy * inv * e1, torch.zeros_like(e1)) + fy * g_m2[:, 1]
        g_inv = g_inv + g_xr * x + g_yr * y
        g_zs = -g_inv * inv * inv
        g_p = torch.stack([g_xr * inv, g_yr * inv, g_z + torch.where(in_front, g_zs, torch.zeros_like(g_zs))])
        return g_p.t() @ R, g_ls.t(), g_q.t(), None, None, None, None, None, None, None, None, None
