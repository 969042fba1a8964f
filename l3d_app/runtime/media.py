"""Images and animations on disk (PNG, GIF, MP4), written atomically."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Sequence, Union

import imageio.v2 as imageio
import numpy as np
import torch

from l3d_app.runtime.files import atomic_path

Frames = Union[torch.Tensor, np.ndarray, Sequence]


def to_uint8(images: Frames) -> np.ndarray:
    """Float images in [0, 1] (..., H, W, C) -> uint8 array (values clamped)."""
    if torch.is_tensor(images):
        images = images.detach().float().cpu().numpy()
    images = np.asarray(images, dtype=np.float32)
    return (np.clip(images, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def gif_bytes(frames: Frames, fps: float = 15.0) -> bytes:
    """(N, H, W, 3) float frames in [0, 1] -> the bytes of a looping GIF at ``fps`` frames/s (encoded in
    memory: :func:`save_gif` writes them; a time budget prices the encoding of one frame with it)."""
    return imageio.mimwrite("<bytes>", list(to_uint8(frames)), format="GIF", duration=1000.0 / float(fps), loop=0)


def save_gif(path: os.PathLike, frames: Frames, fps: float = 15.0) -> Path:
    """Save (N, H, W, 3) float frames in [0, 1] as a looping GIF at ``fps`` frames/s."""
    data = gif_bytes(frames, fps)
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)
    return Path(path)


def save_png(path: os.PathLike, image: Frames) -> Path:
    """Save one (H, W, 3) float image in [0, 1] as PNG."""
    with atomic_path(path) as tmp:
        imageio.imwrite(tmp, to_uint8(image), format="PNG")
    return Path(path)


def save_mp4(path: os.PathLike, frames: Frames, fps: float) -> None:
    """(N, H, W, 3) in [0, 1] -> H.264 mp4 (padded to even sizes), written atomically; needs imageio-ffmpeg."""
    from l3d_app.errors import UserError

    try:
        import imageio_ffmpeg  # noqa: F401
    except ImportError as err:
        raise UserError("mp4 output needs imageio-ffmpeg: pip install imageio-ffmpeg (or formats=[gif])") from err
    x = to_uint8(frames)
    ph, pw = x.shape[1] % 2, x.shape[2] % 2
    x = np.pad(x, ((0, 0), (0, ph), (0, pw), (0, 0)), mode="edge")
    with atomic_path(path) as tmp:
        imageio.mimwrite(tmp, list(x), fps=float(fps), codec="libx264", macro_block_size=1,
                         ffmpeg_log_level="error", output_params=["-pix_fmt", "yuv420p"])
