"""2D Gaussian surfels rendered by the tiled Gaussian rasteriser: colour, depth, normals, distortion.

One public function, :func:`rasterize_surfels`, the surfel primitive of
:func:`~l3d_app.render.gaussians.rasterize.rasterize_gaussians`: the same tiles, depth sort and
(pixel, splat) pair list (:func:`~l3d_app.render.gaussians.composite.bin_tiles`,
:func:`~l3d_app.render.gaussians.composite.splat_pixel_pairs`), the same transmittance and
early termination, with the splat's footprint given by the perspective-correct ray-splat
intersection instead of the projected covariance (2D Gaussian splatting, Huang et al.
SIGGRAPH 2024): projection in :mod:`~l3d_app.render.gaussians.surfel_project`, compositing with
its hand-written backward in :mod:`~l3d_app.render.gaussians.surfel_composite`. Colour is the
SH colour along the camera-to-centre direction, as for 3D Gaussians.
"""

from __future__ import annotations

from typing import Dict, Optional, Sequence, Union

import torch

from l3d_app.geometry.cameras import Cameras
from l3d_app.render.gaussians.composite import bin_tiles, splat_pixel_pairs
from l3d_app.render.gaussians.rasterize import COVERED_ALPHA
from l3d_app.render.gaussians.sh import sh_to_color
from l3d_app.render.gaussians.surfel_composite import composite_surfels
from l3d_app.render.gaussians.surfel_project import LOW_PASS_INV, project_surfels

__all__ = ["rasterize_surfels"]


def rasterize_surfels(means: torch.Tensor, log_scales: torch.Tensor, quats: torch.Tensor,
                      opacity_logits: torch.Tensor, sh_coeffs: torch.Tensor, sh_degree: int, cams: Cameras,
                      background: Optional[Union[torch.Tensor, Sequence[float]]] = None, near: float = 0.01,
                      tile_size: int = 4, max_elements: int = 1 << 22, custom_backward: bool = True
                      ) -> Dict[str, torch.Tensor]:
    """Render N surfels into B cameras.

    Args:
        means: (N, 3) centres, world units.
        log_scales: (N, 2) or (N, 3) log tangent standard deviations (world units); a third
            column (a 3D Gaussian model's thickness) is ignored.
        quats: (N, 4) rotations ``(w, x, y, z)``, any norm; the third axis is the normal.
        opacity_logits: (N,) or (N, 1); sh_coeffs: (N, K, 3); sh_degree: 0..3.
        cams: B cameras of one image size; background: (3,) RGB (default black).
        near: splats whose centre is closer are culled (world units).
        tile_size, max_elements: as :func:`~l3d_app.render.gaussians.rasterize.rasterize_gaussians`.
        custom_backward: composite with the hand-written backward (False: the autograd reference).
    Returns dict:
        color (B, H, W, 3) on the background; alpha (B, H, W) accumulated opacity; depth
        (B, H, W) ``sum w z`` with ``z`` the camera depth of each ray-splat intersection;
        expected_depth (B, H, W) depth / alpha (0 where alpha <= ``COVERED_ALPHA``); median_depth
        (B, H, W) depth of the splat where the transmittance crosses 0.5 (0 where no splat);
        normal (B, H, W, 3) ``sum w n`` of the camera-facing world normals (not unit);
        distortion (B, H, W) ``sum_{k, j<k} w_k w_j (z_k - z_j)^2`` (world units^2); means2d (B, N, 2)
        projected centres (``retain_grad``: the screen-space gradient for densification); radii
        (B, N) px (0 = culled); visible (B, N); n_pairs (B,) (splat, tile) overlaps.
    """
    dt, dev = means.dtype, means.device
    N = means.shape[0]
    cams = cams.to(device=dev, dtype=dt)
    bg = torch.zeros(3, dtype=dt, device=dev) if background is None else \
        torch.as_tensor(background, dtype=dt, device=dev).reshape(3)
    opacity = torch.sigmoid(opacity_logits.reshape(N))
    proj = project_surfels(means, log_scales, quats, opacity, cams, near=near)
    means2d = proj["means2d"]
    if means2d.requires_grad:
        means2d.retain_grad()
    centres = cams.centers()
    H, W = cams.height, cams.width
    low_pass = torch.tensor([LOW_PASS_INV, 0.0, LOW_PASS_INV], dtype=dt, device=dev).expand(N, 3)
    outs, pairs = [], []
    for b in range(cams.batch_size):
        if not bool(proj["visible"][b].any()):
            zero = torch.zeros(H, W, dtype=dt, device=dev) + 0 * means.sum()
            outs.append((bg.expand(H, W, 3) + zero[..., None], zero, zero, zero, zero, zero[..., None].expand(H, W, 3)))
            pairs.append(0)
            continue
        d = means - centres[b]
        d = d * torch.rsqrt((d * d).sum(-1, keepdim=True).clamp_min(1e-24))
        rgb = sh_to_color(sh_degree, sh_coeffs, d)
        m2, rays, row, floor = means2d[b], proj["rays"][b], proj["depth_row"][b], proj["floor"][b]
        with torch.no_grad():
            sid, t_start, t_count = bin_tiles(proj["box_centre"][b], proj["extent"][b], proj["depth"][b], W, H,
                                              tile_size)
            pix, spl = splat_pixel_pairs(sid, t_start, t_count, m2, low_pass, opacity, W, H, tile_size, max_elements,
                                         rays=rays, floor=floor)
        feats = torch.cat([rgb, proj["normals"][b]], -1)
        acc, a, depth, dist, median = composite_surfels(pix, spl, m2, rays, row, opacity, floor, feats, W, H,
                                                        custom_backward=custom_backward)
        acc, a = acc.reshape(H, W, 6), a.reshape(H, W)
        outs.append((acc[..., :3] + (1.0 - a)[..., None] * bg, a, depth.reshape(H, W), median.reshape(H, W),
                     dist.reshape(H, W), acc[..., 3:]))
        pairs.append(int(sid.numel()))
    color, alpha, depth, median, dist, normal = (torch.stack(x) for x in zip(*outs))
    covered = alpha > COVERED_ALPHA
    safe = torch.where(covered, alpha, torch.ones_like(alpha))
    expected = torch.where(covered, depth / safe, torch.zeros_like(depth))
    return {"color": color, "alpha": alpha, "depth": depth, "expected_depth": expected, "median_depth": median,
            "normal": normal, "distortion": dist, "means2d": means2d, "radii": proj["radius"],
            "visible": proj["visible"], "n_pairs": torch.tensor(pairs)}
