"""A learnable SDF box rendered by the course's rule (the ``box`` task's model)."""

from __future__ import annotations

from typing import Dict, Optional

import torch

from l3d_app.geometry.sdf import box_sdf
from l3d_app.render.sdf.densities import laplace_cdf
from l3d_app.render.volume.estimators import StratifiedEstimator
from l3d_app.render.volume.rendering import points_of, render_rays


class SDFBox(torch.nn.Module):
    """Learnable box: ``center`` (3,) and ``size`` (3,) side lengths, world units.

    The course rendered its box images with 64 samples at ``t = linspace(0, 5, 64)`` along
    unit rays, each sample's OPACITY ``alpha * Psi_beta(-sdf)`` (VolSDF's Laplace CDF; alpha 1,
    beta 0.05) composited as ``T_i = prod_{j<i} (1 - a_j)`` on black, colour
    ``clamp(|p - centre|, 0.02, 0.98)``: :meth:`render_rays` does exactly that by default.
    """

    def __init__(self, center=(0.0, 0.0, 0.0), size=(1.5, 1.5, 1.5), alpha: float = 1.0, beta: float = 0.05):
        super().__init__()
        self.center = torch.nn.Parameter(torch.tensor(center, dtype=torch.float32))
        self.size = torch.nn.Parameter(torch.tensor(size, dtype=torch.float32))
        self.alpha, self.beta = float(alpha), float(beta)

    def field(self, points: torch.Tensor, dirs: torch.Tensor = None):
        """points (N, 3) -> (opacity (N,) in [0, 1], rgb (N, 3)) by the course's rule."""
        opacity = self.alpha * laplace_cdf(-box_sdf(points, self.center, self.size), self.beta)
        rgb = (points - self.center).abs().clamp(0.02, 0.98)
        return opacity, rgb

    def render_rays(self, origins: torch.Tensor, dirs: torch.Tensor, estimator: Optional[object] = None
                    ) -> Dict[str, torch.Tensor]:
        """origins, unit dirs (R, 3) -> {"color": (R, 3) on black, "depth": (R,) expected
        distance, "opacity": (R,)}; samples from ``estimator`` (default: the course's 64
        linspace samples on [0, 5])."""
        est = estimator if estimator is not None else StratifiedEstimator(64, near=0.0, far=5.0)

        def fn(t0, t1, rays):
            opacity, rgb = self.field(points_of(origins, dirs, t0, rays)[0])
            return {"rgb": rgb, "alpha": opacity}

        out = render_rays(*est.sampling(origins, dirs), origins.shape[0], fn)
        return {k: out[k] for k in ("color", "depth", "opacity")}
