"""fit_mesh: deform an icosphere to a mesh (chamfer on surface samples + regularisers).

Free parameters: one (3,) offset per icosphere vertex (level ``ico_level``, radius
``init_radius``). Each step samples ``num_samples`` points on the deformed sphere
(differentiable barycentric samples) and on the target and minimises::

    w_chamfer * chamfer + w_smooth * |uniform Laplacian|^2 + w_normal * (1 - cos dihedral)
                        + w_edge * |edge|^2

(Adam, cosine-decayed learning rate). Evaluation: chamfer and F1 at ``f1_threshold``
between ``eval_samples`` points on the fit and a fixed held-out sample of the target that
training never draws: the periodic evaluation reads the VAL sample (``history``,
``val_chamfer``, ``val_f1``), the TEST sample is read once, at the end (``chamfer``, ``f1``),
next to ``chamfer_baseline`` (two independent test-side samplings of the target). Writes fit_mesh.gif
(fit left, target right) and fit_mesh.obj.
"""

from __future__ import annotations

import torch

from l3d_app.geometry.mesh_io import save_mesh
from l3d_app.geometry.primitives import icosphere
from l3d_app.geometry.sampling import sample_points_on_mesh
from l3d_app.losses.mesh_regularizers import edge_length, laplacian_smoothing, normal_consistency
from l3d_app.metrics.chamfer import chamfer_distance
from l3d_app.metrics.fscore import fscore
from l3d_app.registry import TASKS
from l3d_app.tasks.fit_common import (check_fit_knobs, eval_generator, fit_and_test, held_out_surface,
                                      load_target_mesh, side_by_side_turntable)


@TASKS.register("fit_mesh")
def fit_mesh(cfg, ctx) -> dict:
    """Fit, evaluate chamfer / F1 every ``eval_every`` steps, write gif + obj; return the metrics."""
    check_fit_knobs(cfg, "num_samples", "eval_samples", "init_radius", "lr", "eval_every", "f1_threshold")
    target_mesh = load_target_mesh(cfg, ctx.device)
    t, n_eval = float(cfg.f1_threshold), int(cfg.eval_samples)
    held_out = held_out_surface(target_mesh, n_eval, cfg, ctx.device)
    baseline = float(chamfer_distance(held_out["test"], held_out["test_other"]))
    gen_fit = {split: eval_generator(cfg, ctx.device, split, stream=1) for split in ("val", "test")}  # draws on the fit

    source = icosphere(int(cfg.ico_level), float(cfg.init_radius)).to(ctx.device)
    offsets = torch.nn.Parameter(torch.zeros_like(source.verts))
    holder = torch.nn.ParameterDict({"offsets": offsets})
    weights = {k: float(cfg[k]) for k in ("w_chamfer", "w_smooth", "w_normal", "w_edge")}
    faces, s = source.faces, int(cfg.num_samples)

    def fitted():
        return source.with_verts(source.verts + holder["offsets"])

    def step(_i):
        mesh = fitted()
        logs = {"chamfer": chamfer_distance(sample_points_on_mesh(mesh, s, ctx.generator).points,
                                            sample_points_on_mesh(target_mesh, s, ctx.generator).points)}
        if weights["w_smooth"]:
            logs["laplacian"] = laplacian_smoothing(mesh.verts, faces)
        if weights["w_normal"]:
            logs["normal"] = normal_consistency(mesh.verts, faces)
        if weights["w_edge"]:
            logs["edge"] = edge_length(mesh.verts, faces)
        key = {"chamfer": "w_chamfer", "laplacian": "w_smooth", "normal": "w_normal", "edge": "w_edge"}
        logs["loss"] = sum(weights[key[k]] * v for k, v in logs.items())
        return logs

    def evaluate_on(split: str) -> dict:
        pts = sample_points_on_mesh(fitted(), n_eval, gen_fit[split]).points.detach()
        truth = held_out[split]
        return {"chamfer": float(chamfer_distance(pts, truth)), **fscore(pts, truth, t)}

    result, final = fit_and_test(cfg, ctx, "fit_mesh", "mesh", holder, step, evaluate_on)
    with torch.no_grad():
        out_mesh = source.with_verts((source.verts + holder["offsets"]).detach().clone())
    save_mesh(out_mesh, ctx.path("fit_mesh.obj"))
    with ctx.stopwatch.stage("render"):
        side_by_side_turntable(cfg, ctx, out_mesh, target_mesh, "fit_mesh.gif")
    return {
        **{k: v for k, v in result.val_metrics(6).items() if k in ("val_chamfer", "val_f1")},
        "history": result.history_rows(),
        "chamfer": final["chamfer"],
        "chamfer_baseline": baseline,
        "f1": final["f1"],
        "precision": final["precision"],
        "recall": final["recall"],
        "iters": result.step,
        "n_params": int(offsets.numel()),
        "n_verts": out_mesh.num_verts,
        "n_faces": out_mesh.num_faces,
        "train_seconds": round(result.train_seconds, 4),   # steps only, resumed parts included
        "skipped_steps": result.skipped_steps,
        "interrupted": result.interrupted,
    }
