"""Text on images (frame labels such as the field of view of a dolly-zoom frame)."""

from __future__ import annotations

from typing import Sequence

import numpy as np
import torch
from PIL import Image, ImageDraw, ImageFont

from l3d_app.runtime.media import to_uint8


def label_frames(frames: torch.Tensor, labels: Sequence[str], color=(0, 0, 0), corner=(4, 2)) -> torch.Tensor:
    """(N, H, W, 3) float frames in [0, 1] with ``labels[i]`` written on frame ``i`` at the
    top-left ``corner`` (pixels), in Pillow's default font sized to ~8% of the height."""
    if len(labels) != frames.shape[0]:
        raise ValueError(f"need one label per frame: {frames.shape[0]} frames, {len(labels)} labels")
    size = max(8, int(round(0.08 * frames.shape[1])))
    font = ImageFont.load_default(size=size)
    out = []
    for image, text in zip(to_uint8(frames), labels):
        pil = Image.fromarray(image)
        ImageDraw.Draw(pil).text(tuple(corner), str(text), fill=tuple(int(c) for c in color), font=font)
        out.append(np.asarray(pil))
    return torch.from_numpy(np.stack(out)).float() / 255.0
