"""A set of 3D Gaussians as trainable tensors, and their initialisation.

:class:`GaussianModel` holds N splats: ``means`` (N, 3) world units, ``log_scales`` (N, 3)
log standard deviations (or (N, 1) for an isotropic model: one scale per splat),
``quats`` (N, 4) ``(w, x, y, z)``, ``opacity_logits`` (N,), ``sh_dc`` (N, 1, 3) and
``sh_rest`` (N, 15, 3) spherical-harmonic colour (degree 3 storage).

How the set grows, shrinks or moves during training (densification) is a strategy's job:
:mod:`l3d_app.strategies`. Reading and writing the 3DGS PLY layout is
:mod:`l3d_app.geometry.gaussian_ply` (plain tensors: ``GaussianModel(**load_gaussian_ply(f))``,
``save_gaussian_ply(f, **model.tensors())``).
"""

from __future__ import annotations

import math
from typing import Dict, Optional

import torch

from l3d_app.geometry.normals import knn
from l3d_app.render.gaussians.sh import rgb_to_sh

PARAM_NAMES = ("means", "log_scales", "quats", "opacity_logits", "sh_dc", "sh_rest")


class GaussianModel(torch.nn.Module):
    """N Gaussians (see the module docstring); ``sh`` is (N, 16, 3) = [sh_dc | sh_rest]."""

    def __init__(self, means, log_scales, quats, opacity_logits, sh_dc, sh_rest):
        super().__init__()
        for name, v in zip(PARAM_NAMES, (means, log_scales, quats, opacity_logits, sh_dc, sh_rest)):
            setattr(self, name, torch.nn.Parameter(v.detach().clone().float()))

    @property
    def sh(self) -> torch.Tensor:
        return torch.cat([self.sh_dc, self.sh_rest], 1)

    @property
    def num(self) -> int:
        return self.means.shape[0]

    @property
    def isotropic(self) -> bool:
        """True when every splat has one scale (``log_scales`` is (N, 1))."""
        return self.log_scales.shape[-1] == 1

    @property
    def log_scales3(self) -> torch.Tensor:
        """(N, 3) per-axis log scales (an isotropic model's one scale repeated; differentiable)."""
        return self.log_scales.expand(-1, 3)

    def tensors(self) -> Dict[str, torch.Tensor]:
        """The parameters as plain detached tensors by name (scales always (N, 3))."""
        out = {name: getattr(self, name).detach() for name in PARAM_NAMES}
        out["log_scales"] = self.log_scales3.detach()
        return out

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):
        # checkpoints may hold a different number of splats: resize before loading
        for name in PARAM_NAMES:
            key = prefix + name
            if key in state_dict and state_dict[key].shape != getattr(self, name).shape:
                getattr(self, name).data = torch.empty_like(state_dict[key])
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)


def knn_mean_distance(points: torch.Tensor, k: int = 3) -> torch.Tensor:
    """(N,) mean distance of each point to its k nearest other points (shared exact kNN)."""
    n = points.shape[0]
    if n < 2:
        return torch.zeros(n, dtype=points.dtype, device=points.device)
    _, sq = knn(points, min(k, n - 1) + 1)  # the first neighbour is the point itself
    return sq[:, 1:].clamp_min(0).sqrt().mean(-1)


def init_from_points(points: torch.Tensor, colors: Optional[torch.Tensor] = None, sh_degree: int = 3,
                     opacity: float = 0.1, isotropic: bool = False, scale_factor: float = 1.0) -> GaussianModel:
    """Round Gaussians at ``points`` (N, 3): scale = ``scale_factor`` x the mean distance to
    the 3 nearest neighbours, identity rotation, ``opacity``, DC colour ``colors`` (N, 3) or
    grey. ``isotropic``: one scale per splat (``log_scales`` (N, 1)) that stays round in
    training; otherwise three equal scales that training may pull apart."""
    pts = points.float()
    n = pts.shape[0]
    dist = knn_mean_distance(pts).clamp_min(1e-7) * float(scale_factor)
    rgb = colors.float().cpu() if colors is not None else torch.full((n, 3), 0.5)
    quats = torch.zeros(n, 4)
    quats[:, 0] = 1.0
    return GaussianModel(pts.cpu(), torch.log(dist.cpu())[:, None].expand(n, 1 if isotropic else 3), quats,
                         torch.full((n,), math.log(opacity / (1 - opacity))),
                         rgb_to_sh(rgb)[:, None, :], torch.zeros(n, 15, 3))


@torch.no_grad()
def colors_from_views(points: torch.Tensor, images: torch.Tensor, cams) -> torch.Tensor:
    """(N, 3) initial colour of each point: the median, over the views that see it in
    frame (in front of the camera), of the pixel it projects to. Occlusion is ignored; the
    median keeps the colour of the surface seen by most views. Points seen by no view: 0.5.

    points (N, 3) world; images (V, H, W, 3) in [0, 1]; cams: V cameras of that size.
    """
    V, H, W = images.shape[:3]
    out = torch.full((points.shape[0], 3), float("nan"), dtype=images.dtype, device=images.device)
    pix, z = cams.project(points.to(cams.R.dtype))                               # (V, N, 2), (V, N)
    col, row = pix[..., 0].floor().long(), pix[..., 1].floor().long()
    ok = (z > 0) & (col >= 0) & (col < W) & (row >= 0) & (row < H)
    flat = images.reshape(V, H * W, 3)
    idx = (row.clamp(0, H - 1) * W + col.clamp(0, W - 1))                        # (V, N)
    rgb = torch.gather(flat, 1, idx[..., None].expand(-1, -1, 3))                 # (V, N, 3)
    rgb = torch.where(ok[..., None], rgb, out[None])
    out = torch.nanmedian(rgb, dim=0).values
    return torch.nan_to_num(out, nan=0.5)
