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
import re
from typing import Optional, Tuple

import torch

from l3d_app.errors import UserError

COLOURS = {"red": (0.9, 0.1, 0.1), "green": (0.1, 0.75, 0.1), "blue": (0.1, 0.2, 0.9),
           "yellow": (0.95, 0.85, 0.1), "cyan": (0.1, 0.8, 0.85), "magenta": (0.85, 0.1, 0.8)}
SHAPES = ("circle", "square", "triangle")
BACKGROUNDS = {"white": (0.95, 0.95, 0.95), "black": (0.05, 0.05, 0.05), "gray": (0.5, 0.5, 0.5)}
COLOUR_NAMES = tuple(COLOURS)
BACKGROUND_NAMES = tuple(BACKGROUNDS)
ANY = -1
_FILLER = {"a", "an", "the", "on", "one", "single", "background", "with", "in", "of", "and"}
_ALIASES = {"grey": "gray", "purple": "magenta", "box": "square", "disc": "circle", "disk": "circle"}


def parse_prompt(prompt: str) -> Tuple[int, int, int]:
    """(colour, shape, background) indices of ``prompt`` (ANY where not named).

    The background is the colour word after "on" (or a background word next to
    "background"); colour words otherwise name the shape. Unknown words raise UserError.
    """
    words = [_ALIASES.get(w, w) for w in re.findall(r"[a-z]+", str(prompt).lower())]
    colour = shape = background = ANY
    after_on = False
    for i, w in enumerate(words):
        nxt = words[i + 1] if i + 1 < len(words) else ""
        if w == "on":
            after_on = True
        elif w in SHAPES:
            if shape != ANY:
                raise UserError(f"prompt '{prompt}' names two shapes")
            shape = SHAPES.index(w)
        elif (after_on or nxt == "background") and w in BACKGROUNDS:
            background = BACKGROUND_NAMES.index(w)
        elif w in COLOURS and not after_on:
            if colour != ANY:
                raise UserError(f"prompt '{prompt}' names two shape colours")
            colour = COLOUR_NAMES.index(w)
        elif w not in _FILLER:
            raise UserError(
                f"prompt word '{w}' is not in the built-in prior's vocabulary: colours "
                f"{', '.join(COLOUR_NAMES)}; shapes {', '.join(SHAPES)}; backgrounds (after 'on') "
                f"{', '.join(BACKGROUND_NAMES)}; e.g. 'a red circle on white'")
    return colour, shape, background


def prompt_text(colour: int, shape: int, background: int) -> str:
    """The canonical prompt of a label triple (ANY slots left out)."""
    words = ["a"]
    if colour != ANY:
        words.append(COLOUR_NAMES[colour])
    words.append(SHAPES[shape] if shape != ANY else "shape")
    if background != ANY:
        words += ["on", BACKGROUND_NAMES[background]]
    return " ".join(words)


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
    kw = dict(generator=generator, device=device)
    return torch.stack([torch.randint(len(COLOURS), (n,), **kw), torch.randint(len(SHAPES), (n,), **kw),
                        torch.randint(len(BACKGROUNDS), (n,), **kw)], dim=1)


def render_prompt_images(labels: torch.Tensor, size: int = 32, generator: Optional[torch.Generator] = None,
                         jitter: float = 0.08, min_radius: float = 0.22, max_radius: float = 0.30,
                         max_offset: float = 0.05) -> torch.Tensor:
    """Images (B, 3, S, S) in [0, 1] for labels (B, 3) (ANY slots drawn at random).

    Radius is a fraction of the side S in [min_radius, max_radius]; the centre is offset from
    the image centre by up to ``max_offset`` * S per axis (uniform).
    """
    device = labels.device
    B = labels.shape[0]
    kw = dict(generator=generator, device=device)
    rand = sample_labels(B, generator, device)
    labels = torch.where(labels == ANY, rand, labels)
    u = torch.rand(B, 9, **kw)
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
