"""Image encoder for single-view reconstruction: a small CNN (no torchvision).

``(B, H, W, 3)`` images in [0, 1] (the library's image layout) -> ``(B, latent_dim)``
features. Stages of two 3x3 convolutions (GroupNorm, ReLU), each but the first halving
the resolution, until the map is at most 4x4; then an adaptive average pool to 4x4
(so any square size >= 8 works: 32, 64, 128, ...), a flatten (which keeps WHERE things
are in the image, unlike a global pool) and a linear layer with ReLU.
"""

from __future__ import annotations

import torch
from torch import nn

from l3d_app.errors import UserError


def _stage(cin: int, cout: int, stride: int) -> nn.Sequential:
    groups = 8 if cout % 8 == 0 else 1
    return nn.Sequential(
        nn.Conv2d(cin, cout, 3, stride, 1), nn.GroupNorm(groups, cout), nn.ReLU(inplace=True),
        nn.Conv2d(cout, cout, 3, 1, 1), nn.GroupNorm(groups, cout), nn.ReLU(inplace=True))


class ImageEncoder(nn.Module):
    """Small CNN image encoder.

    Args:
        image_size: input side in pixels (square, >= 8).
        width: channels of the first stage; doubled per stage up to ``max_width``.
        max_width: channel cap.
        latent_dim: output feature size.
    """

    def __init__(self, image_size: int = 32, width: int = 16, max_width: int = 128, latent_dim: int = 256):
        super().__init__()
        if int(image_size) < 8 or min(int(width), int(max_width), int(latent_dim)) < 1:
            raise UserError(f"image encoder needs image_size >= 8 and positive widths, got "
                            f"{image_size}, {width}, {max_width}, {latent_dim}")
        stages, size, cin, cout = [], int(image_size), 3, int(width)
        stages.append(_stage(cin, cout, 1))
        while size > 4:
            cin, cout, size = cout, min(cout * 2, int(max_width)), (size + 1) // 2
            stages.append(_stage(cin, cout, 2))
        self.features = nn.Sequential(*stages, nn.AdaptiveAvgPool2d(4))
        self.head = nn.Sequential(nn.Flatten(), nn.Linear(cout * 16, int(latent_dim)), nn.ReLU(inplace=True))
        self.latent_dim = int(latent_dim)

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        """images (B, H, W, 3) in [0, 1] -> (B, latent_dim)."""
        if images.dim() != 4 or images.shape[-1] != 3:
            raise UserError(f"image encoder expects (B, H, W, 3) images, got {tuple(images.shape)}")
        x = images.permute(0, 3, 1, 2) * 2.0 - 1.0
        return self.head(self.features(x))
