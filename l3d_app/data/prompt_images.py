"""Procedural prompt/image pairs for the built-in diffusion prior.

A prompt names up to three *slots* from a fixed vocabulary: a shape colour, a shape and a
background, e.g. ``"a red circle on white"``, ``"a blue square"``, ``"a triangle on black"``.
An unnamed slot means "any" (the prior learns it from slot dropout). Images are RGB in
[0, 1], (B, 3, S, S): one flat shape with soft (1-pixel) edges, random centre and size,
on a flat background; every colour is jittered by up to ``jitter`` per channel.

The default position/size jitter is deliberately small (radius 22-30% of the side, centre
within 5% of the side of the image centre): a design choice for the built-in prior, whose
tiny U-Net trained for minutes on one CPU core learns crisp shapes of this narrow
distribution (and SDS, which seeks its mode, then draws a shape rather than the blurred
average of many placements). The checker does not depend on it.

Labels are index tensors (B, 3) = (colour, shape, background); :data:`ANY` (-1) marks an
unnamed slot in a parsed prompt.
"""

from __future__ import annotations

import math
from typing import Optional, Tuple

import torch


# The vocabulary lives below every layer (data renders it, the prior embeds it, the metric
# checks it); re-exported here, where it has always been imported from.
from l3d_app.prompt_vocab import (ANY, BACKGROUND_NAMES, BACKGROUNDS, COLOUR_NAMES,  # noqa: E402,F401
                                  COLOURS, SHAPES, parse_prompt, prompt_text)
from l3d_app.runtime.random import rand, randint  # noqa: E402


def _palette(table: dict) -> torch.Tensor:
    return torch.tensor(list(table.values()), dtype=torch.float32)


def shape_masks(shape: torch.Tensor, centre: torch.Tensor, radius: torch.Tensor, size: int) -> torch.Tensor:
    """Soft coverage (B, S, S) in [0, 1] of each sample's shape, 1-pixel sigmoid edges.

    shape: (B,) indices into SHAPES; centre: (B, 2) (x, y) in pixels; radius: (B,) half-size
    in pixels (circle radius, square half-side, triangle half-base = half-height).
    """
    device = centre.device
    c = torch.arange(size, device=device, dtype=torch.float32) + 0.5  # pixel centres
    x = (c.view(1, 1, -1) - centre[:, 0].view(-1, 1, 1))
    y = (c.view(1, -1, 1) - centre[:, 1].view(-1, 1, 1))
    r = radius.view(-1, 1, 1)
    circle = torch.sqrt(x * x + y * y) - r
    square = torch.maximum(x.abs(), y.abs()) - r
    # upward isosceles triangle: apex (0, -r), base y = +r from x = -r to +r
    side = (2 * x.abs() - (y + r)) / math.sqrt(5.0)  # the two slanted edges
    triangle = torch.maximum(side, y - r)
    sdf = torch.where(shape.view(-1, 1, 1) == 0, circle, torch.where(shape.view(-1, 1, 1) == 1, square, triangle))
    return torch.sigmoid(-sdf * 4.0)


def sample_labels(n: int, generator: Optional[torch.Generator] = None, device="cpu") -> torch.Tensor:
    """(n, 3) random (colour, shape, background) indices, uniform over the vocabulary."""
    return torch.stack([randint(0, len(COLOURS), (n,), generator, device), randint(0, len(SHAPES), (n,), generator, device),
                        randint(0, len(BACKGROUNDS), (n,), generator, device)], dim=1)


def render_prompt_images(labels: torch.Tensor, size: int = 32, generator: Optional[torch.Generator] = None,
                         jitter: float = 0.08, min_radius: float = 0.22, max_radius: float = 0.30,
                         max_offset: float = 0.05) -> torch.Tensor:
    """Images (B, 3, S, S) in [0, 1] for labels (B, 3) (ANY slots drawn at random).

    Radius is a fraction of the side S in [min_radius, max_radius]; the centre is offset from
    the image centre by up to ``max_offset`` * S per axis (uniform).
    """
    device = labels.device
    B = labels.shape[0]
    drawn = sample_labels(B, generator, device)
    labels = torch.where(labels == ANY, drawn, labels)
    u = rand((B, 9), generator, device)
    radius = (min_radius + (max_radius - min_radius) * u[:, 0]) * size
    centre = size / 2 + (2 * u[:, 1:3] - 1) * max_offset * size
    fg = _palette(COLOURS).to(device)[labels[:, 0]] + jitter * (2 * u[:, 3:6] - 1)
    bg = _palette(BACKGROUNDS).to(device)[labels[:, 2]] + jitter * (2 * u[:, 6:9] - 1)
    m = shape_masks(labels[:, 1], centre, radius, size).unsqueeze(1)
    img = m * fg.clamp(0, 1).view(B, 3, 1, 1) + (1 - m) * bg.clamp(0, 1).view(B, 3, 1, 1)
    return img.clamp(0, 1)


def prompt_batch(n: int, size: int = 32, generator: Optional[torch.Generator] = None,
                 device="cpu") -> Tuple[torch.Tensor, torch.Tensor]:
    """A random training batch: images (n, 3, S, S) in [0, 1] and labels (n, 3)."""
    labels = sample_labels(n, generator, device)
    return render_prompt_images(labels, size, generator), labels
