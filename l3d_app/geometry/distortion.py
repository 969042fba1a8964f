"""Lens distortion (Brown-Conrady radial + tangential, as COLMAP's OPENCV / RADIAL /
SIMPLE_RADIAL models and nerfstudio's ``k1..k4, p1, p2``) and image undistortion.

Normalised image coordinates ``(x, y) = ((u - cx) / fx, (v - cy) / fy)`` of an ideal pinhole
map to distorted ones by, with ``r2 = x^2 + y^2``,

    radial = k1 r2 + k2 r2^2 + k3 r2^3 + k4 r2^4
    xd = x + x radial + 2 p1 x y + p2 (r2 + 2 x^2)
    yd = y + y radial + p1 (r2 + 2 y^2) + 2 p2 x y

(COLMAP's OPENCV model is k1, k2, p1, p2; SIMPLE_RADIAL k1; RADIAL k1, k2.)

Choice: images are UNDISTORTED ONCE AT LOAD (:func:`undistort_image`), so every renderer
keeps its pinhole cameras. Undistortion needs only the forward model: the undistorted image
at pixel (u, v) samples the captured image at ``distort(u, v)`` (bilinear,
``grid_sample``), with the same ``fx, fy, cx, cy``. Pixels whose source falls outside the
captured frame are filled from the nearest border pixel and reported in a mask.
:func:`undistort_points` is the inverse (Newton iterations), for mapping observed
(distorted) pixel positions to the pinhole image.
"""

from __future__ import annotations

from typing import Sequence, Tuple

import torch

from l3d_app.errors import UserError


def _coeffs(dist: Sequence[float], like: torch.Tensor) -> torch.Tensor:
    d = torch.as_tensor(dist, dtype=like.dtype, device=like.device).reshape(-1)
    if d.numel() != 6:
        raise UserError(f"distortion must be 6 numbers (k1, k2, k3, k4, p1, p2), got {d.numel()}")
    return d


def distort(xy: torch.Tensor, dist: Sequence[float]) -> torch.Tensor:
    """(..., 2) normalised pinhole coordinates -> (..., 2) distorted normalised coordinates.
    ``dist`` = (k1, k2, k3, k4, p1, p2)."""
    k1, k2, k3, k4, p1, p2 = _coeffs(dist, xy)
    x, y = xy[..., 0], xy[..., 1]
    r2 = x * x + y * y
    radial = r2 * (k1 + r2 * (k2 + r2 * (k3 + r2 * k4)))
    xd = x + x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y + y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return torch.stack([xd, yd], -1)


def undistort_points(xy_d: torch.Tensor, dist: Sequence[float], iters: int = 20) -> torch.Tensor:
    """Inverse of :func:`distort` by Newton's method with the closed-form 2x2 Jacobian;
    (..., 2) -> (..., 2). Converges in a few iterations for the
    distortion of real lenses (|displacement| well below the radius)."""
    k1, k2, k3, k4, p1, p2 = _coeffs(dist, xy_d)
    xy = xy_d.clone()
    for _ in range(int(iters)):
        x, y = xy[..., 0], xy[..., 1]
        r2 = x * x + y * y
        radial = r2 * (k1 + r2 * (k2 + r2 * (k3 + r2 * k4)))
        dr = k1 + r2 * (2 * k2 + r2 * (3 * k3 + r2 * 4 * k4))          # d radial / d r2
        fx = x + x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x) - xy_d[..., 0]
        fy = y + y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y - xy_d[..., 1]
        a = 1 + radial + 2 * x * x * dr + 2 * p1 * y + 6 * p2 * x          # d fx / dx
        b = 2 * x * y * dr + 2 * p1 * x + 2 * p2 * y                        # d fx / dy
        c = 2 * x * y * dr + 2 * p1 * x + 2 * p2 * y                        # d fy / dx
        d = 1 + radial + 2 * y * y * dr + 6 * p1 * y + 2 * p2 * x           # d fy / dy
        det = a * d - b * c
        det = torch.where(det.abs() < 1e-12, torch.full_like(det, 1e-12), det)
        xy = torch.stack([x - (d * fx - b * fy) / det, y - (a * fy - c * fx) / det], -1)
    return xy


def undistort_image(image: torch.Tensor, fx: float, fy: float, cx: float, cy: float,
                    dist: Sequence[float]) -> Tuple[torch.Tensor, torch.Tensor]:
    """Pinhole image from a distorted one with the same intrinsics.

    Args:
        image: (H, W, C) float.
        fx, fy, cx, cy: intrinsics in pixels (pixel centres at +0.5).
        dist: (k1, k2, k3, k4, p1, p2).
    Returns:
        (H, W, C) undistorted image and (H, W) bool mask of pixels whose source lay inside
        the captured frame.
    """
    H, W = image.shape[:2]
    dt = torch.float64
    v, u = torch.meshgrid(torch.arange(H, dtype=dt) + 0.5, torch.arange(W, dtype=dt) + 0.5, indexing="ij")
    xy = torch.stack([(u - cx) / fx, (v - cy) / fy], -1)
    xd = distort(xy, dist)
    us, vs = xd[..., 0] * fx + cx, xd[..., 1] * fy + cy                 # source pixel coords
    inside = (us >= 0) & (us <= W) & (vs >= 0) & (vs <= H)
    grid = torch.stack([us / W * 2 - 1, vs / H * 2 - 1], -1).to(image.dtype)     # align_corners=False
    out = torch.nn.functional.grid_sample(image.permute(2, 0, 1)[None], grid[None].to(image.device),
                                          mode="bilinear", padding_mode="border", align_corners=False)
    return out[0].permute(1, 2, 0).contiguous(), inside.to(image.device)
