"""The start of a splat model for a capture in which every pixel is scene (walls, floor, sky).

Structure-from-motion leaves a few thousand points, dense on edges and texture, sparse on plain
walls and absent from much of the floor near the camera; their neighbour-distance scales span
orders of magnitude, and a handful of isolated points (huge neighbour distances) would cover the
views many times over. :func:`cover_views` starts from the round splats at the points
(:func:`~l3d_app.models.gaussians.init_from_points`) and

1. caps the splats that cover the most (:func:`~l3d_app.render.gaussians.coverage.cap_to_coverage`),
   so that the start-up cost stays bounded while the other splats keep their scales;
2. gives every cell of a grid over each sampled training view that the splats leave uncovered one
   more splat (:func:`fill_splats`): on the cell centre's ray, at the depth of the sparse points that
   project nearest to it in that view, with the cell's mean colour and a scale that covers the cell;
3. caps the whole set again to the same bound.
"""

from __future__ import annotations

import math

import torch

from l3d_app.geometry.cameras import Cameras
from l3d_app.geometry.rays import pixels_to_directions
from l3d_app.models.gaussians import GaussianModel
from l3d_app.render.gaussians.coverage import cap_to_coverage
from l3d_app.render.gaussians.rasterize import rasterize_gaussians
from l3d_app.render.gaussians.sh import rgb_to_sh

CELLS_PER_SIDE = 16     # grid cells along an image's long side for the uncovered-pixel splats
NEAREST_POINTS = 5      # sparse points whose median depth places a cell's splat
COVERED = 0.5           # a cell is covered when its mean alpha, every splat opaque, reaches this
OPAQUE = 0.99           # the opacity every splat takes for that test


@torch.no_grad()
def fill_splats(means: torch.Tensor, log_scales: torch.Tensor, quats: torch.Tensor, points: torch.Tensor,
                images: torch.Tensor, cams: Cameras, cells: int = CELLS_PER_SIDE):
    """Splats for the grid cells of each view that the splats (``means`` (N, 3), ``log_scales`` (N, S),
    ``quats`` (N, 4)), all opaque, leave uncovered.

    A cell (``max(H, W) / cells`` px square) is uncovered when its mean alpha is under :data:`COVERED`.
    Its splat lies on the ray through the cell centre at the median camera depth of the
    :data:`NEAREST_POINTS` ``points`` (P, 3) projecting nearest to that centre in the view; its
    scale is half the cell's width at that depth; its colour the cell's mean in ``images``
    (V, H, W, 3). Views with fewer points in front of them than that are skipped.

    Returns (M, 3) means, (M,) log scales (world units), (M, 3) colours in [0, 1].
    """
    V, H, W = images.shape[:3]
    cell = max(1, round(max(H, W) / int(cells)))
    gh, gw = H // cell, W // cell
    dev, dt = means.device, means.dtype
    out_means, out_scales, out_colors = [], [], []
    logits = torch.full((means.shape[0],), math.log(OPAQUE / (1 - OPAQUE)), device=dev, dtype=dt)
    black = torch.zeros(means.shape[0], 1, 3, device=dev, dtype=dt)
    v, u = torch.meshgrid(torch.arange(gh, device=dev, dtype=dt), torch.arange(gw, device=dev, dtype=dt), indexing="ij")
    centres = (torch.stack([u, v], -1) * cell + 0.5 * cell).reshape(-1, 2)             # (G, 2) pixels
    for i in range(V):                                                                # views, not pixels
        cam = cams[i]
        alpha = rasterize_gaussians(means, log_scales.expand(-1, 3), quats, logits, black, 0, cam,
                                    torch.zeros(3, device=dev))["alpha"][0]
        pool = lambda x: torch.nn.functional.avg_pool2d(x[: gh * cell, : gw * cell].permute(2, 0, 1)[None], cell)[0]
        cover = pool(alpha[..., None]).reshape(-1)                                     # (G,)
        colour = pool(images[i].to(dt)).permute(1, 2, 0).reshape(-1, 3)                # (G, 3)
        uv, z = cam.project(points.to(dt))
        ok = (z[0] > 1e-6) & (uv[0, :, 0] >= 0) & (uv[0, :, 0] < W) & (uv[0, :, 1] >= 0) & (uv[0, :, 1] < H)
        hole = cover < COVERED
        if int(ok.sum()) < NEAREST_POINTS or not bool(hole.any()):
            continue
        near = torch.cdist(centres[hole], uv[0, ok]).topk(NEAREST_POINTS, largest=False).indices   # (M, k)
        depth = z[0, ok][near].median(-1).values                                       # (M,)
        dirs = pixels_to_directions(cam, centres[hole][None], normalize=False)[0]      # camera z = 1
        out_means.append(cam.centers()[0] + dirs * depth[:, None])
        out_scales.append(torch.log(0.5 * cell * depth / (0.5 * (cam.fx[0] + cam.fy[0]))))
        out_colors.append(colour[hole])
    if not out_means:
        return means.new_zeros(0, 3), means.new_zeros(0), means.new_zeros(0, 3)
    return torch.cat(out_means), torch.cat(out_scales), torch.cat(out_colors).clamp(0, 1)


@torch.no_grad()
def cover_views(model: GaussianModel, images: torch.Tensor, cams: Cameras, max_coverage: float) -> GaussianModel:
    """:func:`fill_splats` over the sampled training views (``images`` (V, H, W, 3), ``cams``) added to
    ``model`` (its splats at the sparse points, scales capped to ``max_coverage`` on the same cameras
    first, when > 0), the whole set capped again; new splats take the first splat's opacity and
    rotation, no higher SH bands. Returns a new model."""
    opacity = torch.sigmoid(model.opacity_logits)
    scales = model.log_scales.data
    if max_coverage > 0:
        scales = cap_to_coverage(model.means, scales, model.quats, opacity, cams, max_coverage)
    new_means, new_scales, new_colors = fill_splats(model.means, scales, model.quats, model.means, images, cams)
    m = new_means.shape[0]
    grown = GaussianModel(torch.cat([model.means, new_means]),
                          torch.cat([scales, new_scales[:, None].expand(m, scales.shape[1])]),
                          torch.cat([model.quats, model.quats[:1].expand(m, 4)]),
                          torch.cat([model.opacity_logits, model.opacity_logits[:1].expand(m)]),
                          torch.cat([model.sh_dc, rgb_to_sh(new_colors)[:, None, :]]),
                          torch.cat([model.sh_rest, model.sh_rest.new_zeros(m, *model.sh_rest.shape[1:])]))
    if max_coverage > 0 and m:
        grown.log_scales.data = cap_to_coverage(grown.means, grown.log_scales, grown.quats,
                                                torch.sigmoid(grown.opacity_logits), cams, max_coverage)
    return grown.to(model.means.device)
