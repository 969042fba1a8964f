"""Evaluation views of a field: render them, score them, make one picture of them.

:func:`render_views` renders cameras through any ``render_fn(origins, dirs) -> {"color",
"depth", "opacity"}`` in chunks (optionally ``supersample``^2 rays per pixel, averaged);
:func:`evaluation_picture` is the picture every evaluation logs
(:func:`l3d_app.pipelines.views.evaluate_views` adds the scores):
one row per view, ``prediction | truth | |error| (x4, clamped) | depth`` (depth: white near,
dark far over pixels with opacity > 0.5, black elsewhere).
"""

from __future__ import annotations

from typing import Callable, Dict, Optional

import torch

from l3d_app.geometry.cameras import Cameras
from l3d_app.geometry.rays import camera_rays, supersampled_rays
from l3d_app.render.volume.renderer import render_rays_chunked

RenderFn = Callable[[torch.Tensor, torch.Tensor], Dict[str, torch.Tensor]]


@torch.no_grad()
def render_views(render_fn: RenderFn, cameras: Cameras, chunk: int = 8192, supersample: int = 1
                 ) -> Dict[str, torch.Tensor]:
    """color (V, H, W, C), depth (V, H, W), opacity (V, H, W) of every pixel of ``cameras``
    (unit ray directions; with ``supersample`` > 1 each pixel averages s*s sub-pixel rays)."""
    def fn(o, d):
        out = render_fn(o, d)
        return {k: out[k] for k in ("color", "depth", "opacity") if k in out}

    if int(supersample) > 1:
        o, d = supersampled_rays(cameras, int(supersample))                 # (V, H, W, s*s, 3)
        return {k: v.mean(dim=3) for k, v in render_rays_chunked(fn, o, d, int(chunk)).items()}
    o, d = camera_rays(cameras, normalize=True)
    return render_rays_chunked(fn, o, d, int(chunk))


def depth_picture(depth: torch.Tensor, opacity: torch.Tensor) -> torch.Tensor:
    """(..., H, W, 3) grey depth: white = nearest, 0.2 = farthest opaque pixel, black = empty.
    ``depth`` is the composited sum w t (divided by the opacity here)."""
    d = depth / opacity.clamp_min(1e-6)
    hit = opacity > 0.5
    lo = d[hit].min() if bool(hit.any()) else d.min()
    hi = d[hit].max() if bool(hit.any()) else d.max()
    gray = torch.where(hit, 1.0 - 0.8 * (d - lo) / (hi - lo).clamp_min(1e-6), torch.zeros_like(d))
    return gray[..., None].expand(*gray.shape, 3)


def evaluation_picture(pred: torch.Tensor, target: torch.Tensor, depth: Optional[torch.Tensor] = None,
                       opacity: Optional[torch.Tensor] = None, max_views: int = 4) -> torch.Tensor:
    """(rows*H, k*W, 3) picture: per view ``pred | truth | 4 |error| | depth`` (depth if given)."""
    rows = []
    for i in range(min(int(max_views), pred.shape[0])):
        p, t = pred[i].clamp(0, 1), target[i]
        cols = [p, t, (4.0 * (p - t).abs()).clamp(0, 1)]
        if depth is not None and opacity is not None:
            cols.append(depth_picture(depth[i], opacity[i]))
        rows.append(torch.cat(cols, dim=1))
    return torch.cat(rows, dim=0).cpu()
