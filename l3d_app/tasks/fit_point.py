"""fit_point: optimise a point cloud to a mesh surface with the chamfer distance.

The ``num_points`` fitted points start as a random ball of ``init_radius``; each step draws a
fresh target sample of as many points on the mesh (area-uniform, the run's generator) and
takes an Adam step on the chamfer distance (squared, world units^2), with a cosine-decayed
learning rate. Evaluation uses a FIXED held-out sample of the surface, so the error floor is
the sampling gap: ``chamfer_baseline`` = chamfer between two independent samplings of the
target (held-out vs another), reported beside the fit's ``chamfer`` and ``f1`` (at
``f1_threshold``). Writes fit_point.gif: fitted points (left) beside the held-out target.
"""

from __future__ import annotations

import torch

from l3d_app.geometry.pointcloud import PointCloud
from l3d_app.geometry.sampling import sample_points_on_mesh
from l3d_app.metrics.chamfer import chamfer_distance
from l3d_app.metrics.fscore import fscore
from l3d_app.registry import TASKS
from l3d_app.runtime.training import Trainable, train
from l3d_app.tasks.fit_common import (check_fit_knobs, eval_generator, load_target_mesh,
                                      side_by_side_turntable)


def random_ball(n: int, radius: float, generator: torch.Generator, device=None) -> torch.Tensor:
    """(n, 3) points uniform in a ball of ``radius`` (world units) around the origin."""
    d = torch.nn.functional.normalize(torch.randn(n, 3, generator=generator, device=device), dim=-1)
    r = radius * torch.rand(n, 1, generator=generator, device=device).pow(1.0 / 3.0)
    return d * r


@TASKS.register("fit_point")
def fit_point(cfg, ctx) -> dict:
    """Fit, evaluate chamfer / F1 every ``eval_every`` steps, write the gif; return the metrics."""
    check_fit_knobs(cfg, "num_points", "init_radius", "lr", "eval_every", "f1_threshold")
    target_mesh = load_target_mesh(cfg, ctx.device)
    n, t = int(cfg.num_points), float(cfg.f1_threshold)
    gen_eval = eval_generator(cfg, ctx.device)
    held_out = sample_points_on_mesh(target_mesh, n, gen_eval).points
    other = sample_points_on_mesh(target_mesh, n, gen_eval).points
    baseline = float(chamfer_distance(held_out, other))
    baseline_f1 = fscore(other, held_out, t)["f1"]

    points = torch.nn.Parameter(random_ball(n, float(cfg.init_radius), ctx.generator, ctx.device))
    holder = torch.nn.ParameterDict({"points": points})
    opt = torch.optim.Adam(holder.parameters(), lr=float(cfg.lr))
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=int(cfg.iters), eta_min=float(cfg.lr_final))
    trainable = Trainable({"cloud": holder}, opt, schedulers=[sched])

    def step(_i):
        target = sample_points_on_mesh(target_mesh, n, ctx.generator).points
        return {"loss": chamfer_distance(holder["points"], target)}

    def evaluate(_i):
        pts = holder["points"].detach()
        return {"chamfer": float(chamfer_distance(pts, held_out)), **fscore(pts, held_out, t)}

    with ctx.stopwatch.stage("train"):
        result = train(ctx, trainable, step, int(cfg.iters), evaluate, int(cfg.eval_every),
                       int(cfg.checkpoint_every), bool(cfg.resume), desc="fit_point")
    final = evaluate(result.step)
    with ctx.stopwatch.stage("render"):
        side_by_side_turntable(cfg, ctx, PointCloud(holder["points"].detach().clone()),
                               PointCloud(held_out), "fit_point.gif")
    return {
        "chamfer": final["chamfer"],
        "chamfer_baseline": baseline,
        "chamfer_ratio": final["chamfer"] / baseline,
        "f1": final["f1"],
        "precision": final["precision"],
        "recall": final["recall"],
        "f1_baseline": baseline_f1,
        "iters": result.step,
        "n_params": 3 * n,
        "n_points": n,
        "train_seconds": round(ctx.stopwatch.stages["train"], 4),
        "skipped_steps": result.skipped_steps,
        "interrupted": result.interrupted,
    }
