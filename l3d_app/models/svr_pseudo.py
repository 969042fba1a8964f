"""2D-supervised dense point generator (Lin, Kong & Lucey, AAAI 2018), decoder ``svr_pseudo``.

The decoder predicts, for K FIXED viewpoints (the 8 corners of a cube around the object,
looking at its centre, at the data's camera distance and field of view), a depth map and a
mask logit map of ``depth_size`` x ``depth_size`` pixels. Every pixel becomes a point on its
camera ray at the predicted depth (:func:`l3d_app.geometry.rays.camera_rays`), so the K maps
fuse into one dense cloud of ``K * depth_size^2`` points in the object frame; depth is
``distance + depth_range * tanh(raw)`` (the object lies within the unit sphere).

Training uses NO 3D supervision: each step renders the fused cloud into ``views_per_step``
of the data's supervision cameras (random per object) with the pseudo-renderer
(:func:`l3d_app.render.pseudo_render.pseudo_render`, upsampling ``upsample``) and compares
with the depth and silhouette of the true mesh rendered from those cameras:

* as in the paper's implementation, only points whose mask logit is > 0 (foreground) are
  z-buffered; the rendered mask logit of a pixel is that of its nearest foreground point,
  else of its nearest background point (so wrongly dropped points can come back), else a
  constant -1 (no point: no gradient);
* ``loss = w_mask * BCE(mask logits, true silhouette) + w_depth * L1(depth, true depth)``,
  the L1 over pixels both the truth and the foreground render cover.

At evaluation the cloud is the foreground points (mask logit > 0).
"""

from __future__ import annotations

import math
from typing import Dict, List

import torch
from torch import nn

from l3d_app.errors import UserError
from l3d_app.geometry.cameras import Cameras, look_at_cameras
from l3d_app.geometry.pointcloud import PointCloud
from l3d_app.geometry.rays import camera_rays
from l3d_app.losses.occupancy import bce_with_logits
from l3d_app.registry import MODELS
from l3d_app.render.pseudo_render import pseudo_render

CUBE_ELEVATION = math.degrees(math.atan(1 / math.sqrt(2)))  # 35.26: a cube corner's elevation


def fixed_cameras(distance: float, fov: float, size: int) -> Cameras:
    """The 8 cube-corner cameras (azimuths 45 + 90 k, elevations +-35.26 degrees)."""
    azim = torch.tensor([45.0, 135.0, 225.0, 315.0] * 2)
    elev = torch.tensor([CUBE_ELEVATION] * 4 + [-CUBE_ELEVATION] * 4)
    return look_at_cameras(distance, elev, azim, fov, size)


def _up(cin: int, cout: int) -> nn.Sequential:
    return nn.Sequential(nn.ConvTranspose2d(cin, cout, 4, 2, 1), nn.ReLU(inplace=True))


class PseudoRenderDecoder(nn.Module):
    """Feature -> K depth maps + mask logits -> fused cloud; trained through pseudo-rendering.

    Args:
        latent_dim: feature size.
        distance, fov: fixed-camera distance (world units) and field of view (degrees).
        depth_size: side of the predicted maps (4 * 2^k pixels).
        width: channels of the first transposed-convolution stage.
        depth_range: depth = distance + depth_range * tanh(raw) (world units).
        upsample: pseudo-renderer sub-pixel factor U.
        views_per_step: supervision views rendered per object per step.
        w_mask, w_depth: loss weights.
    """

    def __init__(self, latent_dim: int, distance: float, fov: float, depth_size: int = 32, width: int = 64,
                 depth_range: float = 1.0, upsample: int = 4, views_per_step: int = 4,
                 w_mask: float = 1.0, w_depth: float = 1.0):
        super().__init__()
        size = int(depth_size)
        ups = int(round(math.log2(size / 4))) if size >= 4 else -1
        if ups < 1 or 4 * 2 ** ups != size:
            raise UserError(f"svr_pseudo needs depth_size = 4 * 2^k (8, 16, 32, 64), got {depth_size}")
        cams = fixed_cameras(float(distance), float(fov), size)
        origins, dirs = camera_rays(cams, normalize=False)            # (K, h, w, 3), camera Z = 1
        self.register_buffer("origins", origins.float())
        self.register_buffer("dirs", dirs.float())
        self.K, self.size, self.width = cams.batch_size, size, int(width)
        self.distance, self.depth_range = float(distance), float(depth_range)
        self.upsample, self.views_per_step = int(upsample), int(views_per_step)
        self.w_mask, self.w_depth = float(w_mask), float(w_depth)
        self.seed = nn.Sequential(nn.Linear(int(latent_dim), self.width * 16), nn.ReLU(inplace=True))
        layers: List[nn.Module] = []
        c = self.width
        for _ in range(ups):
            layers.append(_up(c, max(c // 2, 16)))
            c = max(c // 2, 16)
        self.up = nn.Sequential(*layers)
        self.out = nn.Conv2d(c, 2 * self.K, 3, 1, 1)
        with torch.no_grad():  # start with every point in the foreground, at the centre depth
            self.out.bias[self.K:].fill_(1.0)

    def forward(self, feature: torch.Tensor) -> Dict[str, torch.Tensor]:
        """(B, latent) -> depth (B, K, h, w), mask_logits (B, K, h, w), points (B, K h w, 3)."""
        x = self.up(self.seed(feature).view(-1, self.width, 4, 4))
        raw = self.out(x)
        depth = self.distance + self.depth_range * torch.tanh(raw[:, :self.K])
        logits = raw[:, self.K:]
        points = self.origins + depth[..., None] * self.dirs             # (B, K, h, w, 3)
        return {"depth": depth, "mask_logits": logits, "points": points.reshape(feature.shape[0], -1, 3)}

    def render(self, points: torch.Tensor, logits: torch.Tensor, cams: Cameras) -> Dict[str, torch.Tensor]:
        """Pseudo-render clouds (B, N, 3) with mask logits (B, N) into B cameras: depth,
        covered (foreground z-buffer) and mask_logits (B, H, W) (see the module docstring)."""
        fg = logits.detach() > 0
        lg = logits[..., None]
        front = pseudo_render(points, cams, self.upsample, values=lg, active=fg)
        back = pseudo_render(points, cams, self.upsample, values=lg, active=~fg)
        mask = torch.where(front["covered"], front["values"][..., 0],
                           torch.where(back["covered"], back["values"][..., 0], torch.full_like(front["depth"], -1.0)))
        return {"depth": front["depth"], "covered": front["covered"], "mask_logits": mask}

    def loss(self, feature, batch, generator=None) -> Dict[str, torch.Tensor]:
        out = self(feature)
        B, S = batch["depth"].shape[:2]
        s = min(self.views_per_step, S)
        views = torch.rand(B, S, generator=generator, device=feature.device).argsort(dim=1)[:, :s]  # (B, s)
        cams: Cameras = batch["depth_cameras"][views.reshape(-1)]
        gt = torch.gather(batch["depth"], 1, views[..., None, None].expand(-1, -1, *batch["depth"].shape[2:]))
        gt = gt.reshape(B * s, *gt.shape[2:])
        gt_mask = gt > 0
        pts = out["points"].repeat_interleave(s, dim=0)
        lg = out["mask_logits"].reshape(B, -1).repeat_interleave(s, dim=0)
        r = self.render(pts, lg, cams)
        mask_loss = bce_with_logits(r["mask_logits"], gt_mask.float())
        both = gt_mask & r["covered"]
        depth_loss = ((r["depth"] - gt).abs() * both).sum() / both.sum().clamp_min(1)
        return {"loss": self.w_mask * mask_loss + self.w_depth * depth_loss, "mask_bce": mask_loss,
                "depth_l1": depth_loss, "foreground": (lg > 0).float().mean()}

    def clouds(self, feature) -> List[torch.Tensor]:
        """The foreground points of each object, (P_i, 3)."""
        out = self(feature)
        fg = out["mask_logits"].reshape(feature.shape[0], -1) > 0
        return [p[m].detach() for p, m in zip(out["points"], fg)]

    def shapes(self, feature) -> List[PointCloud]:
        return [PointCloud(p) for p in self.clouds(feature)]

    def points(self, feature, num_points: int = 0, generator=None) -> List[torch.Tensor]:
        return self.clouds(feature)


@MODELS.register("svr_pseudo")
def svr_pseudo(latent_dim: int, geometry: Dict, depth_size: int = 32, width: int = 64, depth_range: float = 1.0,
               upsample: int = 4, views_per_step: int = 4, w_mask: float = 1.0,
               w_depth: float = 1.0) -> PseudoRenderDecoder:
    """Lin et al. generator at the data's camera ``distance`` and ``fov``."""
    return PseudoRenderDecoder(latent_dim, float(geometry["distance"]), float(geometry["fov"]), depth_size, width,
                               depth_range, upsample, views_per_step, w_mask, w_depth)
