"""fit_point: optimise a point cloud to a mesh surface with the chamfer distance.

The ``num_points`` fitted points start as a random ball of ``init_radius``; each step draws a
fresh target sample of as many points on the mesh (area-uniform, the run's generator) and
takes an Adam step on the chamfer distance (squared, world units^2), with a cosine-decayed
learning rate. Evaluation uses FIXED held-out samples of the surface that training never
draws (``fit_common.held_out_surface``): the periodic evaluation reads the VAL sample
(``history``, ``val_chamfer``, ``val_f1``), the TEST sample is read once, at the end
(``chamfer``, ``f1`` at ``f1_threshold``). The error floor is the sampling gap:
``chamfer_baseline`` = chamfer between two independent test-side samplings of the target.
Writes fit_point.gif: fitted points (left) beside the test sample.
"""

from __future__ import annotations

import torch

from l3d_app.geometry.pointcloud import PointCloud
from l3d_app.geometry.sampling import sample_points_on_mesh
from l3d_app.metrics.chamfer import chamfer_distance
from l3d_app.metrics.fscore import fscore
from l3d_app.registry import TASKS
from l3d_app.runtime.random import rand, randn
from l3d_app.tasks.fit_common import (check_fit_knobs, fit_and_test, held_out_surface, load_target_mesh,
                                      side_by_side_turntable)


def random_ball(n: int, radius: float, generator: torch.Generator, device=None) -> torch.Tensor:
    """(n, 3) points uniform in a ball of ``radius`` (world units) around the origin."""
    d = torch.nn.functional.normalize(randn((n, 3), generator, device), dim=-1)
    r = radius * rand((n, 1), generator, device).pow(1.0 / 3.0)
    return d * r


@TASKS.register("fit_point")
def fit_point(cfg, ctx) -> dict:
    """Fit, evaluate chamfer / F1 every ``eval_every`` steps, write the gif; return the metrics."""
    check_fit_knobs(cfg, "num_points", "init_radius", "lr", "eval_every", "f1_threshold")
    target_mesh = load_target_mesh(cfg, ctx.device)
    n, t = int(cfg.num_points), float(cfg.f1_threshold)
    held_out = held_out_surface(target_mesh, n, cfg, ctx.device)
    baseline = float(chamfer_distance(held_out["test"], held_out["test_other"]))
    baseline_f1 = fscore(held_out["test_other"], held_out["test"], t)["f1"]

    points = torch.nn.Parameter(random_ball(n, float(cfg.init_radius), ctx.generator, ctx.device))
    holder = torch.nn.ParameterDict({"points": points})

    def step(_i):
        target = sample_points_on_mesh(target_mesh, n, ctx.generator).points
        return {"loss": chamfer_distance(holder["points"], target)}

    def evaluate_on(split: str) -> dict:
        pts, truth = holder["points"].detach(), held_out[split]
        return {"chamfer": float(chamfer_distance(pts, truth)), **fscore(pts, truth, t)}

    result, final = fit_and_test(cfg, ctx, "fit_point", "cloud", holder, step, evaluate_on)
    with ctx.stopwatch.stage("render"):
        side_by_side_turntable(cfg, ctx, PointCloud(holder["points"].detach().clone()),
                               PointCloud(held_out["test"]), "fit_point.gif")
    return {
        **{k: v for k, v in result.val_metrics(6).items() if k in ("val_chamfer", "val_f1")},
        "history": result.history_rows(),
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
        "train_seconds": round(result.train_seconds, 4),   # steps only, resumed parts included
        "skipped_steps": result.skipped_steps,
        "interrupted": result.interrupted,
    }
