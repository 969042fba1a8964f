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

from l3d_app.geometry.cameras import Cameras
from l3d_app.geometry.rays import pixel_axes
from l3d_app.geometry.textures import sample_texture_indexed
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
        masks: (V, H, W) the images' coverage (alpha) or None; with it only reference patches whose
            every pixel has coverage >= ``min_alpha`` count (a patch across a silhouette is not one plane).
    """

    images: torch.Tensor
    cameras: Cameras
    sources: torch.Tensor
    size: int = 5
    best: int = 2
    min_std: float = 0.01
    min_cos: float = 0.2
    masks: Optional[torch.Tensor] = None
    min_alpha: float = 0.5

    @staticmethod
    def build(images: torch.Tensor, cameras: Cameras, n_sources: int = 4, **kw) -> "PatchConsistency":
        """From the training images (V, H, W, 3) and cameras; ``n_sources`` nearest views per view."""
        return PatchConsistency(grey(images).contiguous(), cameras, nearest_views(cameras.centers(), n_sources), **kw)

    def loss(self, view: torch.Tensor, pixel: torch.Tensor, origins: torch.Tensor, dirs: torch.Tensor,
             t_hit: torch.Tensor, normal: torch.Tensor, hit: torch.Tensor,
             centre_dirs: Optional[torch.Tensor] = None) -> Tuple[torch.Tensor, Dict[str, float]]:
        """Mean of ``(1 - NCC) / 2`` over the rays that count, and figures for the log.

        Args:
            view: (R,) long training view of each ray; ``pixel`` (R, 2) long its (row, column).
            origins, dirs: (R, 3) the rays (unit ``dirs``) through those pixels' centres, or through
                any point of those pixels when ``centre_dirs`` is given (jittered training rays).
            t_hit: (R,) distance to the surface along the ray; ``normal`` (R, 3) its normal there
                (any length, either sign); ``hit`` (R,) bool rays that reach a surface.
            centre_dirs: (R, 3) unit directions through the pixels' centres, where the patch is
                centred (None: ``dirs``). The plane still passes through ``origins + t_hit * dirs``.
        Returns:
            ``(loss (), {"ncc_rays": share of rays that count, "ncc": their mean best NCC})``; a loss of
            0 (no gradient) where no ray counts. Computed in at least float32 with autocast off (pixel
            coordinates of ~100 need more than bf16's 8 bits), whatever the caller's precision.
        """
        work = torch.promote_types(torch.promote_types(origins.dtype, torch.float32), self.cameras.R.dtype)
        with torch.autocast(origins.device.type, enabled=False):
            centre = dirs if centre_dirs is None else centre_dirs
            return self._loss(view, pixel, origins.to(work), dirs.to(work), t_hit.to(work), normal.to(work), hit,
                              centre.to(work))

    def _loss(self, view, pixel, origins, dirs, t_hit, normal, hit, centre) -> Tuple[torch.Tensor, Dict[str, float]]:
        """:meth:`loss` in the inputs' precision (``centre``: the unit rays through the pixel centres)."""
        cams, dtype = self.cameras, origins.dtype
        h, w = cams.height, cams.width
        off = patch_offsets(self.size, dtype, origins.device)                        # (P, 2)
        rows, cols = pixel[:, 0:1] + off[None, :, 1].long(), pixel[:, 1:2] + off[None, :, 0].long()
        in_ref = ((rows >= 0) & (rows < h) & (cols >= 0) & (cols < w)).all(-1)
        at = view[:, None] * (h * w) + rows.clamp(0, h - 1) * w + cols.clamp(0, w - 1)   # (R, P) flat pixels
        ref = self.images.reshape(-1)[at]
        textured = ref.std(dim=-1) >= self.min_std                                    # (R,)
        if self.masks is not None:       # patches wholly on the object: one surface, no silhouette across them
            in_ref = in_ref & (self.masks.reshape(-1)[at] >= self.min_alpha).all(-1)
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
