"""Pictures of Gaussian renders: depth over a fixed range, error maps, side-by-side panels.

Used by ``gs_train`` (validation images in TensorBoard) and ``gs_render`` (the course's
colour | depth | mask turntable). Images are float (H, W, 3) in [0, 1].
"""

from __future__ import annotations

from typing import Sequence

import torch

from l3d_app.errors import UserError

COURSE_DEPTH_CMAP = "jet"       # the course colours depth with matplotlib's jet over a fixed range


def require_colormap(name: str) -> str:
    """``name`` if matplotlib knows the colormap, else :class:`UserError` (checked before rendering)."""
    import matplotlib

    if name not in matplotlib.colormaps:
        raise UserError(f"unknown colormap {name!r}; matplotlib's include jet, viridis, turbo, magma, gray")
    return name


def colorize_depth(depth: torch.Tensor, lo: float, hi: float, mask: torch.Tensor = None,
                   cmap: str = COURSE_DEPTH_CMAP) -> torch.Tensor:
    """(H, W) depth (world units) -> (H, W, 3) colours of ``cmap`` over the FIXED range
    [lo, hi] (values outside are clipped, so frames of a sequence are comparable);
    pixels where ``mask`` (H, W) bool is False are black."""
    import matplotlib

    if not hi > lo:
        raise UserError(f"depth range needs hi > lo, got [{lo}, {hi}]")
    x = ((depth.detach().float().cpu() - lo) / (hi - lo)).clamp(0, 1)
    rgb = torch.from_numpy(matplotlib.colormaps[cmap](x.numpy())[..., :3]).float()
    if mask is not None:
        rgb = rgb * mask.detach().cpu()[..., None].float()
    return rgb


def error_map(pred: torch.Tensor, target: torch.Tensor, gain: float = 4.0) -> torch.Tensor:
    """(H, W, 3) grey image of the per-pixel mean absolute error times ``gain`` (clipped to 1)."""
    e = ((pred.detach().float() - target.detach().float()).abs().mean(-1) * gain).clamp(0, 1)
    return e[..., None].expand(*e.shape, 3).cpu()


def side_by_side(images: Sequence[torch.Tensor]) -> torch.Tensor:
    """(H, sum W, 3): images (H, W_i, 3) or (H, W_i) (grey) concatenated left to right."""
    cols = [(im[..., None].expand(*im.shape, 3) if im.dim() == 2 else im).detach().float().cpu().clamp(0, 1)
            for im in images]
    return torch.cat(cols, 1)


def depth_range(cam_centre: torch.Tensor, scene_box: torch.Tensor) -> tuple:
    """A fixed depth range for pictures: camera-to-box-centre distance -/+ the box's half diagonal."""
    centre = scene_box.float().mean(0).cpu()
    radius = float((scene_box[1].float() - scene_box[0].float()).norm().cpu()) / 2
    dist = float((cam_centre.float().cpu() - centre).norm())
    return max(dist - radius, 1e-3), dist + radius
