"""Dolly-zoom framing by the subject's projected extent (exact for any shape, at any fov).

The bounding-sphere rule (:func:`l3d_app.geometry.camera_paths.dolly_distance`) keeps a
*sphere* at a fixed on-screen size; a non-spherical subject seen from close up at a wide
field of view changes its projected width (measured: the cow of ``cow_on_plane.obj``
drifts by 17% over fov 5-120 degrees). Here the distance of each frame is solved so that
the subject's horizontal projected extent is exactly ``fraction`` of the image width.

For a camera on the fixed look-at direction at distance ``D`` from ``at``, a point ``p``
has camera coordinates ``X = r . (p - at)``, ``Z = D + w . (p - at)`` (``r`` the camera's
right axis, ``w`` its forward axis), and the extent of the points is
``f (max_i X_i / Z_i - min_i X_i / Z_i)`` pixels. The silhouette of a triangle mesh
reaches its leftmost and rightmost pixels at vertices, so this is the mesh's on-screen
width. For a point set on both sides of the optical axis the extent falls monotonically
with ``D``; it is solved by bisection, vectorised over the frames, in float64.
"""

from __future__ import annotations

from typing import Sequence, Tuple

import torch

from l3d_app.geometry.cameras import Cameras, look_at


def extent_distances(points: torch.Tensor, fov_deg: torch.Tensor, fraction: float, elevation: float = 0.0,
                     azimuth: float = 0.0, at: Sequence[float] = (0.0, 0.0, 0.0),
                     iters: int = 80) -> torch.Tensor:
    """(N,) camera distances (world units) at which ``points`` (P, 3) span ``fraction`` of the
    image width for each field of view in ``fov_deg`` (N,) (degrees, across the square image).

    The search runs over ``D`` in (nearest point in front of the camera, far enough); the
    returned distance leaves every point in front of the camera.
    """
    if not 0 < float(fraction) < 1:
        raise ValueError(f"fraction must be in (0, 1), got {fraction}")
    if points.dim() != 2 or points.shape[-1] != 3 or points.shape[0] < 2:
        raise ValueError(f"points must be (P >= 2, 3), got {tuple(points.shape)}")
    p = points.detach().to(torch.float64).cpu()
    centre = torch.as_tensor(at, dtype=torch.float64)
    R, _ = look_at(1.0, elevation, azimuth, at=centre.tolist(), dtype=torch.float64)
    x = (p - centre) @ R[0, 0]                                           # (P,) along the camera's right
    z = (p - centre) @ R[0, 2]                                           # (P,) along its forward axis
    fov = torch.as_tensor(fov_deg, dtype=torch.float64).reshape(-1)
    target = 2.0 * float(fraction) * torch.tan(torch.deg2rad(fov) / 2)  # extent / f, in (X/Z) units

    def extent(d: torch.Tensor) -> torch.Tensor:                         # d (N,) -> (N,)
        ratio = x[None] / (d[:, None] + z[None])
        return ratio.amax(dim=1) - ratio.amin(dim=1)

    radius = float((p - centre).norm(dim=-1).max())
    lo = torch.full_like(fov, float(-z.min()) + 1e-9 * max(radius, 1e-12))
    hi = torch.full_like(fov, radius * 2.0 + 1e-9)
    for _ in range(200):                                                 # grow hi until the extent is small enough
        short = extent(hi) > target
        if not bool(short.any()):
            break
        hi = torch.where(short, hi * 2.0, hi)
    for _ in range(int(iters)):
        mid = 0.5 * (lo + hi)
        too_wide = extent(mid) > target
        lo, hi = torch.where(too_wide, mid, lo), torch.where(too_wide, hi, mid)
    return (0.5 * (lo + hi)).to(points.dtype)


def dolly_cameras(distances: torch.Tensor, fov_deg: torch.Tensor, image_size: int, elevation: float = 0.0,
                  azimuth: float = 0.0, at: Sequence[float] = (0.0, 0.0, 0.0), device=None) -> Cameras:
    """Square cameras at ``distances`` (N,) from ``at`` on one look-at direction, fov (N,) degrees."""
    R, t = look_at(distances.float(), elevation, azimuth, at=list(at), device=device)
    return Cameras.from_fov(R, t, fov_deg.float().to(R.device), int(image_size), int(image_size))
