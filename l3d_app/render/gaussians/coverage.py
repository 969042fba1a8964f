"""How many splats cover a pixel, and initial scales that keep that bounded.

The cost of a Gaussian render (forward and backward) grows with the number of (pixel,
splat) pairs it composites, about ``coverage x H x W`` where the coverage is the summed
screen area of the splats' discs (the culling radius of
:func:`~l3d_app.render.gaussians.rasterize.project_gaussians`) over the image area. Splats drawn at
random in a scene box with neighbour-distance scales overlap ~70 deep per pixel; trained
ones ~30 (measured on the built-in scene), so the first steps of such a run cost several
times the later ones. :func:`shrink_to_coverage` scales the initial splats down until the
coverage is at most a bound by one common factor; :func:`cap_to_coverage` keeps the same bound by
lowering only the splats that cover the most (a room's few isolated SfM points with huge
neighbour distances would otherwise shrink every splat to a dot).
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
    return _disc_areas(means, log_scales, quats, opacity, cams).sum(-1) / float(cams.width * cams.height)


def _disc_areas(means, log_scales, quats, opacity, cams: Cameras) -> torch.Tensor:
    """(B, N) ``pi radius^2`` (px^2) of each splat's culling disc in each camera (0: culled)."""
    p = project_gaussians(means, log_scales, quats, opacity, cams.to(device=means.device, dtype=means.dtype))
    return math.pi * p["radius"] ** 2


@torch.no_grad()
def splat_coverage(means: torch.Tensor, log_scales: torch.Tensor, quats: torch.Tensor, opacity: torch.Tensor,
                   cams: Cameras) -> torch.Tensor:
    """(N,) each splat's share of the mean :func:`screen_coverage` over ``cams``: its disc area over
    the image area, averaged over the cameras (their sum is the mean coverage)."""
    return _disc_areas(means, log_scales, quats, opacity, cams).mean(0) / float(cams.width * cams.height)


def water_level(cover: torch.Tensor, bound: float) -> float:
    """The level ``c`` at which ``sum_i min(cover_i, c) = bound`` (``cover`` (N,) >= 0); inf when
    ``sum cover <= bound`` already."""
    s = cover.double().sort(descending=True).values
    if float(s.sum()) <= bound:
        return float("inf")
    k = torch.arange(1, len(s) + 1, dtype=torch.float64)
    rest = s.sum() - s.cumsum(0)                      # sum of the splats below the k largest
    level = (bound - rest) / k                        # the k largest at one level, the rest as they are
    below = torch.cat([s[1:], s.new_zeros(1)])
    return float(level[int(torch.nonzero(level >= below)[0])])


@torch.no_grad()
def cap_to_coverage(means: torch.Tensor, log_scales: torch.Tensor, quats: torch.Tensor, opacity: torch.Tensor,
                    cams: Cameras, max_coverage: float, rounds: int = 5) -> torch.Tensor:
    """``log_scales`` (N, S) with each splat whose :func:`splat_coverage` is above a common level
    ``c`` scaled down to that level (area ~ scale^2), the others unchanged, so that the mean
    :func:`screen_coverage` over ``cams`` is at most ``max_coverage`` (:func:`water_level`; a few
    rounds aiming 1% below, as in :func:`shrink_to_coverage`)."""
    if max_coverage <= 0:
        raise UserError(f"max_coverage must be > 0, got {max_coverage}")
    out = log_scales.clone()
    for _ in range(rounds):
        cover = splat_coverage(means, out.expand(-1, 3), quats, opacity, cams)
        if float(cover.sum()) <= max_coverage:
            break
        level = water_level(cover, 0.99 * max_coverage)
        out = out + 0.5 * torch.log((level / cover.double().clamp_min(1e-30)).clamp(max=1.0)).to(out.dtype)[:, None]
    return out


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
