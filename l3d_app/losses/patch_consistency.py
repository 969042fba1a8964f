"""Multi-view patch consistency (as Geo-NeuS): a surface point and its normal predict where a small
patch of the reference image lands in nearby training views; the loss is one minus the normalised
cross-correlation (NCC) of the grey patches.

Where the images alone leave the geometry free (a lid over a solid-coloured interior, stripes carved
into a flat face that a view-dependent colour paints back), the colour loss is satisfied by a wrong
surface; a textured patch warped through the wrong plane lands on the wrong pixels of the other
views, so NCC prefers the surface whose parallax matches. A patch without texture (grey std below
``min_std``) says nothing and is left out.

The warp is plane-induced: the ray through each patch pixel of the reference camera meets the plane
through the surface point ``x`` with normal ``n``, and that point is projected into each source camera
(pinhole, :class:`~l3d_app.geometry.cameras.Cameras`' convention: pixel centres at +0.5). Units: world
units for points, pixels for image coordinates, grey levels in [0, 1].
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Dict, Optional, Tuple

import torch

from l3d_app.errors import UserError
from l3d_app.geometry.cameras import Cameras
from l3d_app.geometry.rays import pixel_axes
from l3d_app.geometry.textures import sample_texture_indexed
from l3d_app.losses.terms import Batch, LossTerm
from l3d_app.registry import LOSS_TERMS
from l3d_app.render.volume.estimators.zero_crossing import crossing_bracket


def surface_crossing(t: torch.Tensor, sdf: torch.Tensor, grad: torch.Tensor
                     ) -> Tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Each ray's first zero crossing from its samples: ``t`` (R, S) increasing, ``sdf`` (R, S) and the
    SDF's gradient ``grad`` (R, S, 3) there. Returns ``t_hit`` (R,), the normal (R, 3) (the gradient
    interpolated as ``t`` is, not normalised) and ``hit`` (R,) bool; differentiable in ``sdf`` and ``grad``."""
    i, frac, hit = crossing_bracket(sdf)
    t0, t1 = t.gather(1, i)[:, 0], t.gather(1, i + 1)[:, 0]
    gi = i[..., None].expand(-1, -1, 3)
    g0, g1 = grad.gather(1, gi)[:, 0], grad.gather(1, gi + 1)[:, 0]
    return t0 + frac * (t1 - t0), g0 + frac[:, None] * (g1 - g0), hit


def grey(images: torch.Tensor) -> torch.Tensor:
    """(V, H, W, 3) RGB in [0, 1] -> (V, H, W) grey (Rec. 601 luma weights)."""
    w = torch.tensor([0.299, 0.587, 0.114], dtype=images.dtype, device=images.device)
    return images @ w


def nearest_views(centers: torch.Tensor, k: int) -> torch.Tensor:
    """(V, k) long: for each camera, the ``k`` OTHER cameras whose centres (V, 3) are nearest
    (world distance; ``k`` at most V - 1)."""
    d = torch.cdist(centers, centers)
    d.fill_diagonal_(float("inf"))
    return d.topk(min(int(k), centers.shape[0] - 1), dim=1, largest=False).indices


def patch_offsets(size: int, dtype=torch.float32, device=None) -> torch.Tensor:
    """(size^2, 2) integer pixel offsets (du, dv) of an odd ``size`` x ``size`` patch, row-major."""
    if size < 1 or size % 2 == 0:
        raise ValueError(f"patch size must be odd and positive, got {size}")
    r = torch.arange(size, dtype=dtype, device=device) - (size - 1) / 2
    dv, du = torch.meshgrid(r, r, indexing="ij")
    return torch.stack([du.reshape(-1), dv.reshape(-1)], dim=-1)


def bilinear(images: torch.Tensor, view: torch.Tensor, uv: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
    """Bilinear look-up of single-channel ``images`` (V, H, W) at pixel coordinates ``uv`` (..., 2)
    of images ``view`` (...) (long): ``(values (...), inside (...) bool)``; a coordinate whose four
    neighbours are not all in the image reads 0 and is not ``inside``. Differentiable in ``uv``
    (:func:`~l3d_app.geometry.textures.sample_texture_indexed`, pixel centres at +0.5)."""
    _, h, w = images.shape
    x, y = uv[..., 0] - 0.5, uv[..., 1] - 0.5
    inside = (x >= 0) & (x <= w - 1) & (y >= 0) & (y <= h - 1) & torch.isfinite(x) & torch.isfinite(y)
    uv = torch.where(inside[..., None], uv, torch.full_like(uv, 0.5))
    tex_uv = torch.stack([uv[..., 0] / w, 1.0 - uv[..., 1] / h], dim=-1).reshape(-1, 2)   # v up, as OBJ
    values = sample_texture_indexed(images[..., None], tex_uv, view.reshape(-1))[:, 0].reshape(inside.shape)
    return torch.where(inside, values, torch.zeros_like(values)), inside


def ncc(a: torch.Tensor, b: torch.Tensor, eps: float = 1e-8) -> torch.Tensor:
    """Normalised cross-correlation of patches ``a``, ``b`` (..., P) along the last axis, in [-1, 1]."""
    a = a - a.mean(dim=-1, keepdim=True)
    b = b - b.mean(dim=-1, keepdim=True)
    return (a * b).sum(-1) / torch.sqrt((a * a).sum(-1) * (b * b).sum(-1) + eps)


@dataclass
class PatchConsistency:
    """The training views' grey images, cameras and source-view table for :meth:`loss`.

    Attributes:
        images: (V, H, W) grey training images.
        cameras: the V training cameras.
        sources: (V, k) the nearest other training views of each.
        size: odd patch width in pixels; ``best``: how many of the k source NCCs are averaged (the
            highest: a source that sees another surface, occluded, does not count);
        min_std: grey std (0-1 levels) below which a reference patch has no texture to match;
        min_cos: least ``|n . d|`` between the normal and the reference ray (grazing planes warp
            unstably), and least cosine between the normal and each source's direction to ``x``.
    """

    images: torch.Tensor
    cameras: Cameras
    sources: torch.Tensor
    size: int = 5
    best: int = 2
    min_std: float = 0.01
    min_cos: float = 0.2

    @staticmethod
    def build(images: torch.Tensor, cameras: Cameras, n_sources: int = 4, **kw) -> "PatchConsistency":
        """From the training images (V, H, W, 3) and cameras; ``n_sources`` nearest views per view."""
        return PatchConsistency(grey(images).contiguous(), cameras, nearest_views(cameras.centers(), n_sources), **kw)

    def loss(self, view: torch.Tensor, pixel: torch.Tensor, origins: torch.Tensor, dirs: torch.Tensor,
             t_hit: torch.Tensor, normal: torch.Tensor, hit: torch.Tensor) -> Tuple[torch.Tensor, Dict[str, float]]:
        """Mean of ``(1 - NCC) / 2`` over the rays that count, and figures for the log.

        Args:
            view: (R,) long training view of each ray; ``pixel`` (R, 2) long its (row, column).
            origins, dirs: (R, 3) the rays (unit ``dirs``) through those pixels' centres.
            t_hit: (R,) distance to the surface along the ray; ``normal`` (R, 3) its normal there
                (any length, either sign); ``hit`` (R,) bool rays that reach a surface.
        Returns:
            ``(loss (), {"ncc_rays": share of rays that count, "ncc": their mean best NCC})``; a loss of
            0 (no gradient) where no ray counts. Computed in at least float32 with autocast off (pixel
            coordinates of ~100 need more than bf16's 8 bits), whatever the caller's precision.
        """
        work = torch.promote_types(torch.promote_types(origins.dtype, torch.float32), self.cameras.R.dtype)
        with torch.autocast(origins.device.type, enabled=False):
            return self._loss(view, pixel, origins.to(work), dirs.to(work), t_hit.to(work), normal.to(work), hit)

    def _loss(self, view, pixel, origins, dirs, t_hit, normal, hit) -> Tuple[torch.Tensor, Dict[str, float]]:
        """:meth:`loss` in the inputs' precision."""
        centre = dirs
        cams, dtype = self.cameras, origins.dtype
        h, w = cams.height, cams.width
        off = patch_offsets(self.size, dtype, origins.device)                        # (P, 2)
        rows, cols = pixel[:, 0:1] + off[None, :, 1].long(), pixel[:, 1:2] + off[None, :, 0].long()
        in_ref = ((rows >= 0) & (rows < h) & (cols >= 0) & (cols < w)).all(-1)
        at = view[:, None] * (h * w) + rows.clamp(0, h - 1) * w + cols.clamp(0, w - 1)   # (R, P) flat pixels
        ref = self.images.reshape(-1)[at]
        textured = ref.std(dim=-1) >= self.min_std                                    # (R,)
        n = torch.nn.functional.normalize(normal, dim=-1)
        cos_ref = (n * centre).sum(-1)
        x = origins + t_hit[:, None] * dirs                                           # (R, 3)
        # rays through the patch pixels: unnormalised directions, camera Z = 1
        du, dv = pixel_axes(cams)                                                     # (V, 3) per pixel step
        d_centre = centre / (centre * cams.R[view, 2]).sum(-1, keepdim=True)
        d_patch = d_centre[:, None] + off[None, :, :1] * du[view, None] + off[None, :, 1:] * dv[view, None]   # (R, P, 3)
        plane = ((x - origins) * n).sum(-1, keepdim=True)                            # (R, 1)
        denom = (d_patch * n[:, None]).sum(-1)                                        # (R, P)
        ok_plane = (cos_ref.abs() >= self.min_cos) & (denom.abs() > 1e-6).all(-1)
        s = plane / torch.where(denom.abs() > 1e-6, denom, torch.ones_like(denom))
        pts = origins[:, None] + s[..., None] * d_patch                               # (R, P, 3)
        src = self.sources[view]                                                      # (R, k)
        r, k, p = src.shape[0], src.shape[1], pts.shape[1]
        uv, z = cams[src.reshape(-1)].project(pts.repeat_interleave(k, dim=0))       # (R k, P, 2), (R k, P)
        uv, z = uv.reshape(r, k, p, 2), z.reshape(r, k, p)
        values, inside = bilinear(self.images, src[..., None].expand(z.shape), uv)   # (R, k, P)
        to_src = torch.nn.functional.normalize(cams.centers()[src] - x[:, None], dim=-1)   # (R, k, 3)
        facing = ((to_src * n[:, None]).sum(-1) * torch.sign(-cos_ref)[:, None]) >= self.min_cos
        valid = (inside & (z > 1e-6)).all(-1) & facing                               # (R, k)
        score = torch.where(valid, ncc(ref[:, None, :].expand_as(values), values), torch.full_like(z[..., 0], -2.0))
        top = score.topk(min(self.best, score.shape[1]), dim=1).values               # (R, best)
        counts = hit & in_ref & textured & ok_plane & (top > -2.0).all(-1)
        if not bool(counts.any()):
            return torch.zeros((), dtype=dtype, device=origins.device), {"ncc_rays": 0.0, "ncc": 0.0}
        best_ncc = top[counts].mean(-1)
        return ((1.0 - best_ncc) / 2).mean(), {"ncc_rays": float(counts.float().mean()),
                                                "ncc": float(best_ncc.detach().mean())}


@LOSS_TERMS.register("patch_ncc")
class PatchNCCLoss(LossTerm):
    """:meth:`PatchConsistency.loss` of each batch ray's first zero crossing (from its render's samples) and
    normal, over the training views: ``(1 - NCC) / 2`` of ``size`` x ``size`` grey patches warped into the
    ``sources`` nearest training views (the ``best`` of them averaged); logs ``ncc_rays`` (share of rays that
    count) and ``ncc``. Patches assume surfaces that look alike from nearby views: the shipped schedule fades
    it out by half the steps (kept to the end it hurt a glossy development scene, docs/measured/volsdf.md)."""

    def __init__(self, weight: float = 0.1, until: Optional[float] = 0.5, start: float = 0.0, size: int = 5,
                 sources: int = 4, best: int = 2, min_std: float = 0.01, min_cos: float = 0.2):
        super().__init__(weight, start, until)
        for key, value in (("min_std", min_std), ("min_cos", min_cos)):
            if isinstance(value, bool) or not isinstance(value, (int, float)) or value < 0:
                raise UserError(f"the patch term's {key} must be a number >= 0, got {value!r}")
        for key, value in (("size", size), ("sources", sources), ("best", best)):
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise UserError(f"the patch term's {key} must be a positive integer, got {value!r}")
        if size % 2 == 0:
            raise UserError(f"the patch term's size must be odd (a patch centred on its pixel), got {size}")
        if best > sources:
            raise UserError(f"the patch term's best must be at most its sources ({sources}), got {best}")
        self.options = {"size": size, "best": best, "min_std": float(min_std), "min_cos": float(min_cos)}
        self.sources = sources

    def setup(self, state) -> bool:
        rays = state.rays
        self.patches = PatchConsistency.build(rays.images, rays.cameras, n_sources=self.sources, **self.options)
        return True

    def __call__(self, batch: Batch) -> Tuple[torch.Tensor, Dict[str, float]]:
        rays, out, n = batch.state.rays, batch.out, batch.rays.shape[0]
        hw = rays.height * rays.width
        view, rest = batch.rays // hw, batch.rays % hw
        t_hit, normal, hit = surface_crossing(out["t"].reshape(n, -1), out["sdf"].reshape(n, -1),
                                              out["grad"].reshape(n, -1, 3))
        return self.patches.loss(view, torch.stack([rest // rays.width, rest % rays.width], -1), batch.origins,
                                 batch.dirs, t_hit, normal, hit)
