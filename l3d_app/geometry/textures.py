"""UV texture sampling: bilinear, ``u`` right and ``v`` UP (OBJ), textures top row first.

Texel (row r, col c) has its centre at ``((c + .5) / Wt, 1 - (r + .5) / Ht)`` (as
``grid_sample(align_corners=False)``); look-ups outside the outer texel centres repeat the
border. Two implementations of that one rule: :func:`sample_texture` / ``_t`` through
``grid_sample`` (fast, one texture), and :func:`sample_texture_indexed`, an explicit gather
that picks a texture of a batch per point. ``tests/test_textures.py`` checks they agree.
"""

from __future__ import annotations

from typing import Optional

import torch
import torch.nn.functional as F


def sample_texture_t(texture: torch.Tensor, uv_t: torch.Tensor) -> torch.Tensor:
    """Bilinear look-up, channel-first: ``uv_t`` (2, P) -> (C, P). See :func:`sample_texture`."""
    grid = torch.stack([uv_t[0] * 2 - 1, 1 - uv_t[1] * 2], dim=-1)[None, None]  # (1, 1, P, 2)
    img = texture.permute(2, 0, 1)[None].to(grid.dtype)  # (1, C, Ht, Wt) view, no copy
    out = F.grid_sample(img, grid, mode="bilinear", padding_mode="border", align_corners=False)
    return out[0, :, 0]


def sample_texture(texture: torch.Tensor, uv: torch.Tensor) -> torch.Tensor:
    """Bilinear texture look-up.

    Args:
        texture: (Ht, Wt, C) image, top row first.
        uv: (..., 2) texture coordinates, u right in [0, 1], v UP in [0, 1] (OBJ
            convention: v = 1 is the top row). Texel centres sit at ((j + .5) / Wt,
            1 - (i + .5) / Ht); outside [0, 1] the border texels are repeated.
    Returns:
        (..., C) colours.
    """
    flat = uv.reshape(-1, 2)
    out = sample_texture_t(texture, flat.t())
    return out.t().reshape(*uv.shape[:-1], texture.shape[-1])


def sample_texture_indexed(texture: torch.Tensor, uv: torch.Tensor,
                   batch_index: Optional[torch.Tensor] = None) -> torch.Tensor:
    """Bilinear look-up with a per-point choice among a batch of textures (explicit gather).

    Same sampling rule as :func:`sample_texture`; differentiable w.r.t. ``texture`` and ``uv``.

    Args:
        texture: (Ht, Wt, C) or (Bt, Ht, Wt, C), stored top row first.
        uv: (P, 2) texture coordinates, ``u`` right and ``v`` UP, [0, 1] spanning the
            texture's outer edges; texel (row r, col c) has its centre at
            ``((c + .5) / Wt, 1 - (r + .5) / Ht)`` (``grid_sample(align_corners=False)``),
            and lookups beyond the outer texel centres clamp to the border.
        batch_index: (P,) long, which texture of the batch each lookup reads (default 0).

    Returns:
        (P, C) sampled values.
    """
    if texture.dim() == 3:
        texture = texture[None]
    bt, ht, wt, c = texture.shape
    x = (uv[:, 0] * wt - 0.5).clamp(0, wt - 1)
    y = ((1.0 - uv[:, 1]) * ht - 0.5).clamp(0, ht - 1)
    x0 = x.detach().floor().long().clamp(0, wt - 1)
    y0 = y.detach().floor().long().clamp(0, ht - 1)
    x1, y1 = (x0 + 1).clamp(max=wt - 1), (y0 + 1).clamp(max=ht - 1)
    fx, fy = (x - x0.to(x.dtype))[:, None], (y - y0.to(y.dtype))[:, None]
    base = 0 if batch_index is None else batch_index * (ht * wt)
    flat = texture.reshape(-1, c)

    def texel(yy, xx):
        return flat[base + yy * wt + xx]

    return ((1 - fy) * ((1 - fx) * texel(y0, x0) + fx * texel(y0, x1))
            + fy * ((1 - fx) * texel(y1, x0) + fx * texel(y1, x1)))
