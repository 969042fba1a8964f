"""Noise schedules: betas -> alphas_cumprod (abar_t), the only thing SDS needs from them.

``abar_t = prod_{s<=t} (1 - beta_s)``, decreasing from ~1 (t = 0, almost clean) towards 0
(t = T - 1, almost pure noise). Computed in float64 (cumulative products of numbers near 1
lose digits in float32), returned as float32.
"""

from __future__ import annotations

import math

import torch

from l3d_app.errors import UserError

SCHEDULES = ("linear", "cosine")


def linear_betas(num_timesteps: int, beta_start: float = 1e-4, beta_end: float = 0.02) -> torch.Tensor:
    """DDPM's linear betas, rescaled so that T steps add the same total noise as 1000 steps."""
    scale = 1000.0 / num_timesteps
    return torch.linspace(beta_start * scale, beta_end * scale, num_timesteps, dtype=torch.float64)


def cosine_betas(num_timesteps: int, s: float = 0.008, max_beta: float = 0.999) -> torch.Tensor:
    """Improved-DDPM cosine schedule: abar(t) = cos^2((t/T + s)/(1 + s) pi/2), betas clipped."""
    steps = torch.arange(num_timesteps + 1, dtype=torch.float64) / num_timesteps
    f = torch.cos((steps + s) / (1 + s) * math.pi / 2) ** 2
    abar = f / f[0]
    return (1 - abar[1:] / abar[:-1]).clamp(max=max_beta)


def alphas_cumprod(num_timesteps: int = 1000, schedule: str = "cosine") -> torch.Tensor:
    """abar_t of shape (T,), float32, strictly decreasing in (0, 1)."""
    if int(num_timesteps) < 2:
        raise UserError(f"num_timesteps must be >= 2, got {num_timesteps}")
    if schedule == "linear":
        betas = linear_betas(int(num_timesteps))
    elif schedule == "cosine":
        betas = cosine_betas(int(num_timesteps))
    else:
        raise UserError(f"unknown noise schedule '{schedule}' (known: {', '.join(SCHEDULES)})")
    if not bool(((betas > 0) & (betas < 1)).all()):
        raise UserError(f"schedule '{schedule}' with T={num_timesteps} gives betas outside (0, 1)")
    return torch.cumprod(1 - betas, dim=0).float()
