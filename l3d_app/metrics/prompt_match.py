"""An independent checker: does an image show what its built-in-vocabulary prompt says?

No learned parts: exact colour and shape statistics of the image.

1. Background = per-channel median of the border pixels, named by the nearest background
   colour (must lie within ``colour_tol``).
2. Foreground = pixels farther than ``fg_threshold`` (RGB Euclidean) from that background;
   the shape is its largest 4-connected component, which must hold >= ``min_area`` of the
   image and >= ``min_purity`` of all foreground pixels (one shape, not speckle).
3. Colour = median RGB of the component, named by the nearest shape colour (within
   ``colour_tol``).
4. Shape from the component's fill ratio of its bounding box (square 1, circle pi/4,
   triangle 1/2): nearest of these, with the box's aspect ratio within ``max_aspect``.

A prompt slot that is not named (ANY) always matches.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Dict, Optional

import torch
import torch.nn.functional as F

from l3d_app.errors import UserError
from l3d_app.prompt_vocab import (ANY, BACKGROUND_NAMES, BACKGROUNDS, COLOUR_NAMES, COLOURS,
                                 SHAPES, parse_prompt)

FILL_RATIOS = torch.tensor([math.pi / 4, 1.0, 0.5])  # circle, square, triangle (SHAPES order)


@dataclass
class PromptVerdict:
    """What the checker saw and whether it matches the prompt (names are None if undecided)."""

    match: bool
    colour: Optional[str]
    shape: Optional[str]
    background: Optional[str]
    colour_ok: bool
    shape_ok: bool
    background_ok: bool
    fill_ratio: float
    area_fraction: float
    purity: float

    def as_dict(self) -> Dict:
        return asdict(self)


def largest_component(mask: torch.Tensor) -> torch.Tensor:
    """Boolean (H, W) mask of the largest 4-connected component of ``mask`` (H, W) bool.

    Vectorised label propagation: every foreground pixel starts with its own label and
    repeatedly takes the maximum over its 4-neighbourhood inside the mask.
    """
    H, W = mask.shape
    if not bool(mask.any()):
        return mask.clone()
    labels = torch.where(mask, torch.arange(1, H * W + 1, dtype=torch.float32, device=mask.device).view(H, W),
                         torch.zeros((), device=mask.device))
    for _ in range(H * W):
        p = F.pad(labels, (1, 1, 1, 1))
        nb = torch.stack([p[1:-1, 1:-1], p[:-2, 1:-1], p[2:, 1:-1], p[1:-1, :-2], p[1:-1, 2:]]).amax(0)
        new = torch.where(mask, nb, labels)
        if torch.equal(new, labels):
            break
        labels = new
    values, counts = torch.unique(labels[mask], return_counts=True)
    return labels == values[counts.argmax()]


def _nearest(colour: torch.Tensor, table: dict):
    palette = torch.tensor(list(table.values()), dtype=torch.float32, device=colour.device)
    d = (palette - colour).norm(dim=1)
    i = int(d.argmin())
    return i, float(d[i])


def check_image(image: torch.Tensor, prompt: str, fg_threshold: float = 0.3, colour_tol: float = 0.35,
                min_area: float = 0.03, min_purity: float = 0.8, max_aspect: float = 1.5) -> PromptVerdict:
    """Verdict for one RGB image, (H, W, 3) or (3, H, W), float in [0, 1]."""
    img = image.detach().float().cpu()
    if img.dim() == 3 and img.shape[0] == 3 and img.shape[-1] != 3:
        img = img.permute(1, 2, 0)
    img = img.clamp(0, 1)
    H, W, _ = img.shape
    want_c, want_s, want_b = parse_prompt(prompt)
    border = torch.cat([img[0], img[-1], img[:, 0], img[:, -1]])
    bg_rgb = border.median(dim=0).values
    b, bd = _nearest(bg_rgb, BACKGROUNDS)
    background = BACKGROUND_NAMES[b] if bd <= colour_tol else None
    fg = (img - bg_rgb).norm(dim=-1) > fg_threshold
    comp = largest_component(fg)
    n_fg, n_comp = int(fg.sum()), int(comp.sum())
    area = n_comp / (H * W)
    purity = n_comp / max(n_fg, 1)
    colour = shape = None
    fill = 0.0
    if area >= min_area and purity >= min_purity:
        c, cd = _nearest(img[comp].median(dim=0).values, COLOURS)
        colour = COLOUR_NAMES[c] if cd <= colour_tol else None
        ys, xs = torch.nonzero(comp, as_tuple=True)
        h, w = int(ys.max() - ys.min()) + 1, int(xs.max() - xs.min()) + 1
        fill = n_comp / (h * w)
        if max(h, w) / min(h, w) <= max_aspect:
            shape = SHAPES[int((FILL_RATIOS - fill).abs().argmin())]
    shape_ok = shape is not None and (want_s == ANY or shape == SHAPES[want_s])
    colour_ok = colour is not None and (want_c == ANY or colour == COLOUR_NAMES[want_c])
    background_ok = background is not None and (want_b == ANY or background == BACKGROUND_NAMES[want_b])
    return PromptVerdict(match=colour_ok and shape_ok and background_ok, colour=colour, shape=shape,
                         background=background, colour_ok=colour_ok, shape_ok=shape_ok,
                         background_ok=background_ok, fill_ratio=round(fill, 4),
                         area_fraction=round(area, 4), purity=round(purity, 4))


def match_rate(images: torch.Tensor, prompts) -> float:
    """Fraction of images (B, 3, H, W) or (B, H, W, 3) whose verdict matches their prompt."""
    hits = [check_image(img, p).match for img, p in zip(images, prompts)]
    return sum(hits) / max(len(hits), 1)


def check_prompt_for_checker(prompt: str):
    """The prompt's (colour, shape, background) slots, or None when the checker cannot read it."""
    try:
        return parse_prompt(prompt)
    except UserError:
        return None


def score_frames(frames: torch.Tensor, prompt: str) -> Dict[str, Optional[float]]:
    """Checker verdicts over frames (N, H, W, 3): match rate and per-slot rates (None if the
    prompt is outside the checker's vocabulary, e.g. a free-text Stable Diffusion prompt)."""
    keys = ("match", "colour_ok", "shape_ok", "background_ok")
    if check_prompt_for_checker(prompt) is None:
        return {k: None for k in keys}
    verdicts = [check_image(f, prompt) for f in frames]
    return {k: sum(bool(getattr(v, k)) for v in verdicts) / max(len(verdicts), 1) for k in keys}


def score_metrics(score: Dict[str, Optional[float]]) -> Dict[str, Optional[float]]:
    """:func:`score_frames` output as metrics.json keys."""
    return {"match_rate": score["match"], "colour_match_rate": score["colour_ok"],
            "shape_match_rate": score["shape_ok"], "background_match_rate": score["background_ok"]}
