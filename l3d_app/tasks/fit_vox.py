"""fit_vox: optimise a voxel grid of occupancy logits to a mesh's occupancy.

Target: the ``voxel_size``^3 occupancy of the data source's mesh over its padded bounding
box, by the generalised winding number at the cell centres (robust for any closed-ish mesh).
Model: one free logit per cell (Adam), initialised N(0, 1) from the run's generator.
Loss: binary cross-entropy on logits (``loss`` group entry, ``bce_logits`` by default).
Error: IoU of ``logits > 0`` with the target, logged against step and wall time.
Writes fit_vox.gif: marching cubes of the fitted occupancy (left) beside the target mesh.
"""

from __future__ import annotations

import torch

from l3d_app.errors import UserError
from l3d_app.geometry.marching_cubes import padded_bounds
from l3d_app.geometry.voxels import occupancy_to_mesh, voxelize_mesh
from l3d_app.metrics.iou import iou
from l3d_app.registry import LOSSES, TASKS
from l3d_app.runtime.random import randn
from l3d_app.runtime.training import Trainable, train
from l3d_app.tasks.common import loop_spec
from l3d_app.tasks.fit_common import check_fit_knobs, load_target_mesh, side_by_side_turntable


@TASKS.register("fit_vox")
def fit_vox(cfg, ctx) -> dict:
    """Fit, evaluate IoU every ``eval_every`` steps, write the gif; return the metrics."""
    check_fit_knobs(cfg, "voxel_size", "lr", "eval_every")
    if cfg.get("pos_weight") is not None and not float(cfg.pos_weight) > 0:
        raise UserError(f"pos_weight must be a positive weight of occupied cells or null, got {cfg.pos_weight!r}")
    target_mesh = load_target_mesh(cfg, ctx.device)
    R = int(cfg.voxel_size)
    lo, hi = target_mesh.bounds()
    bounds = padded_bounds((lo.tolist(), hi.tolist()), R, margin=float(cfg.bounds_margin))
    with ctx.stopwatch.stage("voxelize"):
        target = voxelize_mesh(target_mesh, R, bounds)
    if not bool(target.any()):
        raise UserError("the target mesh occupies no voxel (is it closed? try a larger voxel_size)")
    target_f = target.float()
    logits = torch.nn.Parameter(randn((R, R, R), ctx.generator, ctx.device))
    holder = torch.nn.ParameterDict({"logits": logits})
    trainable = Trainable({"voxels": holder}, torch.optim.Adam(holder.parameters(), lr=float(cfg.lr)))
    loss_fn = LOSSES.build(cfg.loss)

    def step(_i):
        return {"loss": loss_fn(holder["logits"], target_f)}

    def evaluate(_i):
        occ = holder["logits"] > 0
        return {"iou": iou(occ, target), "occupied_cells": int(occ.sum())}

    with ctx.stopwatch.stage("train"):
        result = train(ctx, trainable, step, loop_spec(cfg, "fit_vox"), evaluate)
    occ = holder["logits"].detach() > 0
    try:
        fitted = occupancy_to_mesh(torch.sigmoid(holder["logits"].detach()), bounds)
    except UserError:  # nothing (or everything) occupied: show an empty panel
        fitted = None
    with ctx.stopwatch.stage("render"):
        side_by_side_turntable(cfg, ctx, fitted, target_mesh, "fit_vox.gif")
    with torch.no_grad():
        final_loss = float(loss_fn(holder["logits"], target_f))
    return {
        "iou": round(iou(occ, target), 6),
        "bce": final_loss,
        "iters": result.step,
        "n_params": R ** 3,
        "occupied_cells": int(occ.sum()),
        "target_cells": int(target.sum()),
        "voxel_size": R,
        "voxelize_seconds": round(ctx.stopwatch.stages["voxelize"], 4),
        "train_seconds": round(result.train_seconds, 4),   # steps only, resumed parts included
        "skipped_steps": result.skipped_steps,
        "interrupted": result.interrupted,
    }
