"""A small conditional U-Net noise predictor eps(x_t, t, c) for tiny images or latents.

Two resolutions below the input (S -> S/2 -> S/4), residual blocks with GroupNorm + SiLU,
the timestep (sinusoidal features) and the prompt embedding added as a per-channel shift
in every block. Sizes: x (B, C, S, S) with S divisible by 4; t (B,) long; cond (B, D).
"""

from __future__ import annotations

import math

import torch
import torch.nn as nn
import torch.nn.functional as F


def timestep_features(t: torch.Tensor, dim: int, max_period: float = 10000.0) -> torch.Tensor:
    """Sinusoidal features (B, dim) of integer timesteps t (B,)."""
    half = dim // 2
    freqs = torch.exp(-math.log(max_period) * torch.arange(half, device=t.device, dtype=torch.float32) / half)
    angles = t.float().view(-1, 1) * freqs.view(1, -1)
    return torch.cat([angles.sin(), angles.cos()], dim=1)


class ResBlock(nn.Module):
    """GroupNorm-SiLU-conv twice, embedding added in between, 1x1 skip when channels change."""

    def __init__(self, c_in: int, c_out: int, emb_dim: int):
        super().__init__()
        self.norm1, self.conv1 = nn.GroupNorm(8, c_in), nn.Conv2d(c_in, c_out, 3, padding=1)
        self.emb = nn.Linear(emb_dim, c_out)
        self.norm2, self.conv2 = nn.GroupNorm(8, c_out), nn.Conv2d(c_out, c_out, 3, padding=1)
        self.skip = nn.Conv2d(c_in, c_out, 1) if c_in != c_out else nn.Identity()
        nn.init.zeros_(self.conv2.weight)
        nn.init.zeros_(self.conv2.bias)

    def forward(self, x: torch.Tensor, emb: torch.Tensor) -> torch.Tensor:
        h = self.conv1(F.silu(self.norm1(x)))
        h = h + self.emb(emb)[:, :, None, None]
        h = self.conv2(F.silu(self.norm2(h)))
        return self.skip(x) + h


class TinyUNet(nn.Module):
    """Noise predictor with channel widths (c, 2c, 2c) at S/p, S/2p, S/4p.

    ``patch`` p > 1 first folds p x p pixel blocks into channels (space-to-depth) and unfolds
    the output at the end: the cheap way to run at 32 x 32 on a CPU.
    """

    def __init__(self, in_channels: int = 3, channels: int = 32, cond_dim: int = 48, emb_dim: int = 128,
                 patch: int = 1):
        super().__init__()
        c1, c2 = channels, 2 * channels
        self.patch = int(patch)
        io_channels = in_channels * self.patch ** 2
        self.t_dim = emb_dim // 2
        self.emb = nn.Sequential(nn.Linear(self.t_dim + cond_dim, emb_dim), nn.SiLU(), nn.Linear(emb_dim, emb_dim))
        self.inp = nn.Conv2d(io_channels, c1, 3, padding=1)
        self.down1 = ResBlock(c1, c1, emb_dim)
        self.pool1 = nn.Conv2d(c1, c2, 3, stride=2, padding=1)
        self.down2 = ResBlock(c2, c2, emb_dim)
        self.pool2 = nn.Conv2d(c2, c2, 3, stride=2, padding=1)
        self.mid = ResBlock(c2, c2, emb_dim)
        self.up2 = ResBlock(2 * c2, c2, emb_dim)
        self.up1 = ResBlock(c2 + c1, c1, emb_dim)
        self.out = nn.Sequential(nn.GroupNorm(8, c1), nn.SiLU(), nn.Conv2d(c1, io_channels, 3, padding=1))

    def forward(self, x: torch.Tensor, t: torch.Tensor, cond: torch.Tensor) -> torch.Tensor:
        emb = self.emb(torch.cat([timestep_features(t, self.t_dim), cond.float()], dim=1))
        if self.patch > 1:
            x = F.pixel_unshuffle(x, self.patch)
        h1 = self.down1(self.inp(x), emb)                       # S
        h2 = self.down2(self.pool1(h1), emb)                    # S/2
        h = self.mid(self.pool2(h2), emb)                       # S/4
        h = F.interpolate(h, scale_factor=2.0, mode="nearest")
        h = self.up2(torch.cat([h, h2], dim=1), emb)            # S/2
        h = F.interpolate(h, scale_factor=2.0, mode="nearest")
        h = self.up1(torch.cat([h, h1], dim=1), emb)            # S
        h = self.out(h)
        return F.pixel_shuffle(h, self.patch) if self.patch > 1 else h
