"""surfels: 2D Gaussian splatting (Huang et al. 2024) from posed images, and a mesh of its surface.

The splats are oriented disks (:func:`~l3d_app.render.gaussians.surfels.rasterize_surfels`: the
tiled Gaussian rasteriser with the ray-splat intersection), trained as ``gs_train`` trains 3D
Gaussians, from the same data, initialisation, optimiser, densification (``strategy=``),
background and time budget (:mod:`l3d_app.pipelines.splats`), with two more loss terms
(:mod:`l3d_app.losses.surfel_regularizers`): the depth distortion (weight ``distortion.weight``
from step ``distortion.start``) and the depth-normal consistency (``normal.weight`` from
``normal.start``). After training: the test views once, then a mesh: TSDF fusion of the median
depth of the training views (voxel grid sized by the scene, ``mesh_resolution`` voxels along
its longest side, truncation ``mesh_truncation`` voxels), marching cubes, the faces some training
camera sees (:mod:`l3d_app.pipelines.surface_mesh`), written as ``mesh.<fmt>`` with vertex colours
and scored against the data's true surface when it has one (volsdf's scores: chamfer, F1, observed
variants). Outputs: ``test_views.gif``, ``progress.gif``, ``point_cloud.ply`` (the surfels in the
3DGS layout, thickness as the third scale), ``mesh.*``, ``metrics.json``.
"""

from __future__ import annotations

from typing import List

import torch

from l3d_app.errors import UserError
from l3d_app.losses.surfel_regularizers import depth_distortion, depth_normal_consistency
from l3d_app.models.background import background_parameter
from l3d_app.pipelines.live_viewer import finish_viewer, gaussian_view, start_viewer
from l3d_app.pipelines.splats import (SplatSteps, evaluate_views, initial_splats, scene_extent, splat_optimizer,
                                     write_splat_outputs)
from l3d_app.pipelines.surface_mesh import fused_mesh, truth_scores
from l3d_app.registry import DATASETS, STRATEGIES, TASKS
from l3d_app.render.field_mesh import save_field_mesh
from l3d_app.render.gaussians.panels import depth_range
from l3d_app.render.gaussians.surfels import rasterize_surfels
from l3d_app.runtime.budget import TimeBudget
from l3d_app.runtime.config_values import config_words
from l3d_app.runtime.media import to_uint8
from l3d_app.runtime.training import Trainable, train
from l3d_app.tasks.common import loop_spec, require_mesh_formats, require_nonnegative, require_positive


def _check(cfg) -> None:
    require_positive(cfg, "iters", "eval_every", "sh_every", "lr_decay_steps", "tile_size", "log_every",
                     "mesh_resolution", "mesh_truncation", "eval_points", "f1_threshold")
    require_nonnegative(cfg, "mesh_reserve")
    if cfg.get("sh_degree") not in (0, 1, 2, 3):
        raise UserError(f"sh_degree must be 0, 1, 2 or 3, got {cfg.get('sh_degree')!r}")
    for term in ("distortion", "normal"):
        require_nonnegative(cfg[term], "weight", "start")
    if bool(cfg.get("isotropic", False)):
        raise UserError("surfels are disks with two scales: isotropic=true is a gs_train setting")
    if not float(cfg.mesh_truncation) > 1:
        raise UserError(f"mesh_truncation must be more than 1 voxel, got {cfg.mesh_truncation}")
    require_mesh_formats(cfg)


@TASKS.register("surfels")
def surfels(cfg, ctx) -> dict:
    """Train surfels; val figures during training, test figures once; a fused mesh and its scores."""
    _check(cfg)
    raw = DATASETS.build(cfg.data)
    if len(raw.val) == 0:
        raise UserError(f"surfels needs validation views and data '{cfg.data.name}' has none")
    data = raw.to(ctx.device)
    model = initial_splats(raw, data, ctx.generator, int(cfg.n_init), str(cfg.init_colors), float(cfg.init_opacity),
                           False, float(cfg.init_scale), float(cfg.init_max_coverage), surfels=True,
                           data_name=str(cfg.data.name)).to(ctx.device)
    extent = scene_extent(data.cameras[data.train], float(cfg.extent_margin))
    background = background_parameter(cfg.learn_background, data)
    opt, sched = splat_optimizer(model, background, cfg.lr, extent, float(cfg.adam_eps), int(cfg.lr_decay_steps))
    strategy = STRATEGIES.build(cfg.strategy)
    strategy.initialize(model, opt, extent)
    steps = SplatSteps(model, opt, strategy, data.train, data.images, ctx.generator, float(cfg.ssim_lambda),
                       int(cfg.sh_degree), int(cfg.sh_every))
    prog_frames: List[torch.Tensor] = []
    trainable = Trainable({"gaussians": model, "background": background}, opt, schedulers=[sched],
                          extra={"strategy": strategy, "progress_frames": prog_frames, "step_times": steps.step_times})
    dist, normal = cfg.distortion, cfg.normal
    live = start_viewer(cfg, ctx, data, *gaussian_view(model, background["rgb"], steps.degree, int(cfg.tile_size),
                                                       rasterize=rasterize_surfels))

    def render(i: int, deg: int):
        return rasterize_surfels(model.means, model.log_scales, model.quats, model.opacity_logits, model.sh, deg,
                                 data.cameras[i], background["rgb"].clamp(0, 1), tile_size=int(cfg.tile_size))

    def step_fn(step: int):
        i = steps.begin()
        out = render(i, steps.degree(step))
        loss, l1 = steps.photometric(out["color"][0], i)
        logs = {"l1": l1.detach(), "n_gaussians": torch.tensor(float(model.num))}
        if float(dist.weight) > 0 and step >= int(dist.start):
            term = depth_distortion(out["distortion"], extent)
            loss, logs["distortion"] = loss + float(dist.weight) * term, term.detach()
        if float(normal.weight) > 0 and step >= int(normal.start):
            term = depth_normal_consistency(out["normal"], out["median_depth"], out["alpha"], data.cameras[i])
            loss, logs["normal"] = loss + float(normal.weight) * term, term.detach()
        return {"loss": steps.finish(loss, out, step), **logs}

    # after training: the test views and the training views' depth (in validations), then the mesh's seconds
    budget = TimeBudget.of(ctx, evals_after=(len(data.test) + len(data.train)) / len(data.val),
                           reserve=float(cfg.reserve) + float(cfg.mesh_reserve))

    lo_hi = depth_range(data.cameras[int(data.val[0])].centers()[0], data.scene_box)

    def evaluate(views, deg):
        return evaluate_views(lambda i: render(i, deg), views, data.images, lo_hi, depth_key="median_depth")

    def eval_fn(step: int):
        _, _, panel, m = evaluate(data.val, steps.degree(step))
        prog_frames.append(torch.from_numpy(to_uint8(panel)))
        return {**m, "n_gaussians": model.num, "images": {"pred_truth_error_depth": panel}}

    with ctx.stopwatch.stage("train"):
        result = train(ctx, trainable, step_fn, loop_spec(cfg, "surfels", log_every=int(cfg.log_every)), eval_fn,
                       budget, steps.after_step_hook(int(cfg.iters), budget, ctx.logger))
    finish_viewer(live, ctx, result.step)
    deg = steps.degree(result.step)
    test = write_splat_outputs(ctx, model, result.step, *evaluate(data.test, deg), prog_frames, float(cfg.fps))
    with ctx.stopwatch.stage("mesh"):
        mesh_stats = _mesh(cfg, ctx, data, lambda i: render(i, deg))
    return {**test, **result.val_metrics(), **result.timing(), "n_gaussians": model.num, **mesh_stats,
            "mesh_seconds": round(ctx.stopwatch.stages["mesh"], 3),
            "background": [round(float(c), 4) for c in background["rgb"].detach().clamp(0, 1)],
            **steps.step_cost(), "history": result.history_rows()}


def _mesh(cfg, ctx, data, render) -> dict:
    """The fused mesh of the training views' depth, written and scored (empty: a note, no file)."""
    cams = data.cameras[data.train.to(data.cameras.device)]
    mesh, stats = fused_mesh(render, data.train.tolist(), cams, data.scene_box, int(cfg.mesh_resolution),
                             float(cfg.mesh_truncation))
    if mesh is None:
        ctx.logger.text("mesh", "no mesh written: the fused depth holds no surface")
        return stats
    save_field_mesh(mesh, ctx.path("mesh"), config_words(cfg.mesh_formats, "mesh_formats"))
    truth = getattr(data, "mesh", None)
    if truth is not None:
        stats.update(truth_scores(mesh, truth, cams, int(cfg.eval_points), float(cfg.f1_threshold)))
    return stats
