"""Every pixel of a set of training views as one ray, flattened view-major."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import torch

from l3d_app.geometry.cameras import Cameras
from l3d_app.geometry.rays import camera_rays


@dataclass
class TrainingRays:
    """The rays through the pixel centres of V training views of H x W pixels; ray ``v*H*W + y*W + x`` is
    pixel (x, y) of view v.

    Attributes:
        origins: (N, 3) world units. dirs: (N, 3) camera-frame Z = 1 (a point at distance ``s`` along
            the ray has depth ``s``); ``unit_dirs()`` normalises them.
        rgb: (N, 3) the pixels' colours in [0, 1].
        mask: (N,) the pixels' coverage (alpha) in [0, 1], or None when the data has none.
        cameras: the V views; images: (V, H, W, 3) their images.
    """

    origins: torch.Tensor
    dirs: torch.Tensor
    rgb: torch.Tensor
    mask: Optional[torch.Tensor]
    cameras: Cameras
    images: torch.Tensor

    @classmethod
    def of_views(cls, cameras: Cameras, images: torch.Tensor, masks: Optional[torch.Tensor],
                 views: torch.Tensor) -> "TrainingRays":
        """The rays of ``views`` (long indices) among all ``cameras`` (with their ``images`` (V, H, W, 3) and
        ``masks`` (V, H, W) or None)."""
        origins, dirs = camera_rays(cameras, normalize=False)          # (V, H, W, 3), camera Z = 1
        return cls(origins[views].reshape(-1, 3), dirs[views].reshape(-1, 3), images[views].reshape(-1, 3),
                   None if masks is None else masks[views].reshape(-1), cameras[views], images[views])

    @property
    def n(self) -> int:
        return int(self.origins.shape[0])

    @property
    def height(self) -> int:
        return int(self.cameras.height)

    @property
    def width(self) -> int:
        return int(self.cameras.width)

    @property
    def covered(self) -> Optional[torch.Tensor]:
        """(N,) bool: the pixel's alpha is at least 0.5 (None without masks)."""
        return None if self.mask is None else self.mask >= 0.5

    def unit_dirs(self) -> torch.Tensor:
        """(N, 3) the directions normalised."""
        return torch.nn.functional.normalize(self.dirs, dim=-1)
