"""The two geometric regularisers of 2D Gaussian splatting (Huang et al. 2024), on a surfel render
(:func:`~l3d_app.render.gaussians.surfels.rasterize_surfels`).

* :func:`depth_distortion`: the mean over pixels of ``sum_{k, j<k} w_k w_j (z_k - z_j)^2`` (the
  render's ``distortion``), over ``scale^2`` so that the weight does not depend on the scene's units:
  it pulls each pixel's contributions together in depth, onto one surface.
* :func:`depth_normal_consistency`: the mean over pixels of ``alpha (alpha - n . N)``: ``n`` the
  rendered normal (``sum w n``, of length about ``alpha``), ``N`` the unit normal of the rendered
  depth map (:func:`~l3d_app.geometry.depth_normals.depth_to_normals`), ``alpha`` the accumulated
  opacity (no gradient). It is ``alpha^2 (1 - cos)`` for aligned weights: the splats' orientations
  and the surface their depths describe are made to agree; the gradient is 2DGS's
  ``1 - alpha n . N`` (a pixel's weight in it is its opacity, so faint pixels do not pull the
  weights up). Pixels without a depth normal (image border, next to empty pixels) count 0.
"""

from __future__ import annotations

import torch

from l3d_app.geometry.cameras import Cameras
from l3d_app.geometry.depth_normals import depth_to_normals


def depth_distortion(distortion: torch.Tensor, scale: float) -> torch.Tensor:
    """Scalar: mean of ``distortion`` (B, H, W) (world units^2) over ``scale``^2 (world units)."""
    return distortion.mean() / float(scale) ** 2


def depth_normal_consistency(normal: torch.Tensor, depth: torch.Tensor, alpha: torch.Tensor,
                             cams: Cameras) -> torch.Tensor:
    """Scalar: mean of ``alpha (alpha - normal . N(depth))`` over the pixels (normal (B, H, W, 3)
    rendered, depth (B, H, W) camera z, alpha (B, H, W), no gradient through it); zero where the
    depth map has no normal."""
    N = depth_to_normals(depth, cams)
    has = (N * N).sum(-1) > 0
    a = alpha.detach()
    return torch.where(has, a * (a - (normal * N).sum(-1)), torch.zeros_like(a)).mean()
