"""sds_mesh: paint a fixed mesh from a text prompt by score distillation (SDS).

Model: a texture *field* (:class:`~l3d_app.models.texture_field.TextureField`), ``rgb = sigmoid(MLP(harmonic(p)))`` of the surface point ``p``
(world units), so the texture has no UV seams and its resolution does not depend on the
mesh's vertex density. Rendering: the hard rasteriser of ``renderer=mesh`` (visibility is
fixed, the mesh does not move) with the field evaluated at every covered pixel's
interpolated surface point (:class:`~l3d_app.render.mesh.field_texture.FieldTextureRenderer`); shading ``unlit`` (flat colour,
like the built-in prior's images) or ``lambert``/``phong`` with a headlight. Only the
field's parameters are trained; gradients reach them through the per-pixel albedo.

Each step renders ``batch_views`` random cameras on an orbit
(:func:`~l3d_app.diffusion.view_prompts.sample_orbit_cameras`), maps the renders to the
prior's model space and applies :func:`~l3d_app.losses.sds.sds_loss` (CFG, w(t) = 1 -
abar_t, target trick; a non-finite SDS gradient makes the shared loop skip the step).

Measured: every turntable frame (before and after) is scored by the independent prompt
checker (:mod:`l3d_app.metrics.prompt_match`, the built-in prior's vocabulary);
``metrics.json`` has the match rates before/after, per-slot rates, seconds and
seconds per iteration. Outputs: ``sds_mesh.gif`` (turntable, before | after),
``after.png`` (the frames), TensorBoard scalars and the front view over iterations.
"""

from __future__ import annotations

from typing import Dict

import torch

from l3d_app.diffusion.view_prompts import check_orbit_ranges, sample_orbit_cameras
from l3d_app.errors import UserError
from l3d_app.geometry.camera_paths import turntable
from l3d_app.geometry.mesh import Mesh
from l3d_app.losses.sds import rgb_to_model_space, sds_loss
from l3d_app.metrics.prompt_match import score_frames, score_metrics
from l3d_app.models.texture_field import TextureField
from l3d_app.registry import DATASETS, TASKS
from l3d_app.render.evaluation import render_frames
from l3d_app.render.mesh.field_texture import FieldTextureRenderer
from l3d_app.runtime.media import save_gif, save_png
from l3d_app.runtime.training import Trainable, train
from l3d_app.tasks.common import loop_spec, require_positive
from l3d_app.tasks.prior_common import load_prior

__all__ = ["sds_mesh", "load_prior", "score_frames", "score_metrics"]  # the last three: sds_nerf's old import path


@TASKS.register("sds_mesh")
def sds_mesh(cfg, ctx) -> dict:
    """Optimise the texture field with SDS; score turntables before and after; write gif/metrics."""
    require_positive(cfg, "iters", "lr", "batch_views", "num_frames", "fps", "eval_every", "batch_frames")
    check_orbit_ranges(distance=cfg.distance_range, elevation=cfg.elevation_range, fov=cfg.fov_range)
    mesh = DATASETS.build(cfg.data, device=ctx.device)
    if not isinstance(mesh, Mesh):
        raise UserError("sds_mesh needs a mesh data source (data=cube, data=mesh data.path=FILE, ...)")
    prior = load_prior(cfg, ctx.device)
    prompt = str(cfg.prompt)
    embedding = prior.embed_prompt(prompt)
    size = int(cfg.image_size) if int(cfg.image_size) > 0 else int(prior.image_size)
    field = TextureField(int(cfg.field.n_frequencies), int(cfg.field.hidden), int(cfg.field.layers)).to(ctx.device)
    renderer = FieldTextureRenderer(field, shading=str(cfg.shading), background=list(cfg.background),
                                    antialias=int(cfg.antialias))
    dist_range, elev_range, fov_range = (list(cfg[k]) for k in ("distance_range", "elevation_range", "fov_range"))
    cams_360 = turntable(int(cfg.num_frames), float(cfg.eval_distance), float(cfg.eval_elevation),
                         float(cfg.eval_fov), int(cfg.turntable_size) or size, device=ctx.device)
    # the periodic check's own views, half a turntable step off its frames: the final match rate
    # (read once, on the turntable) is not the figure the run was watched by
    cams_val = turntable(min(int(cfg.eval_views), int(cfg.num_frames)), float(cfg.eval_distance),
                         float(cfg.eval_elevation), float(cfg.eval_fov), int(cfg.turntable_size) or size,
                         device=ctx.device, azimuth_offset=180.0 / int(cfg.num_frames))
    n_params = sum(p.numel() for p in field.parameters())

    def render_turntable(desc: str) -> torch.Tensor:
        return render_frames(renderer, mesh, cams_360, int(cfg.batch_frames), desc=desc, keys=("image",))["image"]

    with ctx.stopwatch.stage("render"):
        before = render_turntable("render before")
    score_before = score_frames(before, prompt)

    opt = torch.optim.Adam(field.parameters(), lr=float(cfg.lr))
    trainable = Trainable({"texture": field}, opt)

    def step_fn(step: int) -> Dict[str, torch.Tensor]:
        cams, _, _ = sample_orbit_cameras(int(cfg.batch_views), size, ctx.generator, distance=dist_range,
                                          elevation=elev_range, fov=fov_range, device=ctx.device)
        images = renderer(mesh, cams)["image"]                           # (B, H, W, 3)
        x = rgb_to_model_space(prior, images, channels_last=True)
        out = sds_loss(prior, x, embedding, float(cfg.guidance_scale), float(cfg.t_min), float(cfg.t_max),
                       generator=ctx.generator, on_nonfinite="flag")
        return {"loss": out.loss, "sds_grad_norm": torch.tensor(out.grad_norm),
                "t": out.t.float().mean()}

    def eval_fn(step: int) -> Dict[str, float]:
        frames = renderer(mesh, cams_val)["image"]
        ctx.logger.image("sds_mesh/front", frames[0], step)
        rate = score_frames(frames, prompt)["match"]
        return {} if rate is None else {"match_rate": rate}

    with ctx.stopwatch.stage("train"):
        result = train(ctx, trainable, step_fn, loop_spec(cfg, "sds_mesh"), eval_fn=eval_fn)
    with ctx.stopwatch.stage("render"):
        after = render_turntable("render after")
    score_after = score_frames(after, prompt)
    frames = torch.cat([before, after], dim=2)
    save_gif(ctx.path("sds_mesh.gif"), frames, fps=float(cfg.fps))
    save_png(ctx.path("after.png"), torch.cat(list(after[: min(int(cfg.png_frames), len(after))]), dim=1))
    ctx.logger.image_sequence("sds_mesh/turntable", frames)
    if not bool(torch.isfinite(after).all()):
        raise UserError("the optimised texture rendered non-finite values")
    return {
        "prompt": prompt,
        "prior": str(cfg.prior.name),
        **score_metrics(score_after),
        "match_rate_before": score_before["match"],
        "guidance_scale": float(cfg.guidance_scale),
        "iters": result.step,
        "n_params": n_params,
        "train_seconds": round(result.train_seconds, 4),   # steps only, resumed parts included
        "seconds_per_iter": round(result.seconds_per_step, 5),
        "image_size": size,
        "turntable_size": int(cfg.turntable_size) or size,
        "skipped_steps": result.skipped_steps,
        "history": result.history_rows(),
        "interrupted": result.interrupted,
    }

