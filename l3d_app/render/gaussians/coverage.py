"""How many splats cover a pixel, and initial scales that keep that bounded.

The cost of a Gaussian render (forward and backward) grows with the number of (pixel,
splat) pairs it composites, about ``coverage x H x W`` where the coverage is the summed
screen area of the splats' discs (the culling radius of
:func:`~l3d_app.render.gaussians.rasterize.project_gaussians`) over the image area. Splats drawn at
random in a scene box with neighbour-distance scales overlap ~70 deep per pixel; trained
ones ~30 (measured on the built-in scene), so the first steps of such a run cost several
times the later ones. :func:`shrink_to_coverage` scales the initial splats down until the
coverage is at most a bound.
"""

from __future__ import annotations

import math

import torch

from l3d_app.errors import UserError
from l3d_app.geometry.cameras import Cameras
from l3d_app.render.gaussians.rasterize import project_gaussians


@torch.no_grad()
def screen_coverage(means: torch.Tensor, log_scales: torch.Tensor, quats: torch.Tensor, opacity: torch.Tensor,
                    cams: Cameras) -> torch.Tensor:
    """(B,) sum over visible splats of ``pi radius^2`` / (H W): the mean splats per pixel.

    means (N, 3), log_scales (N, 3), quats (N, 4), opacity (N,) in [0, 1]; cams: B cameras.
    """
    p = project_gaussians(means, log_scales, quats, opacity, cams.to(device=means.device, dtype=means.dtype))
    return (math.pi * p["radius"] ** 2).sum(-1) / float(cams.width * cams.height)


@torch.no_grad()
def shrink_to_coverage(means: torch.Tensor, log_scales: torch.Tensor, quats: torch.Tensor, opacity: torch.Tensor,
                       cams: Cameras, max_coverage: float, rounds: int = 5) -> torch.Tensor:
    """``log_scales`` (N, S) shifted by one common ``log f <= 0`` so that the mean
    :func:`screen_coverage` over ``cams`` is at most ``max_coverage`` (unchanged when it
    already is). A few rounds aiming 1% below the bound, since the 0.3 px low-pass keeps
    areas from scaling exactly as f^2."""
    if max_coverage <= 0:
        raise UserError(f"max_coverage must be > 0, got {max_coverage}")
    out = log_scales.clone()
    for _ in range(rounds):
        cov = float(screen_coverage(means, out.expand(-1, 3), quats, opacity, cams).mean())
        if cov <= max_coverage:
            break
        out = out + 0.5 * math.log(0.99 * max_coverage / cov)
    return out
