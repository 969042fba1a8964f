"""A tiny convolutional autoencoder: RGB (B, 3, S, S) in [0, 1] <-> latents (B, C, S/4, S/4).

The latent space of the built-in *latent* prior (the role Stable Diffusion's VAE plays,
at toy size). Deterministic (no KL); a small latent-norm penalty during training keeps the
latents bounded and the prior rescales them to unit standard deviation.
"""

from __future__ import annotations

import torch
import torch.nn as nn


class TinyAutoencoder(nn.Module):
    """Two stride-2 convolutions down, two nearest-upsample convolutions up."""

    def __init__(self, latent_channels: int = 4, width: int = 32):
        super().__init__()
        w = width
        self.encoder = nn.Sequential(
            nn.Conv2d(3, w, 3, padding=1), nn.SiLU(),
            nn.Conv2d(w, w, 3, stride=2, padding=1), nn.SiLU(),
            nn.Conv2d(w, w, 3, stride=2, padding=1), nn.SiLU(),
            nn.Conv2d(w, latent_channels, 1))
        self.decoder = nn.Sequential(
            nn.Conv2d(latent_channels, w, 3, padding=1), nn.SiLU(),
            nn.Upsample(scale_factor=2.0, mode="nearest"), nn.Conv2d(w, w, 3, padding=1), nn.SiLU(),
            nn.Upsample(scale_factor=2.0, mode="nearest"), nn.Conv2d(w, w, 3, padding=1), nn.SiLU(),
            nn.Conv2d(w, 3, 3, padding=1))

    def encode(self, images: torch.Tensor) -> torch.Tensor:
        """(B, 3, S, S) in [0, 1] -> (B, C, S/4, S/4) (unscaled)."""
        return self.encoder(images * 2 - 1)

    def decode(self, z: torch.Tensor) -> torch.Tensor:
        """(B, C, S/4, S/4) -> (B, 3, S, S) in [0, 1] (sigmoid output)."""
        return torch.sigmoid(self.decoder(z))

    def loss(self, images: torch.Tensor, latent_weight: float = 1e-3) -> torch.Tensor:
        """Reconstruction MSE + ``latent_weight`` * mean squared latent."""
        z = self.encode(images)
        return ((self.decode(z) - images) ** 2).mean() + latent_weight * (z ** 2).mean()
