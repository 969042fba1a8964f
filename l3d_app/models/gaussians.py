"""A set of 3D Gaussians as trainable tensors, and adaptive density control (3DGS).

:class:`GaussianModel` holds N splats: ``means`` (N, 3) world units, ``log_scales`` (N, 3)
log standard deviations, ``quats`` (N, 4) ``(w, x, y, z)``, ``opacity_logits`` (N,),
``sh_dc`` (N, 1, 3) and ``sh_rest`` (N, 15, 3) spherical-harmonic colour (degree 3 storage).

:class:`DensityControl` is the 3DGS strategy as a small pluggable class: it accumulates the
screen-space (NDC) gradient norm of each splat's projected centre over the views in which
it is visible, then periodically clones small splats / splits large ones whose average
exceeds ``grad_threshold``, prunes transparent or too large ones, resets opacities, and
caps the count. Resized parameters are new ``Parameter`` objects swapped into the model
and the optimiser, Adam moments carried over (zeros for new splats); a list of
parameters taken before a resize (the shared loop's gradient check) goes stale.
"""

from __future__ import annotations

import math
from typing import Dict, Optional

import torch

from l3d_app.geometry.normals import knn
from l3d_app.models.sh import rgb_to_sh

PARAM_NAMES = ("means", "log_scales", "quats", "opacity_logits", "sh_dc", "sh_rest")


class GaussianModel(torch.nn.Module):
    """N Gaussians (see the module docstring); ``sh`` is (N, 16, 3) = [sh_dc | sh_rest]."""

    def __init__(self, means, log_scales, quats, opacity_logits, sh_dc, sh_rest):
        super().__init__()
        for name, v in zip(PARAM_NAMES, (means, log_scales, quats, opacity_logits, sh_dc, sh_rest)):
            setattr(self, name, torch.nn.Parameter(v.detach().clone().float()))

    @property
    def sh(self) -> torch.Tensor:
        return torch.cat([self.sh_dc, self.sh_rest], 1)

    @property
    def num(self) -> int:
        return self.means.shape[0]

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):
        # checkpoints may hold a different number of splats: resize before loading
        for name in PARAM_NAMES:
            key = prefix + name
            if key in state_dict and state_dict[key].shape != getattr(self, name).shape:
                getattr(self, name).data = torch.empty_like(state_dict[key])
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)


def knn_mean_distance(points: torch.Tensor, k: int = 3) -> torch.Tensor:
    """(N,) mean distance of each point to its k nearest other points (shared exact kNN)."""
    n = points.shape[0]
    if n < 2:
        return torch.zeros(n, dtype=points.dtype, device=points.device)
    _, sq = knn(points, min(k, n - 1) + 1)  # the first neighbour is the point itself
    return sq[:, 1:].clamp_min(0).sqrt().mean(-1)


def init_from_points(points: torch.Tensor, colors: Optional[torch.Tensor] = None, sh_degree: int = 3,
                     opacity: float = 0.1) -> GaussianModel:
    """Isotropic Gaussians at ``points`` (N, 3): scale = mean distance to the 3 nearest
    neighbours, identity rotation, ``opacity``, DC colour ``colors`` (N, 3) or grey."""
    pts = points.float()
    n = pts.shape[0]
    dist = knn_mean_distance(pts).clamp_min(1e-7)
    rgb = colors.float() if colors is not None else torch.full((n, 3), 0.5)
    quats = torch.zeros(n, 4)
    quats[:, 0] = 1.0
    return GaussianModel(pts, torch.log(dist)[:, None].expand(n, 3), quats,
                         torch.full((n,), math.log(opacity / (1 - opacity))),
                         rgb_to_sh(rgb)[:, None, :], torch.zeros(n, 15, 3))


@torch.no_grad()
def colors_from_views(points: torch.Tensor, images: torch.Tensor, cams) -> torch.Tensor:
    """(N, 3) initial colour of each point: the median, over the views that see it in
    frame (in front of the camera), of the pixel it projects to. Occlusion is ignored; the
    median keeps the colour of the surface seen by most views. Points seen by no view: 0.5.

    points (N, 3) world; images (V, H, W, 3) in [0, 1]; cams: V cameras of that size.
    """
    V, H, W = images.shape[:3]
    out = torch.full((points.shape[0], 3), float("nan"), dtype=images.dtype, device=images.device)
    pix, z = cams.project(points.to(cams.R.dtype))                               # (V, N, 2), (V, N)
    col, row = pix[..., 0].floor().long(), pix[..., 1].floor().long()
    ok = (z > 0) & (col >= 0) & (col < W) & (row >= 0) & (row < H)
    flat = images.reshape(V, H * W, 3)
    idx = (row.clamp(0, H - 1) * W + col.clamp(0, W - 1))                        # (V, N)
    rgb = torch.gather(flat, 1, idx[..., None].expand(-1, -1, 3))                 # (V, N, 3)
    rgb = torch.where(ok[..., None], rgb, out[None])
    out = torch.nanmedian(rgb, dim=0).values
    return torch.nan_to_num(out, nan=0.5)


class DensityControl:
    """3DGS adaptive density control (clone / split / prune / opacity reset / cap).

    Args:
        scene_extent: world size used for "large" splats (3DGS: camera-sphere radius * 1.1).
        grad_threshold: mean NDC screen-space gradient norm above which a splat densifies.
        percent_dense: splats with max scale <= percent_dense * extent are cloned, others split.
        min_opacity: prune below this opacity.
        max_screen_size: prune splats with a 2D radius above this (pixels; 0 = off).
        max_world_scale: prune splats larger than this fraction of the extent (0 = off).
        max_gaussians: cap on the count (densification stops adding above it).
    """

    def __init__(self, scene_extent: float, grad_threshold: float = 2e-4, percent_dense: float = 0.01,
                 min_opacity: float = 0.005, max_screen_size: float = 0.0, max_world_scale: float = 0.1,
                 max_gaussians: int = 200_000):
        self.extent = float(scene_extent)
        self.grad_threshold = float(grad_threshold)
        self.percent_dense = float(percent_dense)
        self.min_opacity = float(min_opacity)
        self.max_screen_size = float(max_screen_size)
        self.max_world_scale = float(max_world_scale)
        self.max_gaussians = int(max_gaussians)
        self.grad_accum = self.count = self.max_radii = None

    def state_dict(self) -> Dict[str, Optional[torch.Tensor]]:
        """The accumulators (checkpointed so that a resumed run densifies identically)."""
        return {"grad_accum": self.grad_accum, "count": self.count, "max_radii": self.max_radii}

    def load_state_dict(self, state: Dict[str, Optional[torch.Tensor]]) -> None:
        for k in ("grad_accum", "count", "max_radii"):
            v = state.get(k)
            setattr(self, k, None if v is None else v.clone())

    def reset_stats(self, n: int, device) -> None:
        self.grad_accum = torch.zeros(n, device=device)
        self.count = torch.zeros(n, device=device)
        self.max_radii = torch.zeros(n, device=device)

    @torch.no_grad()
    def accumulate(self, means2d_grad: torch.Tensor, radii: torch.Tensor, width: int, height: int) -> None:
        """Add one step's screen-space gradients: means2d_grad (B, N, 2) px, radii (B, N) px."""
        n = means2d_grad.shape[1]
        if self.grad_accum is None or self.grad_accum.shape[0] != n:
            self.reset_stats(n, means2d_grad.device)
        scale = means2d_grad.new_tensor([0.5 * width, 0.5 * height])
        norm = (means2d_grad * scale).norm(dim=-1)
        vis = radii > 0
        self.grad_accum += (norm * vis).sum(0)
        self.count += vis.sum(0)
        self.max_radii = torch.maximum(self.max_radii, radii.max(0).values)

    @torch.no_grad()
    def densify_and_prune(self, model: GaussianModel, optimizer, generator=None, prune_screen: bool = False) -> Dict:
        """One densification round; returns counts {cloned, split, pruned, n}."""
        if self.grad_accum is None or self.grad_accum.shape[0] != model.num:
            return {"cloned": 0, "split": 0, "pruned": 0, "n": model.num}
        grads = self.grad_accum / self.count.clamp_min(1)
        max_scale = torch.exp(model.log_scales).max(-1).values
        high = grads >= self.grad_threshold
        room = max(0, self.max_gaussians - model.num)
        if int(high.sum()) > room // 2:                 # cap: keep the strongest only
            idx = torch.nonzero(high).reshape(-1)
            keep = idx[torch.argsort(grads[idx], descending=True)[: room // 2]]
            high = torch.zeros_like(high)
            high[keep] = True
        small = max_scale <= self.percent_dense * self.extent
        clone, split = high & small, high & ~small
        n0 = model.num
        # new splats: clones (same params), split children (2 per split, sampled inside)
        new = {name: [] for name in ("means", "log_scales", "quats", "opacity_logits", "sh_dc", "sh_rest")}
        ci = torch.nonzero(clone).reshape(-1)
        for name in new:
            new[name].append(getattr(model, name)[ci])
        si = torch.nonzero(split).reshape(-1)
        if si.numel():
            from l3d_app.render.gaussians import quaternion_to_rotation

            s = torch.exp(model.log_scales[si]).repeat(2, 1)
            noise = torch.randn(s.shape, generator=generator, device=s.device) if generator is None or \
                generator.device == s.device else torch.randn(s.shape, generator=generator).to(s.device)
            rot = quaternion_to_rotation(model.quats[si]).repeat(2, 1, 1)
            new["means"].append((rot @ (noise * s)[..., None])[..., 0] + model.means[si].repeat(2, 1))
            new["log_scales"].append(torch.log(s / 1.6))
            for name in ("quats", "opacity_logits", "sh_dc", "sh_rest"):
                new[name].append(getattr(model, name)[si].repeat(2, *([1] * (getattr(model, name).dim() - 1))))
        added = {k: torch.cat(v) for k, v in new.items()}
        n_add = added["means"].shape[0]
        # prune: split parents, transparent, too large
        opac = torch.sigmoid(model.opacity_logits)
        prune = split | (opac < self.min_opacity)
        if self.max_world_scale > 0:
            prune |= max_scale > self.max_world_scale * self.extent
        if prune_screen and self.max_screen_size > 0:
            prune |= self.max_radii > self.max_screen_size
        keep = torch.cat([~prune, torch.ones(n_add, dtype=torch.bool, device=prune.device)])
        _resize(model, optimizer, added, keep)
        self.reset_stats(model.num, model.means.device)
        return {"cloned": int(ci.numel()), "split": int(si.numel()), "pruned": int(prune.sum()), "n": model.num,
                "was": n0}

    @torch.no_grad()
    def reset_opacity(self, model: GaussianModel, optimizer, value: float = 0.01) -> None:
        """Clamp opacities to at most ``value`` (3DGS reset) and zero their Adam moments."""
        logit = math.log(value / (1 - value))
        model.opacity_logits.data.clamp_(max=logit)
        st = optimizer.state.get(model.opacity_logits, {})
        for k in ("exp_avg", "exp_avg_sq"):
            if k in st:
                st[k].zero_()


def _resize(model: GaussianModel, optimizer, added: Dict[str, torch.Tensor], keep: torch.Tensor) -> None:
    """Append ``added`` rows then keep rows ``keep``. Each resized tensor becomes a NEW
    ``Parameter`` (autograd caches leaf shapes), swapped into the optimiser's param group
    with its Adam moments carried over (zeros for new rows)."""
    for name in PARAM_NAMES:
        p = getattr(model, name)
        q = torch.nn.Parameter(torch.cat([p.data, added[name].to(p.dtype)])[keep].contiguous())
        st = optimizer.state.pop(p, None)
        if st:
            for k in ("exp_avg", "exp_avg_sq"):
                if k in st:
                    v = st[k]
                    st[k] = torch.cat([v, torch.zeros((added[name].shape[0], *v.shape[1:]), dtype=v.dtype,
                                                      device=v.device)])[keep].contiguous()
            optimizer.state[q] = st
        for g in optimizer.param_groups:
            g["params"] = [q if x is p else x for x in g["params"]]
        setattr(model, name, q)
