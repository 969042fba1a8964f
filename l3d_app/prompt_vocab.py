"""The built-in prompt vocabulary: shape colours, shapes and backgrounds, and the grammar
that turns a prompt into (colour, shape, background) indices.

It sits at the bottom of the package (beside :mod:`l3d_app.errors`) because three layers
share it: the procedural images (:mod:`l3d_app.data.prompt_images`) draw it, the built-in
prior (:mod:`l3d_app.diffusion.builtin_prior`) embeds it, and the independent checker
(:mod:`l3d_app.metrics.prompt_match`) names what an image shows in it. Colours are RGB
in [0, 1]; :data:`ANY` (-1) marks a slot a prompt leaves unnamed.
"""

from __future__ import annotations

import re
from typing import List, Tuple

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
