"""volsdf: a neural SDF + colour network trained from posed images by SDF volume rendering.

``python main.py task=volsdf beta=0.1`` (``density=auto``, default: NeuS where a quarter or more of the
training cameras look from below the scene, VolSDF otherwise, :mod:`~l3d_app.render.sdf.density_choice`;
``alpha``/``beta`` at the top level), ``density=volsdf`` or ``density=neus s=64``. Pieces:

* model (``model=sdf_grid_field``, default): :class:`~l3d_app.models.sdf_grid.SDFGridField`,
  a multi-resolution grid (table near zero) + small MLP initialised to a sphere of
  ``model.radius`` and pretrained to it (MLP only) for ``pretrain_steps``; its exact spatial
  gradient (no double backward) feeds the colour network (normal) and the eikonal loss. Grid
  levels are switched on coarse to fine: ``levels_start`` levels, one more every
  ``level_every`` steps. ``model=sdf_field`` is the slower harmonic-MLP alternative.
* density: VolSDF ``sigma = alpha * Psi_beta(-f)`` (:class:`~l3d_app.render.sdf.densities.LaplaceDensity`).
  ``beta`` is the initial value: ``beta_mode=anneal`` (default) takes it geometrically to
  ``beta_end`` over ``anneal_fraction`` of the steps, ``beta_mode=learnable`` trains it with
  the field (floor ``beta_min``), ``beta_mode=fixed`` keeps it. ``alpha=null`` (default) ties
  ``alpha = 1/beta`` (VolSDF), a number fixes it. NeuS: ``density=neus`` with fixed ``s``; under
  ``density=auto`` NeuS takes ``s = 1/beta`` and the same schedule.
  Why ``beta_end`` is small: a ray that passes a convex surface at distance ``h`` (curvature
  radius ``R``) accumulates optical depth ``exp(-h/beta) sqrt(pi R / (2 beta))`` (alpha = 1/beta),
  so silhouettes appear ``beta ln(sqrt(pi R / (2 beta)) / ln 2)`` OUTSIDE the zero level set and
  the learned surface shrinks by that much to match the images (0.023 on the 0.28 sphere at
  beta 0.01, measured 0.023-0.026).
  ``density_along_ray=true`` reads ``f / |n . d|`` instead (the distance to the surface along the ray,
  :func:`~l3d_app.render.sdf.densities.distance_along_ray`): the transition in ``t`` is the same at every angle,
  so the silhouettes no longer sit outside the zero level set (option; docs/measured/volsdf.md).
* sampling only near the surface: a trilinear :class:`~l3d_app.render.sdf.volume.SDFGridCache`
  of the SDF (``cache_resolution``^3, refreshed every ``cache_every`` steps, from ``cache_late_from`` on every
  ``cache_late_every`` when set; no grad) gives
  ``n_coarse`` look-ups per ray whose VolSDF weights place ``n_fine`` field samples at the
  zero level set (:func:`~l3d_app.render.sdf.volume.render_sdf_rays`); metrics report both
  counts (``samples_per_ray``, ``fine_samples_per_ray``). Evaluation renders put 8 of them at the
  field's own first zero crossing once ``beta`` is below what the cache resolves
  (``sampler.eval_anchor``, ``sampler.anchor_when=narrow``).
* loss: colour MSE + ``w_eikonal`` x eikonal loss at the fine samples and at
  ``eikonal_points`` random box points (+ ``w_free`` x an occupied-volume prior at the same box points, default off:
  :func:`~l3d_app.losses.free_space.occupied_volume`, or with ``free_softness`` > 0
  :func:`~l3d_app.losses.free_space.occupied_fraction`), through the shared
  :func:`~l3d_app.runtime.training.train` loop (evaluation, checkpoints, ``resume=true``);
  ``optim=warmup_cosine`` (Adam eps 1e-15, ``warmup_steps`` linear warm-up, ``auto``: 150 steps with NeuS, 50
  with VolSDF (:data:`WARMUP_STEPS_AUTO`), then cosine decay to ``lr * lr_final_ratio``).
  ``pixel_jitter=true`` sends each training ray through a random point of its pixel.
* multi-view patch consistency (``ncc.*``, Geo-NeuS's NCC): each training ray's first zero crossing and
  normal warp its grey patch into the nearest training views
  (:class:`~l3d_app.losses.patch_consistency.PatchConsistency`); ``ncc.weight`` x (1 - NCC) / 2, falling
  linearly to 0 at ``ncc.until`` of the steps (patches assume surfaces that look alike from nearby views:
  kept to the end it hurt a glossy development scene; docs/measured/volsdf.md).
* known free space (``free_space.steps``: ``auto`` = 600 steps with either density): a short radiance-field fit first
  (:mod:`~l3d_app.tasks.free_space_common`) marks, on each training ray, the stretch before its
  opacity reaches ``free_space.opacity`` (less ``free_space.margin``, and less ``free_space.margin_beta``
  x the current beta); each step adds
  ``free_space.weight`` x a loss at ``free_space.points`` points drawn on those stretches (uniformly,
  or with ``free_space.proposal=surface`` importance-resampled near the surface, the same expectation; what a
  ray passes through before any surface is empty; :func:`~l3d_app.losses.free_space.free_stretch_loss`), the weight falling
  linearly to 0 at ``free_space.until`` x iters when that is set; ``free_space.ray_weight`` (0.03; 0: off) adds
  that weight x the batch mean of the render's opacity before each ray's own stretch end (the same shortening;
  :func:`~l3d_app.losses.free_space.opacity_before`; a ray the images' alpha covers on which the radiance field
  never became opaque makes no claim; ``free_space.ray_margin_beta``, when set, replaces ``margin_beta`` for it
  and ``free_space.ray_margin`` ``margin``; ``free_space.ray_loss=log_depth`` takes ``log(1 + tau)`` of that
  opacity's optical depth instead (:func:`~l3d_app.losses.free_space.log_depth`: no saturation behind a lid);
  with ``free_space.ray_cut=multi_view`` an end is cut back where another training view's stretch stops in front
  of it: :meth:`~l3d_app.render.volume.free_space.FreeRays.multi_view_cut`). With a ``time_budget`` the stage
  gets at most half of what the budget leaves after the final work predicted from the timed "before"
  validation (:func:`~l3d_app.tasks.free_space_common.stage_deadline`), and is skipped (logged,
  ``free_space_skipped`` in the metrics) where that is under 90 s: at 256 px the test views cost
  too much for both.
* evaluation renders average ``supersample``^2 rays per pixel (the images are SSAA renders).

Evaluation: every ``eval_every`` steps on the VALIDATION views (PSNR / SSIM and a
``pred | truth | error | depth`` picture in TensorBoard); the TEST views are rendered once at the
end (``psnr``, ``ssim``; ``val_*`` the last validation). ``time_budget`` > 0: wall seconds
for the whole task, ``reserve`` of them kept for the mesh and its scores at ``mesh_resolution`` 128 (at
another resolution the grid's extra points are priced by the SDF's measured cost:
:meth:`~l3d_app.runtime.budget.TimeBudget.keep_mesh`; the test views are
reserved from the measured evaluation time; the gifs come last with the frames that still fit,
:func:`~l3d_app.render.previews.write_turntables`); when the budget stops training before ``iters``,
the LR, beta anneal and level schedules follow the loop's prediction of its last step
(:class:`~l3d_app.runtime.horizon.Horizon`), so the run still ends annealed. A marching-cubes mesh of the SDF's zero level set, scored
against the ground-truth surface when the data carries one (``data.mesh``; the built-in scene) by
:func:`~l3d_app.metrics.surface_scores.surface_scores`: ``chamfer`` = mean accuracy + mean
completeness, EXACT point-to-mesh distances of ``eval_points`` samples of each surface
(world units, not squared), ``chamfer_rel_diag`` the same over the true mesh's
bounding-box diagonal, ``f1`` / ``precision`` / ``recall`` at ``f1_threshold`` (0.05); the
``*_observed`` variants score only the true surface the TRAINING cameras see (and the
predicted surface nearest to it), ``observed_fraction`` its share of the true area.
Outputs: ``render.gif`` (360 colour | depth) and ``geometry.gif`` (sphere-traced shading of the SDF),
both orbiting the data's up axis; ``mesh.<fmt>`` (``mesh_formats``, vertex colours from the colour
network looking along -normal; with ``mesh_cull`` only the faces some training camera sees, the
whole level set in ``mesh_uncut.ply``, ``mesh_culled_area`` the share of area removed; the
surface scores are of the culled mesh); ``test_views.png``; ``metrics.json``.
"""

from __future__ import annotations

import time
from typing import Callable, Dict, Tuple

import torch
from omegaconf import OmegaConf

from l3d_app.errors import UserError
from l3d_app.geometry.rays import camera_rays, pixel_axes
from l3d_app.losses.eikonal import eikonal_loss, sdf_gradient
from l3d_app.losses.free_space import (fade_to_zero, free_stretch_loss, occupied_fraction, occupied_volume,
                                       log_depth, opacity_before)
from l3d_app.losses.occupancy import coverage_bce
from l3d_app.losses.patch_consistency import PatchConsistency, surface_crossing
from l3d_app.metrics.surface_scores import surface_scores
from l3d_app.models.background import background_parameter
from l3d_app.models.level_schedule import LevelSchedule
from l3d_app.models.sdf_gradients import field_with_gradient
from l3d_app.models.sdf_grid import pretrain_field
from l3d_app.pipelines.views import BeforeAfter, evaluate_views
from l3d_app.registry import DATASETS, DENSITIES, MODELS, SAMPLERS, TASKS
from l3d_app.render.sdf.density_choice import candidate_configs, choose_density
from l3d_app.render.sdf.densities import transition_width
from l3d_app.render.evaluation import render_views
from l3d_app.render.field_mesh import extract_mesh, save_field_mesh, seconds_per_grid_point
from l3d_app.render.volume.free_space import near_surface_weight
from l3d_app.render.mesh.rgbd import true_depth_maps
from l3d_app.render.mesh.visibility import cull_to_training_views
from l3d_app.render.sdf.volume import render_sdf_rays
from l3d_app.render.sdf.sphere_tracing import render_sdf_shaded
from l3d_app.render.turntable import color_depth_frames
from l3d_app.runtime.budget import TimeBudget, views_in_validations
from l3d_app.runtime.config_values import config_words
from l3d_app.runtime.media import save_png
from l3d_app.runtime.horizon import Horizon
from l3d_app.runtime.optim import build_optimizer
from l3d_app.runtime.random import rand, randint
from l3d_app.runtime.training import Trainable, log_test, train
from l3d_app.tasks.common import (loop_spec, require_fade_end, require_mesh_formats, require_mesh_resolution,
                                 require_nonnegative, require_positive)
from l3d_app.tasks.field_common import write_field_turntables
from l3d_app.pipelines.live_viewer import finish_viewer, sdf_view, start_viewer
from l3d_app.tasks.free_space_common import FILE as FREE_SPACE_FILE
from l3d_app.tasks.free_space_common import (MIN_STAGE_SECONDS, check_free_space_config, fit_free_rays,
                                               resolve_free_space)


VOLSDF_ONLY = {"density_along_ray": False, "quadrature": "left", "alpha": None, "beta": 0.3, "beta_mode": "anneal",
               "beta_end": 0.005, "beta_min": 0.001}
"""VolSDF's own top-level knobs and the values conf/task/volsdf.yaml ships (tests/test_neus_schedule.py checks them)."""
NEUS_ONLY = {"s": 64.0, "s_mode": "fixed", "s_end": 200.0}
"""NeuS's own top-level knobs and their shipped values (``anneal_fraction`` and ``lr_beta`` serve both densities)."""


WARMUP_STEPS_AUTO = {"neus": 150, "volsdf": 50}
"""``warmup_steps=auto``: the learning rate's linear ramp (steps) for the density that runs (after
``density=auto``). NeuS ramps over 10% of the 1500 default steps: with 50 it lost its surface on the development
scene ``dev`` in 3 of 9 runs on 2 AVX2 cores (black speckle by step 250), with 150 in none of 5 whole runs and 8
stopped at or after step 250; VolSDF keeps 50 (150 cost the development scene ``ground`` 0.5 dB and 0.25 points of
chamfer). docs/measured/volsdf.md."""


def warmup_steps_for(value, density: str) -> int:
    """The warm-up steps of knob ``value`` (``auto`` or an integer >= 0) for ``density`` (``neus`` / ``volsdf``);
    UserError for anything else."""
    if value == "auto":
        return WARMUP_STEPS_AUTO[str(density)]
    if isinstance(value, bool) or not isinstance(value, int) or value < 0:
        raise UserError(f"warmup_steps must be auto or an integer >= 0, got {value!r}")
    return value


def optimizer_config(cfg, density: str):
    """``cfg.optim``, with ``warmup_steps: auto`` (optim=warmup_cosine reads the task's top-level knob) made
    ``density``'s number of steps."""
    if cfg.optim.get("warmup_steps") != "auto":
        return cfg.optim
    out = OmegaConf.create(OmegaConf.to_container(cfg.optim, resolve=True))
    out.warmup_steps = warmup_steps_for("auto", density)
    return out


AUTO_SHARED = ("beta", "beta_mode", "beta_end")
"""VolSDF's knobs that ``density=auto`` also gives NeuS (``s = 1 / beta``, ``s_end = 1 / beta_end``, the mode)."""


def _refuse_the_other_densitys_knobs(cfg) -> None:
    """A knob of one density set away from its shipped value while the other density runs would be
    silently ignored (``density=neus beta=0.1``): one line instead, naming the density it needs. Under
    ``density=auto`` only the shared width knobs (:data:`AUTO_SHARED`) may be set: the others would hold
    for one of the two densities only."""
    name = str(cfg.density.name)
    for needs, knobs in (("volsdf", VOLSDF_ONLY), ("neus", NEUS_ONLY)):
        if name == needs:
            continue
        for key, shipped in knobs.items():
            value = cfg.get(key, shipped)
            if value != shipped and not (name == "auto" and key in AUTO_SHARED):
                if name == "auto":
                    hint = (" (density=auto picks NeuS or VolSDF from the training cameras"
                            + (" and gives NeuS s = 1 / beta" if needs == "neus" else "") + ")")
                else:
                    hint = " (NeuS's transition width is 1 / s: s, s_mode, s_end)" if needs == "volsdf" else ""
                raise UserError(f"{key}={value} needs density={needs}, got density={name}{hint}")


@TASKS.register("volsdf")
def volsdf(cfg, ctx) -> dict:
    """Train on the train views, validate on val, test once; surface scores, gifs, mesh, metrics."""
    require_positive(cfg, "iters", "batch_rays", "chunk", "supersample", "val_supersample", "eval_every")
    require_nonnegative(cfg, "w_free", "free_softness", "eikonal_points", "cache_resolution", "pretrain_steps",
                        "level_every")     # the shared run knobs: app.run_task (require_run_keys)
    warmup_steps_for(cfg.warmup_steps, "volsdf")      # auto or an integer >= 0, checked before the data is read
    require_positive(cfg, "cache_every")
    require_nonnegative(cfg, "cache_late_from")
    if cfg.get("cache_late_every") is not None:
        require_positive(cfg, "cache_late_every")
    require_mesh_resolution(cfg)
    require_mesh_formats(cfg)
    check_free_space_config(cfg.free_space)
    _check_ncc(cfg)
    fs = resolve_free_space(cfg.free_space)     # steps=auto: auto_steps
    if int(fs.steps) > 0 and str(fs.loss) == "density" and str(cfg.density.name) != "volsdf":
        raise UserError(f"free_space.loss=density needs density=volsdf (a density per point), got density="
                        f"{cfg.density.name}: use free_space.loss=occupancy or outside")
    _refuse_the_other_densitys_knobs(cfg)
    if bool(cfg.density.get("along_ray", False)) and not hasattr(MODELS.get(str(cfg.model.name)), "sdf_rgb_grad"):
        raise UserError(f"density_along_ray needs a field with an exact gradient at evaluation (model=sdf_grid_field), "
                        f"got model={cfg.model.name}")
    for candidate in candidate_configs(cfg.density):     # the knobs are checked before the data is read
        DENSITIES.build(candidate)
    data = DATASETS.build(cfg.data).to(ctx.device)
    density_cfg, below = choose_density(cfg.density, data)
    dens = DENSITIES.build(density_cfg)
    ctx.logger.text("density", f"{density_cfg['name']} ({100 * below:.0f}% of the training cameras below the scene's "
                               f"centre; density={cfg.density.name})")
    box = data.scene_box.tolist()
    model = MODELS.build(cfg.model, scene_box=box).to(ctx.device)
    dens = dens.to(ctx.device)
    if int(cfg.pretrain_steps) > 0 and not (bool(cfg.resume) and (ctx.out_dir / "checkpoint.pt").exists()):
        err = pretrain_field(model, float(cfg.model.radius if "radius" in cfg.model else cfg.model.sdf_net.radius),
                             box, int(cfg.pretrain_steps), generator=ctx.generator)
        ctx.logger.text("pretrain", f"sphere pretraining: mean |f - sdf_sphere| = {err:.4g}")
    levels = LevelSchedule(model, int(cfg.levels_start), int(cfg.level_every))
    sampler = SAMPLERS.build(cfg.sampler, scene_box=box).to(ctx.device)
    background = background_parameter(cfg.learn_background, data)  # learnt for real captures
    groups = [{"params": list(model.parameters()) + ([background["rgb"]] if background["rgb"].requires_grad else [])},
              {"params": list(dens.parameters()), "lr": float(cfg.lr_beta)}]
    horizon = Horizon(int(cfg.iters))     # where a time budget will stop the run: the schedules end there
    optim_cfg = optimizer_config(cfg, density_cfg["name"])
    opt, scheds = build_optimizer(optim_cfg, groups, int(cfg.iters), horizon=horizon)
    trainable = Trainable({"field": model, "density": dens, "background": background}, opt,
                          extra={"sampler": sampler, "horizon": horizon}, schedulers=scheds)

    origins, dirs = camera_rays(data.cameras, normalize=False)                # (N, H, W, 3), camera Z = 1
    tr = data.train.to(ctx.device)
    flat_o, flat_d, flat_rgb = origins[tr].reshape(-1, 3), dirs[tr].reshape(-1, 3), data.images[tr].reshape(-1, 3)
    # the images' coverage (RGBA alpha) when the data has it: w_mask x BCE of each ray's opacity
    flat_mask = data.masks[tr].reshape(-1) if data.masks is not None and float(cfg.w_mask) > 0 else None
    du, dv = pixel_axes(data.cameras[tr])                                     # (n_train, 3) per pixel step
    flat_cam = torch.arange(len(tr), device=ctx.device).repeat_interleave(data.cameras.height * data.cameras.width)
    n_rays, batch = flat_o.shape[0], int(cfg.batch_rays)
    patches = _patch_consistency(cfg, data, tr)     # None with ncc.weight 0
    lo, hi = torch.tensor(box[0], device=ctx.device), torch.tensor(box[1], device=ctx.device)
    field_fn = field_with_gradient(model)
    stats = {"samples_per_ray": 0.0, "fine_samples_per_ray": 0.0, "train_seconds": 0.0, "cpu_seconds": 0.0,
             "steps": 0}
    trainable.extra["step_stats"] = stats      # checkpointed: the rates cover the resumed parts of a run

    def render(o, d, **kw):
        return render_sdf_rays(field_fn, o, d, sampler, dens, field=model,
                              background=background["rgb"].clamp(0, 1), **kw)

    live = start_viewer(cfg, ctx, data, *sdf_view(model, sampler, dens, background["rgb"], int(cfg.chunk)))

    def evaluate(views: torch.Tensor, supersample: int):
        views = views.to(ctx.device)
        with torch.no_grad():   # a fresh SDF cache (step -1: not a training step; the schedule goes on)
            sampler.update(-1, model, ctx.generator, force=True)   # evaluation renders skip the rays it calls empty
        return evaluate_views(render, data.cameras[views], data.images[views], int(cfg.chunk), supersample)

    val = data.val[: int(cfg.eval_views)] if int(cfg.eval_views) > 0 else data.val
    evals_after = views_in_validations(   # the test views, in validations (the gifs take what is left at the end)
        len(val), len(data.test), int(cfg.supersample), int(cfg.val_supersample))
    budget = TimeBudget.of(ctx, reserve=0.0, evals_after=evals_after, horizon=horizon)
    # reserve: the mesh step's seconds at mesh_resolution 128; another resolution is priced by the SDF's timed cost
    reserve = budget.keep_mesh(int(cfg.mesh_resolution), float(cfg.reserve),
                               lambda: seconds_per_grid_point(model.sdf, box, device=ctx.device))
    resuming = bool(cfg.resume) and ctx.path("checkpoint.pt").exists()
    before_after, before_seconds = BeforeAfter(), None
    trainable.extra["before_after"] = before_after      # checkpointed: a resumed run keeps its "before"
    if len(val) and bool(cfg.before_after) and not resuming:   # timed: the dearest validation (fuzzy start)
        t_before = time.perf_counter()
        before_after.before(ctx, lambda: evaluate(val, int(cfg.val_supersample)))
        before_seconds = time.perf_counter() - t_before
    budget.eval_price = before_seconds
    free, w_carve, w_ray = None, float(fs.weight), float(fs.ray_weight)
    covered = data.masks[tr].reshape(-1) >= 0.5 if data.masks is not None else None   # the images' alpha
    if int(fs.steps) > 0 and (w_carve > 0 or w_ray > 0):     # what the training rays pass through, from a radiance field
        deadline = budget.stage_deadline(before_seconds, MIN_STAGE_SECONDS)
        if resuming:     # the saved stretches, or none where the run being resumed skipped its stage
            deadline = 0.0 if ctx.path(FREE_SPACE_FILE).exists() else None
        before = "unknown" if before_seconds is None else f"{before_seconds:.1f} s"
        if deadline is None:
            ctx.logger.text("free_space", f"skipped: time_budget {float(cfg.time_budget):g} s leaves it under "
                                          f"{MIN_STAGE_SECONDS:g} s after the predicted evaluation (before "
                                          f"validation {before} x {1 + evals_after:.1f})")
        else:
            ctx.logger.text("free_space", f"stage until {deadline:.1f} s of the task (0: no limit; before "
                                          f"validation {before} x {1 + evals_after:.1f})")
            with ctx.stopwatch.stage("free_space"):
                free = fit_free_rays(fs, ctx, data, box, flat_o, torch.nn.functional.normalize(flat_d, dim=-1),
                                     flat_rgb, cfg.learn_background, deadline, resuming, covered)
            if free is None:     # interrupted during the stage: nothing trained yet
                return {"interrupted_in": "free_space"}
    ray_ends = None     # (n_rays,) each training ray's free-stretch end, for free_space.ray_weight
    if free is not None and w_ray > 0:
        ray_margin = fs.get("ray_margin")     # null: the stage's margin; else its own, the ends moved by the difference
        ray_ends = free.ends_per_ray(n_rays, covered, 0.0 if ray_margin is None
                                     else float(fs.margin) - float(ray_margin))
        if str(fs.get("ray_cut", "none")) == "multi_view":    # other views' stretches stopping in front
            with ctx.stopwatch.stage("free_space"):
                uncut, ray_ends = ray_ends, free.multi_view_cut(
                    ray_ends, data.cameras[tr], flat_o, torch.nn.functional.normalize(flat_d, dim=-1), float(fs.margin))
            ctx.logger.text("free_space", f"ray_cut multi_view: {int((ray_ends < uncut).sum())} ray ends cut back")

    cache = getattr(sampler, "cache", None)
    half_cell = 0.5 * cache.cell_size if cache is not None else 0.0

    def proposal(points: torch.Tensor) -> torch.Tensor:     # free_space.proposal=surface: where the loss has a gradient
        return near_surface_weight((cache if cache is not None else model.sdf)(points),
                                   max(transition_width(dens), half_cell))

    def step_fn(step: int) -> Dict[str, torch.Tensor]:
        stats["_t0"], stats["_c0"] = time.perf_counter(), time.process_time()
        nominal = horizon.nominal(step)      # = step unless the time budget binds
        levels.apply(int(nominal))
        dens.schedule(nominal, int(cfg.iters))
        sampler.update(step, model, ctx.generator)
        idx = randint(0, n_rays, (batch,), ctx.generator, ctx.device)
        d = centre_d = flat_d[idx]
        if bool(cfg.pixel_jitter):     # a uniformly random point of the pixel: the images are box-filtered (SSAA)
            j = rand((batch, 2), ctx.generator, ctx.device) - 0.5
            d = d + j[:, :1] * du[flat_cam[idx]] + j[:, 1:] * dv[flat_cam[idx]]
        out_dirs = torch.nn.functional.normalize(d, dim=-1)
        out = render(flat_o[idx], out_dirs, perturb=True, generator=ctx.generator)
        color_loss = ((out["color"] - flat_rgb[idx]) ** 2).mean()
        logs = {"color_loss": color_loss.detach(), "samples_per_ray": out["samples_per_ray"],
                "nominal_step": torch.tensor(float(nominal)), "predicted_steps": torch.tensor(horizon.steps),
                **{k: torch.tensor(v) for k, v in dens.stats().items()},
                "active_levels": torch.tensor(float(levels.active))}
        loss = color_loss
        if flat_mask is not None:
            mask_loss = coverage_bce(out["optical_depth"], flat_mask[idx])
            loss, logs["mask_loss"] = loss + float(cfg.w_mask) * mask_loss, mask_loss.detach()
        if float(cfg.w_eikonal) > 0 or float(cfg.w_free) > 0:
            u = rand((int(cfg.eikonal_points), 3), ctx.generator, ctx.device)
            f_box, g_box = sdf_and_gradient_at(model, lo + u * (hi - lo))
            if float(cfg.w_eikonal) > 0:
                grads = [g_box] + ([out["grad"].reshape(-1, 3)] if "grad" in out else [])
                eik = eikonal_loss(torch.cat(grads))
                loss, logs["eikonal"] = loss + float(cfg.w_eikonal) * eik, eik.detach()
            if float(cfg.w_free) > 0:    # the least solid the images allow
                soft = float(cfg.free_softness)
                occ = occupied_fraction(f_box, soft) if soft > 0 else occupied_volume(f_box)
                loss, logs["free_prior"] = loss + float(cfg.w_free) * occ, occ.detach()
        fade = fade_to_zero(nominal / max(int(cfg.iters), 1), fs.get("until"))
        w_now = w_carve * fade
        shorten = float(fs.margin_beta) * transition_width(dens) if float(fs.margin_beta) > 0 else 0.0
        if ray_ends is not None and w_ray * fade > 0:     # the render's own opacity before each ray's stretch end
            ray_shorten = (shorten if fs.get("ray_margin_beta") is None
                           else float(fs.ray_margin_beta) * transition_width(dens))
            before = opacity_before(out["weights"], out["t"], out["ray_indices"], ray_ends[idx] - ray_shorten, batch)
            if str(fs.get("ray_loss", "opacity")) == "log_depth":     # does not saturate behind an opaque sheet
                before = log_depth(before)
            loss, logs["free_ray"] = loss + w_ray * fade * before.mean(), before.mean().detach()
        if free is not None and len(free) and w_now > 0:   # points some training ray passes before any surface
            if str(fs.proposal) == "surface":     # the same loss, its points drawn where it has a gradient
                pts, length, iw = free.sample_resampled(int(fs.points), int(fs.candidates), proposal,
                                                        ctx.generator, shorten, float(fs.mix))
            else:
                (pts, length), iw = free.sample(int(fs.points), ctx.generator, shorten), None
            f_free = model.sdf(pts)
            carve = free_stretch_loss(str(fs.loss), f_free, length, dens, iw)
            loss, logs["free_space"] = loss + w_now * carve, carve.detach()
        w_ncc = 0.0 if patches is None else float(cfg.ncc.weight) * fade_to_zero(nominal / max(int(cfg.iters), 1),
                                                                                 cfg.ncc.get("until"))
        if w_ncc > 0:     # the surface where the training views' patches agree
            hw = data.cameras.height * data.cameras.width
            view, rest = idx // hw, idx % hw
            t_hit, normal, hit = surface_crossing(out["t"].reshape(batch, -1), out["sdf"].reshape(batch, -1),
                                                  out["grad"].reshape(batch, -1, 3))
            ncc, figs = patches.loss(view, torch.stack([rest // data.cameras.width, rest % data.cameras.width], -1),
                                     flat_o[idx], out_dirs, t_hit, normal, hit,
                                     centre_dirs=torch.nn.functional.normalize(centre_d, dim=-1))
            loss, logs["ncc_loss"] = loss + w_ncc * ncc, ncc.detach()
            logs.update({k: torch.tensor(v) for k, v in figs.items()})
        stats["samples_per_ray"] = float(out["samples_per_ray"])
        stats["fine_samples_per_ray"] = float(out["fine_samples_per_ray"])
        return {**logs, "loss": loss}

    def after_step(step: int) -> None:
        stats["train_seconds"] += time.perf_counter() - stats.pop("_t0", time.perf_counter())
        stats["cpu_seconds"] += time.process_time() - stats.pop("_c0", time.process_time())
        stats["steps"] += 1

    def eval_fn(step: int) -> Dict[str, float]:
        metrics, picture, _ = evaluate(val, int(cfg.val_supersample))
        before_after.after(picture)
        return {**metrics, **dens.stats(), "samples_per_ray": stats["samples_per_ray"],
                "train_seconds": stats["train_seconds"], "cpu_seconds": stats["cpu_seconds"],
                "images": {"views": picture}}

    with ctx.stopwatch.stage("train"):
        result = train(ctx, trainable, step_fn, loop_spec(cfg, "volsdf"), eval_fn if len(val) else None, budget,
                       after_step)
    finish_viewer(live, ctx, result.step)
    model.eval()
    with torch.no_grad():
        sampler.update(result.step, model, ctx.generator, force=True)
        test, picture, _ = evaluate(data.test, int(cfg.supersample))             # the one test evaluation
        log_test(ctx, test, result.step, images={"views": picture})
        save_png(ctx.path("test_views.png"), picture)
    metrics = {k: round(v, 4) for k, v in test.items()}
    metrics.update(before_after.save(ctx))
    with ctx.stopwatch.stage("mesh"):
        metrics.update(_surface_metrics(cfg, ctx, model, field_fn, box, data))
    frames = 0
    if int(cfg.gif_frames) > 0:
        with ctx.stopwatch.stage("gifs"):
            frames = write_field_turntables(cfg, ctx, data, _turntable_frames(cfg, model, render, box), budget)
    steps = max(stats["steps"], 1)
    metrics.update({
        **{k: v for k, v in result.val_metrics().items() if k in ("val_psnr", "val_ssim")},
        "density": str(density_cfg["name"]), "cameras_below_fraction": round(below, 4),
        **{f"{k}_final": round(v, 6) for k, v in dens.stats().items()},
        "beta": float(cfg.beta), "iters": result.step, "n_params": sum(p.numel() for p in model.parameters()),
        "warmup_steps": int(optim_cfg.get("warmup_steps", 0)),
        "train_seconds": round(stats["train_seconds"], 4), "mesh_seconds": round(ctx.stopwatch.stages["mesh"], 4),
        "mesh_reserve_seconds": round(reserve, 4),
        "gif_seconds": round(ctx.stopwatch.stages.get("gifs", 0.0), 4), "gif_frames": frames,
        "free_space_seconds": round(ctx.stopwatch.stages.get("free_space", 0.0), 4),
        "free_space_rays": 0 if free is None else len(free),
        "free_space_skipped": bool(int(fs.steps) > 0 and (w_carve > 0 or w_ray > 0) and free is None),
        "samples_per_ray": round(stats["samples_per_ray"], 3),
        "fine_samples_per_ray": round(stats["fine_samples_per_ray"], 3),
        "rays_per_second": round(stats["steps"] * batch / max(stats["train_seconds"], 1e-9), 1),
        "seconds_per_step": round(stats["train_seconds"] / steps, 4),
        # CPU time of the training steps (all threads): the per-step cost on a shared machine
        "cpu_seconds_per_step": round(stats["cpu_seconds"] / steps, 4),
        "budget_stop": result.budget_stop, "history": result.history_rows(),
        "background": [round(float(c), 4) for c in background["rgb"].detach().clamp(0, 1)],
    })
    return metrics


def _check_ncc(cfg) -> None:
    """UserError for a bad ``ncc`` block, before any data is read (one line, naming the key)."""
    c = cfg.get("ncc")
    if c is None:
        return
    for key in ("weight", "min_std", "min_cos"):
        value = c.get(key)
        if isinstance(value, bool) or not isinstance(value, (int, float)) or value < 0:
            raise UserError(f"ncc.{key} must be a number >= 0, got {value!r}")
    for key in ("size", "sources", "best"):
        value = c.get(key)
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise UserError(f"ncc.{key} must be a positive integer, got {value!r}")
    if c.size % 2 == 0:
        raise UserError(f"ncc.size must be odd (a patch centred on its pixel), got {c.size}")
    require_fade_end(c.get("until"), "ncc.until")
    if c.best > c.sources:
        raise UserError(f"ncc.best must be at most ncc.sources ({c.sources}), got {c.best}")


def _patch_consistency(cfg, data, train_views: torch.Tensor):
    """The multi-view patch loss of ``cfg.ncc`` over the training views, or None when its weight is 0."""
    c = cfg.get("ncc")
    if c is None or float(c.weight) <= 0:
        return None
    masks = data.masks[train_views] if data.masks is not None and bool(c.within_mask) else None
    return PatchConsistency.build(data.images[train_views], data.cameras[train_views], n_sources=int(c.sources),
                                  size=int(c.size), best=int(c.best), min_std=float(c.min_std),
                                  min_cos=float(c.min_cos), masks=masks)


def sdf_and_gradient_at(model, points: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
    """SDF (N,) and its spatial gradient (N, 3) at points (N, 3), both differentiable w.r.t. the
    model: its exact gradient if it has one, else autograd's."""
    if hasattr(model, "sdf_features_gradient"):
        f, _, grad = model.sdf_features_gradient(points)
        return f, grad
    return model.sdf(points), sdf_gradient(model.sdf, points, create_graph=True)


def _ground_truth(cfg, data):
    """The data's true surface: ``data.mesh`` when the dataset carries one (the built-in
    scene does; ``data=blender data.mesh_path=FILE`` loads one), else None."""
    return getattr(data, "mesh", None)


@torch.no_grad()
def _surface_metrics(cfg, ctx, model, field_fn, box, data) -> Dict[str, float]:
    """Marching cubes of the SDF -> coloured mesh files; chamfer / F1 against the truth if known."""
    mesh = extract_mesh(model.sdf, box, int(cfg.mesh_resolution), 0.0,
                        color_fn=lambda v, n: field_fn(v, -n)[1], device=ctx.device)
    if mesh is None:      # empty level set: say so, keep the other results
        ctx.logger.text("mesh", "no mesh written: the SDF has no zero level set in the box")
        return {"mesh_faces": 0}
    out: Dict[str, float] = {}
    if bool(cfg.mesh_cull):              # what no training camera sees: free space, not a leftover
        save_field_mesh(mesh, ctx.path("mesh_uncut"), ["ply"])
        mesh, out["mesh_culled_area"] = cull_to_training_views(mesh, data, box, int(cfg.mesh_resolution))
    save_field_mesh(mesh, ctx.path("mesh"), config_words(cfg.mesh_formats, "mesh_formats"))
    out["mesh_faces"] = int(mesh.num_faces)
    truth = _ground_truth(cfg, data)
    if truth is not None:
        cams = data.cameras[data.train.to(data.cameras.device)].to("cpu")
        depth = true_depth_maps(truth.to("cpu"), cams, scale=4)       # what the training views see of the truth
        scores = surface_scores(mesh, truth, cameras=cams, depth_maps=depth, n=int(cfg.eval_points),
                                threshold=float(cfg.f1_threshold), seed=2)
        out.update({k: round(v, 6) for k, v in scores.items()})
    return out


def _turntable_frames(cfg, model, render, box) -> Dict[str, Callable]:
    """render.gif (colour | depth) and geometry.gif (sphere-traced SDF shading): their frame functions
    (about the data's up axis: :func:`~l3d_app.render.previews.write_turntables`)."""
    shade = lambda o, d: {"color": render_sdf_shaded(model.sdf, o, d, box)}  # noqa: E731
    return {"render.gif": color_depth_frames(render, int(cfg.chunk)),
            "geometry.gif": lambda c: render_views(shade, c, int(cfg.chunk))["color"]}
