"""Pieces shared by the prior tasks (train_prior, sds_image, sds_mesh, sds_nerf): the
configured prior, prompt lists, image grids."""

from __future__ import annotations

from typing import List

import torch

from l3d_app.diffusion.registry import PRIORS
from l3d_app.prompt_vocab import BACKGROUND_NAMES, COLOUR_NAMES, SHAPES


def full_prompts(n_per_shape: int = 0) -> List[str]:
    """Fully specified prompts: every (colour, shape, background) triple (54), or with
    ``n_per_shape`` > 0 a fixed, balanced subset cycling colours and backgrounds per shape."""
    triples = [(c, s, b) for s in SHAPES for c in COLOUR_NAMES for b in BACKGROUND_NAMES]
    if n_per_shape <= 0:
        return [f"a {c} {s} on {b}" for c, s, b in triples]
    out = []
    for s in SHAPES:
        for i in range(n_per_shape):
            c = COLOUR_NAMES[i % len(COLOUR_NAMES)]
            b = BACKGROUND_NAMES[(i + SHAPES.index(s)) % len(BACKGROUND_NAMES)]
            out.append(f"a {c} {s} on {b}")
    return out


def image_grid(images: torch.Tensor, cols: int, pad: int = 1, value: float = 1.0) -> torch.Tensor:
    """Tile (N, 3, H, W) images into one (rows*(H+pad)-pad, cols*(W+pad)-pad, 3) image."""
    N, C, H, W = images.shape
    rows = -(-N // cols)
    canvas = torch.full((rows * cols, C, H + pad, W + pad), value, dtype=images.dtype)
    canvas[:N, :, :H, :W] = images.detach().cpu()
    grid = canvas.view(rows, cols, C, H + pad, W + pad).permute(0, 3, 1, 4, 2)
    return grid.reshape(rows * (H + pad), cols * (W + pad), C)[:-pad or None, :-pad or None]


def load_prior(cfg, device):
    """The configured prior (``prior=builtin`` | ``prior=stable_diffusion prior.path=DIR``), frozen."""
    return PRIORS.build(cfg.prior, device=device)
