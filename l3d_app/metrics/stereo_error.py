"""How disparity noise becomes depth error in a rectified stereo rig, measured against the first-order law.

With ``d = f B / Z`` and a measured disparity ``d + n``, ``n ~ N(0, sigma^2)`` pixels, the
recovered depth ``f B / (d + n)`` has, to first order, the error ``Z^2 / (f B) * n``, so its
RMS over a depth map is ``sigma * sqrt(mean(Z^4)) / (f B)``: quadratic in depth, inverse in
focal length and in baseline, linear in the disparity error
(:func:`l3d_app.geometry.stereo.depth_error_from_disparity_error`). :func:`simulate_depth_error`
draws the noise, recovers the depth exactly and reports both figures.
"""

from __future__ import annotations

from typing import Dict

import torch

from l3d_app.geometry.stereo import depth_to_disparity, disparity_to_depth
from l3d_app.runtime.random import randn


def noisy_depth(depth: torch.Tensor, focal_px: float, baseline: float, sigma_px: float,
                generator: torch.Generator) -> Dict[str, torch.Tensor]:
    """Disparity of ``depth`` (...) (world units), the same plus N(0, sigma_px^2) noise, and
    the depth recovered from the noisy disparity (``+inf`` where it is not positive)."""
    disparity = depth_to_disparity(depth, focal_px, baseline)
    noisy = disparity + float(sigma_px) * randn(depth.shape, generator, device=depth.device).to(depth.dtype)
    return {"disparity": disparity, "noisy_disparity": noisy,
            "depth": disparity_to_depth(noisy, focal_px, baseline)}


def simulate_depth_error(depth: torch.Tensor, focal_px: float, baseline: float, sigma_px: float,
                         generator: torch.Generator, trials: int = 4) -> Dict[str, float]:
    """RMS depth error over the (N,) valid depths, measured over ``trials`` noise draws, and
    the first-order prediction; ``lost`` counts draws whose disparity fell to <= 0.

    Returns rmse (measured, world units), rmse_first_order, ratio (measured / predicted),
    bias (mean signed error), lost (fraction of draws with no finite depth).
    """
    z = depth.reshape(-1).to(torch.float64)
    zs = z.expand(int(trials), -1)
    out = noisy_depth(zs, focal_px, baseline, sigma_px, generator)
    finite = torch.isfinite(out["depth"])
    err = (out["depth"] - zs)[finite]
    rmse = float(err.square().mean().sqrt()) if err.numel() else float("inf")
    predicted = float(sigma_px) * float(z.pow(4).mean().sqrt()) / (float(focal_px) * float(baseline))
    return {"rmse": rmse, "rmse_first_order": predicted, "ratio": rmse / predicted if predicted > 0 else float("nan"),
            "bias": float(err.mean()) if err.numel() else float("nan"), "lost": float(1 - finite.float().mean())}


def binned_rmse(depth: torch.Tensor, error: torch.Tensor, bins: int = 8) -> Dict[str, list]:
    """RMS of ``error`` (N,) in ``bins`` equal-width depth bins over the range of ``depth`` (N,):
    centres and RMS of the non-empty bins."""
    lo, hi = float(depth.min()), float(depth.max())
    edges = torch.linspace(lo, hi, int(bins) + 1, dtype=torch.float64)
    idx = torch.bucketize(depth.to(torch.float64), edges[1:-1])
    counts = torch.bincount(idx, minlength=int(bins)).double()
    sq = torch.zeros(int(bins), dtype=torch.float64).index_add_(0, idx, error.to(torch.float64).square())
    keep = counts > 0
    centres = 0.5 * (edges[1:] + edges[:-1])
    return {"depth": centres[keep].tolist(), "rmse": (sq[keep] / counts[keep]).sqrt().tolist()}
