"""Small charts as images (H, W, 3) in [0, 1]: a confusion matrix and a line plot (matplotlib), a grid of images."""

from __future__ import annotations

from typing import Optional, Sequence

import numpy as np
import torch


def _figure_image(fig) -> np.ndarray:
    import matplotlib.pyplot as plt

    fig.tight_layout()
    fig.canvas.draw()
    image = np.asarray(fig.canvas.buffer_rgba())[..., :3].astype(np.float32) / 255.0
    plt.close(fig)
    return image


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def confusion_image(cm: torch.Tensor, names: Sequence[str], title: str) -> np.ndarray:
    """(H, W, 3) float image of a (K, K) confusion matrix (rows: truth), row-normalised
    colours with the counts written in (for K <= 20)."""
    plt = _pyplot()
    k = cm.shape[0]
    rows = cm.double() / cm.sum(1, keepdim=True).clamp_min(1)
    fig, ax = plt.subplots(figsize=(2 + 0.6 * k, 1.6 + 0.6 * k), dpi=100)
    ax.imshow(rows.numpy(), cmap="Blues", vmin=0, vmax=1)
    if k <= 20:
        for i in range(k):
            for j in range(k):
                ax.text(j, i, str(int(cm[i, j])), ha="center", va="center", fontsize=7,
                        color="white" if rows[i, j] > 0.5 else "black")
    ax.set_xticks(range(k), labels=list(names), rotation=60, ha="right", fontsize=7)
    ax.set_yticks(range(k), labels=list(names), fontsize=7)
    ax.set_xlabel("predicted")
    ax.set_ylabel("true")
    ax.set_title(title, fontsize=9)
    return _figure_image(fig)


def line_plot(x: Sequence[float], y: Sequence[float], xlabel: str, ylabel: str, title: str,
              ylim: Optional[Sequence[float]] = None, vline: Optional[float] = None) -> np.ndarray:
    """(H, W, 3) float image of one line with markers; optional y range and vertical guide."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(5, 3.6), dpi=100)
    ax.plot(list(x), list(y), "o-", color="tab:blue")
    if vline is not None:
        ax.axvline(float(vline), color="0.6", lw=0.8, ls="--")
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    if ylim is not None:
        ax.set_ylim(*ylim)
    ax.set_title(title, fontsize=9)
    ax.grid(alpha=0.3)
    return _figure_image(fig)


def image_grid(images: torch.Tensor, cols: int, pad: int = 1, value: float = 1.0) -> torch.Tensor:
    """Tile (N, 3, H, W) images into one (rows*(H+pad)-pad, cols*(W+pad)-pad, 3) image."""
    N, C, H, W = images.shape
    rows = -(-N // cols)
    canvas = torch.full((rows * cols, C, H + pad, W + pad), value, dtype=images.dtype)
    canvas[:N, :, :H, :W] = images.detach().cpu()
    grid = canvas.view(rows, cols, C, H + pad, W + pad).permute(0, 3, 1, 4, 2)
    return grid.reshape(rows * (H + pad), cols * (W + pad), C)[:-pad or None, :-pad or None]
