"""Part 4 of bench/diagnose_free_space.py: other rules for where a training ray's free stretch ends.

A run made with ``free_space.save_levels=[...]`` keeps each read-off ray's distance at those opacity
levels besides the stage's own (``free_space.opacity``). Each rule below gives every ray an end
(distance - ``free_space.margin``), scored against the scene's true mesh over ALL training views:

* ``level L``: where the accumulated opacity reaches L;
* ``multi-view``: the stage's own end, cut back where another view's end point lies on this ray in
  front of it by more than ``tol`` (each view's end points projected into every other view, the
  nearest one per pixel: a free-space violation as depth-map fusion tests it);
* ``multi-view, plain pixels``: the same cut only where the ray's pixel is plain (the image's colour
  standard deviation over a 5 x 5 window, mean over RGB, under ``plain``).

Printed per rule: the share of covered rays (a true surface on the pixel) whose end lies behind the
true first surface by more than 0.02 (all, and per object of the scene's ``parts/*.ply``), on
``ground`` the median (end - truth) over the tray floor's rays, and ``kept``: the covered rays'
summed free length (each end clamped at the truth) relative to the stage's own rule.
A diagnosis aid for the development scenes; it chooses nothing.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from l3d_app.render.volume.free_space import nearest_other_view_ends


def plain_texture(images: torch.Tensor, window: int = 5) -> torch.Tensor:
    """(V, H, W, 3) images in [0, 1] -> (V, H, W) colour standard deviation over a ``window`` x
    ``window`` neighbourhood (mean over RGB; the image border averages what lies inside). Summed in
    float64: E[x^2] - E[x]^2 in float32 leaves ~2e-4 on a constant image."""
    x = images.permute(0, 3, 1, 2).double()
    mean = F.avg_pool2d(x, window, 1, window // 2, count_include_pad=False)
    mean_sq = F.avg_pool2d(x * x, window, 1, window // 2, count_include_pad=False)
    return (mean_sq - mean * mean).clamp_min(0).sqrt().mean(1).to(images.dtype)


def report_end_rules(cams, images, saved, margin: float, stage_level: float, truth: torch.Tensor,
                     part: torch.Tensor, floor, origins: torch.Tensor, dirs: torch.Tensor,
                     tol: float = 0.02, plain: float = 0.02) -> None:
    """Print the rules of the module docstring. ``saved``: free_space.pt with ``levels``;
    ``truth`` (V*H*W,) true first-hit distance along unit ``dirs`` (+inf: none); ``part`` (V*H*W,)
    each covered ray's object (-1: none); ``floor``: (V*H*W,) bool or None (ground's tray floor)."""
    n = truth.shape[0]
    dist = torch.full((n, 1 + len(saved["levels"])), float("nan"))
    dist[saved["index"]] = torch.cat([saved["distance"][:, None], saved["level_distances"]], 1).float()
    levels = [stage_level] + [float(x) for x in saved["levels"]]
    seen = torch.isfinite(truth) & ~torch.isnan(dist[:, 0])
    own = dist[:, 0]

    def line(name: str, end: torch.Tensor) -> None:
        behind = seen & (end > truth + 0.02)
        text = f"{name:40s} behind > 0.02: {float(behind.sum() / seen.sum()):.4f}"
        if int(part.max()) >= 0:
            text += " (" + ", ".join(f"part_{k} {float((behind & (part == k)).sum() / (seen & (part == k)).sum()):.3f}"
                                     for k in range(int(part.max()) + 1)) + ")"
        if floor is not None:
            text += f"; tray floor end - truth {float((end - truth)[floor & torch.isfinite(end)].median()):+.3f}"
        both = seen & torch.isfinite(end) & torch.isfinite(own)
        kept = torch.minimum(end, truth)[both].sum() / torch.minimum(own - margin, truth)[both].sum()
        print(text + f"; kept {float(kept):.3f}")

    for k in sorted(range(len(levels)), key=lambda k: levels[k]):
        line(f"level {levels[k]:g}" + (" (the stage's)" if k == 0 else ""), dist[:, k] - margin)
    cut = nearest_other_view_ends(cams, origins, dirs, own, own - margin, tol)
    line(f"multi-view (tol {tol:g})", torch.minimum(own, cut + tol) - margin)
    flat = (plain_texture(images) < plain).reshape(-1)
    line(f"multi-view, plain pixels (< {plain:g})", torch.where(flat, torch.minimum(own, cut + tol), own) - margin)
