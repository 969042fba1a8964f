"""Training losses of the single-view-reconstruction decoders (:mod:`l3d_app.models.svr_decoders`,
:mod:`l3d_app.models.svr_pseudo`).

The decoders are plain networks; what supervises each one lives here, so models import no
loss, metric or data module. :func:`svr_loss` picks the loss by the decoder's ``kind``:

* ``vox``: BCE on logits against the (B, R, R, R) voxel grid (``pos_weight`` of the decoder);
* ``point``: chamfer between the (B, N, 3) points and ``target_points`` surface samples;
* ``mesh``: chamfer between ``num_samples`` area-uniform samples of the predicted meshes and
  as many surface samples, plus ``w_smooth`` x uniform Laplacian smoothing;
* ``implicit``: BCE on logits at ``queries`` of the stored labelled query points;
* ``pseudo``: 2D supervision only (Lin et al. 2018): the fused cloud is pseudo-rendered into
  ``views_per_step`` random supervision cameras per object; ``w_mask`` x BCE(mask logits,
  silhouette) + ``w_depth`` x L1(depth) over pixels both the truth and the render cover.

``batch`` holds what :func:`l3d_app.pipelines.svr.make_batch` gives: images (B, H, W, 3),
points (B, P, 3), voxels (B, R, R, R), occ_points (B, Q, 3), occ_labels (B, Q), depth
(B, S, H, W) and the S depth_cameras. Random draws use ``generator`` (a CPU generator,
drawn on the CPU and moved: :mod:`l3d_app.runtime.random`).
"""

from __future__ import annotations

from typing import Callable, Dict, Optional

import torch

from l3d_app.geometry.cameras import Cameras
from l3d_app.losses.mesh_regularizers import laplacian_smoothing
from l3d_app.losses.occupancy import bce_with_logits
from l3d_app.metrics.chamfer import chamfer_distance_batched
from l3d_app.render.points.pseudo import pseudo_render
from l3d_app.runtime.random import rand

Logs = Dict[str, torch.Tensor]


def subsample(points: torch.Tensor, n: int, generator: Optional[torch.Generator]) -> torch.Tensor:
    """(B, M, D) -> (B, n, D): a random subset (without replacement) per batch element."""
    if n >= points.shape[1]:
        return points
    keys = rand(points.shape[:2], generator, points.device)
    idx = keys.argsort(dim=1)[:, :n]
    return torch.gather(points, 1, idx[..., None].expand(-1, -1, points.shape[-1]))


def _chamfer(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Mean over the batch of the (B, N, 3) vs (B, M, 3) chamfer; one block of all N rows (the
    default block pads a small set up to ~2M distances, which dominates the step for N ~ 1000)."""
    return chamfer_distance_batched(pred, target, chunk_size=int(pred.shape[1])).mean()


def vox_loss(decoder, feature, batch, generator=None) -> Logs:
    bce = bce_with_logits(decoder(feature), batch["voxels"].float(), decoder.pos_weight)
    return {"loss": bce, "bce": bce}


def point_loss(decoder, feature, batch, generator=None) -> Logs:
    target = subsample(batch["points"], decoder.target_points, generator)
    chamfer = _chamfer(decoder(feature), target)
    return {"loss": chamfer, "chamfer": chamfer}


def mesh_loss(decoder, feature, batch, generator=None) -> Logs:
    verts = decoder(feature)
    samples = decoder.sample(verts, decoder.num_samples, generator)
    chamfer = _chamfer(samples, subsample(batch["points"], decoder.num_samples, generator))
    B, V = verts.shape[:2]
    # the Laplacian is linear per coordinate: all B meshes at once as (V, B*3) columns
    smooth = laplacian_smoothing(verts.permute(1, 0, 2).reshape(V, B * 3), decoder.faces) / B
    return {"loss": decoder.w_chamfer * chamfer + decoder.w_smooth * smooth, "chamfer": chamfer,
            "laplacian": smooth}


def implicit_loss(decoder, feature, batch, generator=None) -> Logs:
    pts = batch["occ_points"]
    both = torch.cat([pts, batch["occ_labels"][..., None].to(pts.dtype)], -1)
    pick = subsample(both, decoder.queries, generator)
    bce = bce_with_logits(decoder(feature, pick[..., :3]), pick[..., 3], decoder.pos_weight)
    return {"loss": bce, "bce": bce}


def pseudo_render_cloud(points: torch.Tensor, logits: torch.Tensor, cams: Cameras, upsample: int) -> Logs:
    """Pseudo-render clouds (B, N, 3) with mask logits (B, N) into B cameras: depth, covered
    (the foreground z-buffer) and mask_logits (B, H, W). Only foreground points (logit > 0)
    are z-buffered; a pixel's mask logit is its nearest foreground point's, else its nearest
    background point's (so wrongly dropped points can come back), else -1 (no gradient)."""
    fg = logits.detach() > 0
    lg = logits[..., None]
    front = pseudo_render(points, cams, upsample, values=lg, active=fg)
    back = pseudo_render(points, cams, upsample, values=lg, active=~fg)
    mask = torch.where(front["covered"], front["values"][..., 0],
                       torch.where(back["covered"], back["values"][..., 0], torch.full_like(front["depth"], -1.0)))
    return {"depth": front["depth"], "covered": front["covered"], "mask_logits": mask}


def pseudo_loss(decoder, feature, batch, generator=None) -> Logs:
    out = decoder(feature)
    B, S = batch["depth"].shape[:2]
    s = min(decoder.views_per_step, S)
    views = rand((B, S), generator, feature.device).argsort(dim=1)[:, :s]      # (B, s)
    cams: Cameras = batch["depth_cameras"][views.reshape(-1)]
    gt = torch.gather(batch["depth"], 1, views[..., None, None].expand(-1, -1, *batch["depth"].shape[2:]))
    gt = gt.reshape(B * s, *gt.shape[2:])
    gt_mask = gt > 0
    pts = out["points"].repeat_interleave(s, dim=0)
    lg = out["mask_logits"].reshape(B, -1).repeat_interleave(s, dim=0)
    r = pseudo_render_cloud(pts, lg, cams, decoder.upsample)
    mask_loss = bce_with_logits(r["mask_logits"], gt_mask.float())
    both = gt_mask & r["covered"]
    depth_loss = ((r["depth"] - gt).abs() * both).sum() / both.sum().clamp_min(1)
    return {"loss": decoder.w_mask * mask_loss + decoder.w_depth * depth_loss, "mask_bce": mask_loss,
            "depth_l1": depth_loss, "foreground": (lg > 0).float().mean()}


LOSSES_BY_KIND: Dict[str, Callable[..., Logs]] = {
    "vox": vox_loss, "point": point_loss, "mesh": mesh_loss, "implicit": implicit_loss, "pseudo": pseudo_loss}


def svr_loss(decoder, feature: torch.Tensor, batch: Dict, generator: Optional[torch.Generator] = None) -> Logs:
    """The training loss of ``decoder`` (its ``kind``) for image features (B, latent):
    ``{"loss": scalar, other logs...}``."""
    kind = getattr(decoder, "kind", None)
    if kind not in LOSSES_BY_KIND:
        raise TypeError(f"no SVR loss for decoder kind {kind!r}; known: {', '.join(LOSSES_BY_KIND)}")
    return LOSSES_BY_KIND[kind](decoder, feature, batch, generator)
