"""sds_nerf: text-to-3D in the DreamFusion manner, at low resolution.

Model: the fast radiance field of ``train_nerf`` (``model=grid_field``: multi-resolution grid
+ small MLP) over the box [-1, 1]^3, its density multiplied by a Gaussian *blob*
``exp(blob_density * exp(-|x|^2 / (2 blob_radius^2)))`` (for the exp activation this adds the
blob to the raw density, as DreamFusion does), so optimisation starts from a soft ball.

Each step renders ``batch_views`` random orbit cameras at ``image_size`` pixels (0: the
prior's image size, at most 64; renders are resized to the prior's size before encoding)
by volume rendering (ray-box segments, stratified samples,
:func:`~l3d_app.render.volume.radiance.render_field_rays`), with a shading drawn at random
(``shading_probs``):

* ``albedo``: the field's colour;
* ``lambertian``: ``albedo * (ambient + (1 - ambient) max(0, n . l))``;
* ``textureless``: the same with a white albedo (geometry only);
* ``normal``: ``(n + 1) / 2``;

with ``n = -grad sigma / |grad sigma|`` (autograd, differentiable) and a light ``l`` near
the camera (the direction to the camera plus a random offset of size ``light_jitter``).

Guidance: SDS (:func:`~l3d_app.losses.sds.sds_loss`) under the prompt embedding of each
view (:class:`~l3d_app.diffusion.view_prompts.ViewPrompts`: front / side / back blended by
azimuth, overhead / bottom by elevation; on by default for Stable Diffusion, off for the
built-in prior, whose vocabulary has no view words and whose shapes are flat).
Regularisers (:mod:`l3d_app.losses.nerf_regularizers`), both scaled by the number of
model-space pixels ``h w`` so that their weights are per pixel, like the SDS gradient (which
acts on every model-space element): ``lambda_entropy`` x the mean binary entropy of the ray
opacities and ``lambda_orient`` x the mean over rays of ``sum_i w_i max(0, n_i . d)^2``
(Ref-NeRF orientation), the latter applied on the steps that compute
normals (every shading but ``albedo``, which skips the normals' double backward: about half
the cost of a step). An :class:`~l3d_app.render.volume.occupancy.OccupancyGrid` (``occupancy.*``,
started from the blob's extent) skips samples in empty cells.

Latent iterations (``latent_iter_ratio``): with a latent prior (Stable Diffusion, or the
built-in prior with ``space=latent``), the first ``latent_iter_ratio * iters`` steps skip the
encoder: the field is rendered directly at the latent resolution as 4 channels, the
composited normals (3, in [-1, 1]) and ``2 * opacity - 1``, and that image is used as the
latent (Latent-NeRF / Fantasia3D's geometry warm-up; needs a 4-channel latent space). With
a pixel-space prior there is no latent space and no encoder to skip: the knob has no effect
(every step renders RGB at the prior's resolution) and ``latent_iters`` is 0.

Outputs: ``sds_nerf.gif`` (turntable: albedo colour | textureless | depth, white = near),
``metrics.json`` (match rate of the albedo turntable by the prompt checker, opacity,
entropy, orientation, seconds, seconds per iteration), TensorBoard scalars and the front
view over iterations.
"""

from __future__ import annotations

import math
from typing import Dict

import torch


from l3d_app.diffusion.registry import PRIORS
from l3d_app.diffusion.view_prompts import VIEWS, ViewPrompts, check_orbit_ranges, sample_orbit_cameras
from l3d_app.errors import UserError
from l3d_app.geometry.camera_paths import turntable
from l3d_app.geometry.cameras import Cameras
from l3d_app.losses.nerf_regularizers import density_normals, opacity_entropy, orientation_penalty
from l3d_app.losses.sds import rgb_to_model_space, sds_loss
from l3d_app.metrics.prompt_match import score_frames, score_metrics
from l3d_app.models.blob_field import BlobField
from l3d_app.registry import MODELS, SAMPLERS, TASKS
from l3d_app.render.evaluation import depth_picture
from l3d_app.render.volume.field_shading import (SCENE_BOX, SHADINGS, normals_as_latent, render_shaded_views,
                                          shading_sampler)
from l3d_app.runtime.budget import TimeBudget
from l3d_app.runtime.config_values import config_floats
from l3d_app.runtime.media import save_gif, save_png
from l3d_app.runtime.optim import build_optimizer
from l3d_app.runtime.random import randn
from l3d_app.runtime.training import Trainable, train
from l3d_app.tasks.common import loop_spec, require_positive



def _view_dependent(cfg) -> bool:
    value = str(cfg.view_dependent).lower()
    if value == "auto":
        return str(cfg.prior.name) != "builtin"
    if value in ("true", "false"):
        return value == "true"
    raise UserError(f"view_dependent must be auto, true or false, got {cfg.view_dependent!r}")


@TASKS.register("sds_nerf")
def sds_nerf(cfg, ctx) -> dict:
    """Optimise the field by SDS with shading, view prompts and regularisers; write gifs/metrics."""
    require_positive(cfg, "iters", "lr", "batch_views", "n_samples", "num_frames", "fps", "chunk", "eval_every")
    if not 0.0 <= float(cfg.latent_iter_ratio) <= 1.0:
        raise UserError(f"latent_iter_ratio must be in [0, 1], got {cfg.latent_iter_ratio}")
    if not 0.0 <= float(cfg.ambient) <= 1.0:
        raise UserError(f"ambient must be in [0, 1], got {cfg.ambient}")
    check_orbit_ranges(distance=cfg.distance_range, elevation=cfg.elevation_range, fov=cfg.fov_range)
    bg = config_floats(cfg.background, "background", 3)
    prior = PRIORS.build(cfg.prior, device=ctx.device)
    prompt = str(cfg.prompt)
    overrides = {str(k): str(v) for k, v in dict(cfg.get("view_prompts") or {}).items() if v}
    views = ViewPrompts.build(prior, prompt, _view_dependent(cfg), str(cfg.view_template), overrides,
                              float(cfg.overhead_deg))
    latent_iters = 0
    if prior.is_latent:
        latent_iters = int(math.floor(float(cfg.latent_iter_ratio) * int(cfg.iters)))
        if latent_iters > 0 and prior.latent_shape[0] != 4:
            raise UserError(f"latent_iter_ratio > 0 needs a 4-channel latent prior, this one has "
                            f"{prior.latent_shape[0]} channels; set latent_iter_ratio=0")
    size = int(cfg.image_size) if int(cfg.image_size) > 0 else min(int(prior.image_size), 64)
    base = MODELS.build(cfg.model, scene_box=[list(SCENE_BOX[0]), list(SCENE_BOX[1])])
    field = BlobField(base, float(cfg.blob_density), float(cfg.blob_radius)).to(ctx.device)
    n_params = sum(p.numel() for p in field.parameters())
    draw_shading = shading_sampler(dict(cfg.shading_probs))
    render_kw = dict(n_samples=int(cfg.n_samples), background=bg, ambient=float(cfg.ambient),
                     normals_fn=density_normals, penalty_fn=orientation_penalty)
    ranges = {k: list(cfg[k]) for k in ("distance_range", "elevation_range", "fov_range")}
    lam_e, lam_o = float(cfg.lambda_entropy), float(cfg.lambda_orient)
    opt, scheds = build_optimizer(cfg.optim, field.parameters(), int(cfg.iters))
    sampler = SAMPLERS.build(cfg.sampler, scene_box=SCENE_BOX).to(ctx.device)
    sampler.update(0, field, ctx.generator)          # an occupancy grid starts from the blob's extent
    render_kw["estimator"] = sampler
    trainable = Trainable({"field": field}, opt, extra={"sampler": sampler}, schedulers=scheds)
    gen = ctx.generator

    def step_fn(step: int) -> Dict[str, torch.Tensor]:
        sampler.update(step, field, gen)
        latent = step < latent_iters
        side = prior.latent_shape[-1] if latent else size
        cams, azim, elev = sample_orbit_cameras(int(cfg.batch_views), side, gen, distance=ranges["distance_range"],
                                                elevation=ranges["elevation_range"], fov=ranges["fov_range"],
                                                device=ctx.device)
        shading = "normal" if latent else draw_shading(gen)
        offset = float(cfg.light_jitter) * randn((3,), gen, ctx.device)
        out = render_shaded_views(field, cams, shading, light_offset=offset, training=True, generator=gen,
                           need_normals=latent or (lam_o > 0 and shading != "albedo"), **render_kw)
        x = normals_as_latent(out) if latent else rgb_to_model_space(prior, out["image"], channels_last=True)
        sds = sds_loss(prior, x, views.embedding(azim, elev), float(cfg.guidance_scale), float(cfg.t_min),
                       float(cfg.t_max), generator=gen, on_nonfinite="flag")
        entropy = opacity_entropy(out["opacity"])
        orient = out["orient"].mean()
        pixels = x.shape[-1] * x.shape[-2]       # regularisers on the per-pixel scale of the SDS gradient
        return {"loss": sds.loss + pixels * (lam_e * entropy + lam_o * orient), "sds": sds.loss.detach(),
                "entropy": entropy.detach(), "orient": orient.detach(),
                "opacity": out["opacity"].mean().detach(), "latent": torch.tensor(float(latent)),
                "shading": torch.tensor(float(SHADINGS.index(shading)))}

    cams_360 = turntable(int(cfg.num_frames), float(cfg.eval_distance), float(cfg.eval_elevation),
                         float(cfg.eval_fov), int(cfg.turntable_size) or size, device=ctx.device)
    # the periodic check's own views, half a turntable step off its frames: the final match rate
    # (read once, on the turntable) is not the figure the run was watched by
    cams_val = turntable(min(int(cfg.eval_views), int(cfg.num_frames)), float(cfg.eval_distance),
                         float(cfg.eval_elevation), float(cfg.eval_fov), int(cfg.turntable_size) or size,
                         device=ctx.device, azimuth_offset=180.0 / int(cfg.num_frames))

    def render_turntable(cams: Cameras, shading: str) -> Dict[str, torch.Tensor]:
        return {k: v.detach() for k, v in render_shaded_views(field, cams, shading, chunk=int(cfg.chunk),
                                                       need_normals=False, **render_kw).items()}

    def eval_fn(step: int) -> Dict[str, float]:
        out = render_turntable(cams_val, "albedo")
        ctx.logger.image("sds_nerf/front", out["image"][0].clamp(0, 1), step)
        rate = score_frames(out["image"].clamp(0, 1), prompt)["match"]
        return {"opacity": float(out["opacity"].mean()), **({} if rate is None else {"match_rate": rate})}

    with ctx.stopwatch.stage("train"):
        budget = TimeBudget.of(ctx).keep_renders(2 * len(cams_360), len(cams_val))  # the turntable, albedo and textureless
        result = train(ctx, trainable, step_fn, loop_spec(cfg, "sds_nerf"), eval_fn=eval_fn, budget=budget)
    with ctx.stopwatch.stage("render"):
        colour = render_turntable(cams_360, "albedo")
        plain = render_turntable(cams_360, "textureless")
    frames = torch.cat([colour["image"].clamp(0, 1), plain["image"].clamp(0, 1),
                        depth_picture(colour["depth"], colour["opacity"])], dim=2)
    if not bool(torch.isfinite(frames).all()):
        raise UserError("the optimised field rendered non-finite values")
    save_gif(ctx.path("sds_nerf.gif"), frames, fps=float(cfg.fps))
    save_png(ctx.path("views.png"), torch.cat(list(frames[:: max(1, len(frames) // 4)][:4]), dim=0))
    ctx.logger.image_sequence("sds_nerf/turntable", frames)
    return {
        "prompt": prompt,
        "prior": str(cfg.prior.name),
        "view_prompts": dict(zip(VIEWS, views.prompts)),
        **score_metrics(score_frames(colour["image"].clamp(0, 1), prompt)),
        "opacity": round(float(colour["opacity"].mean()), 5),
        "opacity_entropy": round(float(opacity_entropy(colour["opacity"])), 5),
        "orientation": round(float(plain["orient"].mean()), 6),
        "guidance_scale": float(cfg.guidance_scale),
        "latent_iters": min(latent_iters, result.step),
        **{k: round(v, 5) for k, v in sampler.stats().items()},
        "iters": result.step,
        "n_params": n_params,
        "image_size": size,
        "turntable_size": int(cfg.turntable_size) or size,
        "train_seconds": round(result.train_seconds, 4),   # steps only, resumed parts included
        "seconds_per_iter": round(result.seconds_per_step, 5),
        "skipped_steps": result.skipped_steps,
        "history": result.history_rows(),
        "interrupted": result.interrupted,
    }
