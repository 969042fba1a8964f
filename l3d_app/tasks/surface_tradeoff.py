"""surface_tradeoff: speed vs error of two ways to get a torus surface from a function.

1. Parametric sampling: ``num_samples`` points, (u, v) i.i.d. uniform in the parameters.
2. Implicit: the exact torus SDF evaluated on a ``resolution``^3 grid + marching cubes, then
   ``mesh_samples`` area-uniform points sampled on the mesh.

Error: chamfer distance (sum of the two mean squared nearest distances, world units^2) to a
dense exact reference: ``reference_samples`` area-uniform points on the true torus (rejection
sampling on the area element, a different seed). The chamfer includes a sampling floor (even
perfect points have nearest-neighbour gaps), so for the meshes we also report
``surface_error``: the mean |exact SDF| of the mesh samples, i.e. their mean distance to the
true surface (world units), which isolates the marching-cubes discretisation error.

Time: parametric sampling alone; SDF grid evaluation + marching cubes (not the metric's
sampling). Writes tradeoff.md / tradeoff.csv, logs scalars and a markdown table. The summary
``best_setting`` is the lowest chamfer against a second, independent reference (``val_chamfer``);
``chamfer`` is that setting's figure against the first (a minimum over noisy estimates read on
the sample that picked it would be biased low).
"""

from __future__ import annotations

import csv
import time
from typing import Dict, List

import torch

from l3d_app.errors import UserError
from l3d_app.geometry.marching_cubes import sdf_to_mesh
from l3d_app.geometry.parametric import torus_points
from l3d_app.geometry.sdf import Torus
from l3d_app.geometry.sampling import sample_points_on_mesh
from l3d_app.metrics.chamfer import chamfer_distance, require_backend
from l3d_app.registry import TASKS
from l3d_app.runtime.files import atomic_path
from l3d_app.runtime.progress import progress

COLUMNS = ("method", "setting", "seconds", "chamfer", "surface_error", "num_points", "num_faces")


def _positive_ints(cfg, key: str) -> List[int]:
    values = cfg.get(key)
    try:
        out = [int(v) for v in values]
    except (TypeError, ValueError):
        raise UserError(f"{key} must be a list of positive integers, got {values!r}") from None
    if not out or any(v <= 0 for v in out):
        raise UserError(f"{key} must be a non-empty list of positive integers, got {out}")
    return out


def _timed(fn):
    t0 = time.perf_counter()
    out = fn()
    return out, time.perf_counter() - t0


def _markdown(rows: List[Dict]) -> str:
    head = "| method | setting | seconds | chamfer | surface error | points | faces |\n|---|---:|---:|---:|---:|---:|---:|\n"
    body = "".join(
        f"| {r['method']} | {r['setting']} | {r['seconds']:.4f} | {r['chamfer']:.3e} | "
        f"{'' if r['surface_error'] is None else format(r['surface_error'], '.3e')} | "
        f"{r['num_points']} | {r['num_faces'] if r['num_faces'] is not None else ''} |\n" for r in rows)
    return head + body


@TASKS.register("surface_tradeoff")
def surface_tradeoff(cfg, ctx) -> dict:
    """Time and chamfer of parametric sampling vs marching cubes for the torus; see module doc."""
    R, r = float(cfg.major_radius), float(cfg.minor_radius)
    if not (R > 0 and r > 0):
        raise UserError(f"torus radii must be positive, got major_radius={R}, minor_radius={r}")
    sample_counts = _positive_ints(cfg, "num_samples_list")
    resolutions = _positive_ints(cfg, "resolutions")
    if min(resolutions) < 3:
        raise UserError(f"resolutions must be >= 3, got {resolutions}")
    n_ref, n_mesh = int(cfg.reference_samples), int(cfg.mesh_samples)
    if n_ref <= 0 or n_mesh <= 0:
        raise UserError("reference_samples and mesh_samples must be positive")
    backend = require_backend(str(cfg.chamfer_backend))
    seed = int(cfg.get("seed", 0))

    sdf = Torus(R, r)
    reference = torus_points(n_ref, R, r, torch.Generator().manual_seed(seed + int(cfg.reference_seed_offset)),
                             area_uniform=True).points
    # a second, independent reference chooses best_setting; the first reports its chamfer (read once)
    reference_val = torus_points(n_ref, R, r, torch.Generator().manual_seed(seed + int(cfg.reference_seed_offset) + 1),
                                 area_uniform=True).points
    # warm-up so the first timed setting does not pay one-off allocation costs
    torus_points(16, R, r, torch.Generator().manual_seed(0))
    sdf_to_mesh(sdf, 8, colors=None)

    rows: List[Dict] = []
    settings = [("points", n) for n in sample_counts] + [("marching_cubes", res) for res in resolutions]
    for step, (method, value) in enumerate(progress(settings, desc="surface_tradeoff")):
        gen = torch.Generator().manual_seed(seed + step)
        if method == "points":
            cloud, seconds = _timed(lambda: torus_points(value, R, r, gen))
            points, faces, surface_error = cloud.points, None, None
            key = f"points_{value}"
        else:
            mesh, seconds = _timed(lambda: sdf_to_mesh(sdf, value, colors=None))
            points = sample_points_on_mesh(mesh, n_mesh, gen).points
            faces = mesh.num_faces
            surface_error = float(sdf(points.double()).abs().mean())
            key = f"mc_{value}"
        chamfer = float(chamfer_distance(points, reference, backend=backend))
        rows.append({"method": method, "setting": value, "seconds": seconds, "chamfer": chamfer,
                     "val_chamfer": float(chamfer_distance(points, reference_val, backend=backend)),
                     "surface_error": surface_error, "num_points": points.shape[0], "num_faces": faces,
                     "key": key})
        scalars = {f"surface_tradeoff/{key}/chamfer": chamfer, f"surface_tradeoff/{key}/seconds": seconds}
        if surface_error is not None:
            scalars[f"surface_tradeoff/{key}/surface_error"] = surface_error
        ctx.logger.log_scalars(scalars, step=step)
        # curves: chamfer and time against the setting, one tag per method
        ctx.logger.log_scalars({f"surface_tradeoff/{method}_chamfer": chamfer,
                                f"surface_tradeoff/{method}_seconds": seconds}, step=int(value))

    table = _markdown(rows)
    ctx.logger.text("surface_tradeoff/table", table)
    with atomic_path(ctx.path("tradeoff.md")) as tmp:
        tmp.write_text(f"# Torus (R={R}, r={r}): parametric points vs marching cubes\n\n"
                       f"Reference: {n_ref} exact area-uniform points; marching-cubes meshes "
                       f"sampled with {n_mesh} points; chamfer = sum of the two mean squared "
                       f"nearest distances (world units^2); surface error = mean |SDF| of the "
                       f"mesh samples (world units).\n\n" + table)
    with atomic_path(ctx.path("tradeoff.csv")) as tmp:
        with open(tmp, "w", newline="") as fh:
            writer = csv.DictWriter(fh, fieldnames=COLUMNS, extrasaction="ignore")
            writer.writeheader()
            writer.writerows(rows)

    metrics: Dict[str, float] = {"reference_samples": n_ref, "mesh_samples": n_mesh}
    for row in rows:
        metrics[f"{row['key']}_chamfer"] = row["chamfer"]
        metrics[f"{row['key']}_seconds"] = round(row["seconds"], 5)
        if row["surface_error"] is not None:
            metrics[f"{row['key']}_surface_error"] = row["surface_error"]
            metrics[f"{row['key']}_faces"] = row["num_faces"]
    best = min(rows, key=lambda row: row["val_chamfer"])     # chosen on the second reference ...
    metrics["chamfer"] = best["chamfer"]                      # ... reported on the first
    metrics["val_chamfer"] = best["val_chamfer"]
    metrics["best_setting"] = best["key"]
    metrics["selected_on"] = "val"
    return metrics
