"""2D-supervised dense point generator (Lin, Kong & Lucey, AAAI 2018), decoder ``svr_pseudo``.

The decoder predicts, for K FIXED viewpoints (the 8 corners of a cube around the object,
looking at its centre, at the data's camera distance and field of view), a depth map and a
mask logit map of ``depth_size`` x ``depth_size`` pixels. Every pixel becomes a point on its
camera ray at the predicted depth (:func:`l3d_app.geometry.rays.camera_rays`), so the K maps
fuse into one dense cloud of ``K * depth_size^2`` points in the object frame; depth is
``distance + depth_range * tanh(raw)`` (the object lies within the unit sphere).

Training uses NO 3D supervision: each step renders the fused cloud into ``views_per_step``
of the data's supervision cameras (random per object) with the pseudo-renderer (upsampling
``upsample``) and compares with the depth and silhouette of the true mesh rendered from
those cameras (``loss = w_mask * BCE(mask) + w_depth * L1(depth)``; the loss and the
rendering wiring are :func:`l3d_app.losses.svr.pseudo_loss`).

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
from l3d_app.registry import MODELS

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

    ``kind`` "pseudo": its loss is :func:`l3d_app.losses.svr.pseudo_loss`.

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

    kind = "pseudo"

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
