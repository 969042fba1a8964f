"""Image encoders of single-view reconstruction by name: ``cnn`` (the small CNN) and ``resnet18`` (the course's)."""

from __future__ import annotations

from torch import nn

from l3d_app.errors import UserError
from l3d_app.models.resnet_encoder import ResNet18Encoder
from l3d_app.models.svr_encoder import ImageEncoder

IMAGE_ENCODERS = {"cnn": ImageEncoder, "resnet18": ResNet18Encoder}


def build_image_encoder(image_size: int, name: str = "cnn", **kwargs) -> nn.Module:
    """The encoder ``name`` for square images of ``image_size`` px, with its keyword arguments; each has
    ``latent_dim`` (its output size)."""
    if name not in IMAGE_ENCODERS:
        raise UserError(f"unknown image encoder '{name}'. Known: {', '.join(sorted(IMAGE_ENCODERS))}")
    return IMAGE_ENCODERS[name](image_size=int(image_size), **kwargs)
