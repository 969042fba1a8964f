"""Surface normals of a depth map: the cross product of its back-projected neighbours.

A pixel ``(i, j)`` with camera depth ``z`` back-projects to ``P = C + z d`` (``d`` the ray of camera
z = 1 through its centre, :func:`~l3d_app.geometry.rays.pixels_to_directions`); the normal is
``normalize((P[i+1, j] - P[i-1, j]) x (P[i, j+1] - P[i, j-1]))``, which faces the camera for
any surface the camera sees (image rows grow downwards, columns to the right). Differentiable
in the depth; used by the depth-normal consistency of Gaussian surfels.
"""

from __future__ import annotations

import torch

from l3d_app.geometry.cameras import Cameras
from l3d_app.geometry.rays import camera_rays


def depth_to_points(depth: torch.Tensor, cams: Cameras) -> torch.Tensor:
    """(B, H, W, 3) world points of depth maps (B, H, W) (camera z, world units)."""
    origins, dirs = camera_rays(cams.to(device=depth.device, dtype=depth.dtype), normalize=False)
    return origins + depth[..., None] * dirs


def depth_to_normals(depth: torch.Tensor, cams: Cameras, eps: float = 1e-12) -> torch.Tensor:
    """(B, H, W, 3) unit world normals of depth maps (B, H, W) by central differences, facing
    the camera; zero on the one-pixel border (no neighbour on one side) and where one of the four
    neighbours has no depth (<= 0: no surface)."""
    P = depth_to_points(depth, cams)
    dv = P[:, 2:, 1:-1] - P[:, :-2, 1:-1]
    du = P[:, 1:-1, 2:] - P[:, 1:-1, :-2]
    n = torch.cross(dv, du, dim=-1)
    n = n * torch.rsqrt((n * n).sum(-1, keepdim=True).clamp_min(eps))
    has = (depth[:, 2:, 1:-1] > 0) & (depth[:, :-2, 1:-1] > 0) & (depth[:, 1:-1, 2:] > 0) & (depth[:, 1:-1, :-2] > 0)
    n = torch.where(has[..., None], n, torch.zeros_like(n))
    return torch.nn.functional.pad(n, (0, 0, 1, 1, 1, 1))
