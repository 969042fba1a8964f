"""Evaluation views of a field: render them, score them, make one picture of them.

:func:`render_views` renders cameras through any ``render_fn(origins, dirs) -> {"color",
"depth", "opacity"}`` in chunks (optionally ``supersample``^2 rays per pixel, averaged), and
:func:`render_part` a spread share of their pixels, to time it;
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
from l3d_app.runtime.progress import progress

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


@torch.no_grad()
def render_part(render_fn: RenderFn, cameras: Cameras, share: float = 1.0 / 16, most: int = 16384) -> float:
    """Render one call of rays through pixels spread evenly over all of ``cameras``' pixels: a
    ``share`` of them, at most ``most``; returns the share rendered (a cheap timing of
    :func:`render_views`: seconds / share)."""
    o, d = camera_rays(cameras, normalize=True)
    total = o.shape[0] * o.shape[1] * o.shape[2]
    n = max(1, min(int(most), int(round(float(share) * total)), total))
    idx = torch.linspace(0, total - 1, n, device=o.device).round().long()
    render_fn(o.reshape(-1, 3)[idx], d.reshape(-1, 3)[idx])
    return n / float(total)


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


def panel_frames(out: Dict[str, torch.Tensor], panels) -> torch.Tensor:
    """(N, H, W * len(panels), 3) frames in [0, 1] of ``panels`` (any of colour, depth, alpha) side by
    side, from ``out``'s color (N, H, W, 3), depth and alpha (N, H, W); depth: grey over covered
    pixels (alpha > 0.5), white near, normalised by its 2% and 98% quantiles over all frames."""
    alpha = out["alpha"].clamp(0, 1)
    depth = out["depth"] / alpha.clamp_min(1e-6)
    hit = alpha > 0.5
    if bool(hit.any()):
        q = torch.quantile(depth[hit].float()[:1_000_000], torch.tensor([0.02, 0.98]))
        lo, hi = float(q[0]), float(q[1])
    else:
        lo, hi = 0.0, 1.0
    gray = torch.where(hit, (1.0 - 0.8 * (depth - lo) / max(hi - lo, 1e-6)).clamp(0.2, 1.0), torch.zeros_like(depth))
    parts = {"color": out["color"].clamp(0, 1), "depth": gray[..., None].expand(*gray.shape, 3),
             "alpha": alpha[..., None].expand(*alpha.shape, 3)}
    return torch.cat([parts[p] for p in panels], dim=2)


@torch.no_grad()
def render_frames(renderer, mesh, cams: Cameras, batch: int, desc: str,
                  keys=("image", "alpha", "depth")) -> Dict[str, torch.Tensor]:
    """Render ``cams`` in batches of ``batch`` views; returns the ``keys`` outputs
    stacked over all views, on the CPU: image (N, H, W, 3), alpha (N, H, W), depth (N, H, W).
    """
    chunks: Dict[str, list] = {k: [] for k in keys}
    for start in progress(range(0, len(cams), batch), desc=desc):
        out = renderer(mesh, cams[start:start + batch])
        for k in keys:
            chunks[k].append(out[k].detach().cpu())
    return {k: torch.cat(v) for k, v in chunks.items()}
