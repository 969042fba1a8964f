"""stereo_depth: depth from disparity on a rendered scene, and its error against baseline, focal length
and disparity error (the course's stereo exercise as a table and a plot).

The scene (``data``, the built-in one by default) is rendered by the mesh renderer from one
camera; its depth map is the ground truth. A rectified rig with that camera's focal length
(or ``focal_px``) and ``baseline`` gives the disparity ``f B / Z``; Gaussian noise of
``sigma_px`` pixels is added and the depth recovered (:mod:`l3d_app.metrics.stereo_error`).
Writes ``stereo.png`` (depth | disparity | recovered depth | |error|, depths on one viridis
range), ``error_vs_depth.png`` (first-order curves ``Z^2 sigma / (f B)`` per baseline with
the measured per-depth-bin RMS as points), ``table.md`` and metrics.json with one row per
setting: the reference rig and one factor varied at a time.

``preset=exercise``: the worked exercise instead, no rendering: the ``exercise`` rig (focal 1000 px,
baseline 0.12 m) at depths 1-100 m with a disparity error of +-1 px, as a table printed on stdout and
written to ``table.md`` (:mod:`l3d_app.metrics.stereo_table`), its rows in metrics.json.
"""

from __future__ import annotations

import torch

from l3d_app.errors import UserError
from l3d_app.geometry.cameras import look_at_cameras
from l3d_app.metrics.stereo_error import binned_rmse, noisy_depth, simulate_depth_error
from l3d_app.metrics.stereo_table import disparity_error_markdown, disparity_error_rows
from l3d_app.registry import DATASETS, RENDERERS, TASKS
from l3d_app.render.volume.diagnostics import depth_colormap
from l3d_app.runtime.config_values import config_floats
from l3d_app.runtime.media import save_png
from l3d_app.runtime.plots import line_plot
from l3d_app.tasks.common import require_positive


def _rows(depth, f0, b0, s0, cfg, generator):
    """The reference setting, then baselines, focal scales and disparity errors one at a time."""
    settings = [("reference", f0, b0, s0)]
    settings += [("baseline", f0, float(b), s0) for b in cfg.sweep.baselines]
    settings += [("focal", f0 * float(k), b0, s0) for k in cfg.sweep.focal_scales]
    settings += [("disparity_error", f0, b0, float(s)) for s in cfg.sweep.sigmas_px]
    rows = []
    for varied, f, b, s in settings:
        r = simulate_depth_error(depth, f, b, s, generator, trials=int(cfg.trials))
        rows.append({"varied": varied, "focal_px": round(f, 3), "baseline": b, "sigma_px": s,
                     **{k: round(v, 6) for k, v in r.items()}})
    return rows


def _table(rows) -> str:
    head = "| varied | focal (px) | baseline | sigma (px) | RMSE measured | RMSE first order | ratio |\n" \
           "|---|---|---|---|---|---|---|\n"
    return head + "".join(f"| {r['varied']} | {r['focal_px']} | {r['baseline']} | {r['sigma_px']} | "
                          f"{r['rmse']:.5f} | {r['rmse_first_order']:.5f} | {r['ratio']:.3f} |\n" for r in rows)


def _exercise(cfg, ctx) -> dict:
    """The worked exercise's table for the ``exercise`` rig: printed, written to table.md, returned."""
    ex = cfg.exercise
    require_positive(ex, "focal_px", "baseline", "disparity_error")
    depths = config_floats(ex.depths, "exercise.depths")
    if not depths or min(depths) <= 0:
        raise UserError(f"exercise.depths must be a non-empty list of positive depths (m), got {depths}")
    f, b, dd = float(ex.focal_px), float(ex.baseline), float(ex.disparity_error)
    rows = disparity_error_rows(f, b, depths, dd)
    table = disparity_error_markdown(rows, dd)
    ctx.path("table.md").write_text(f"focal {f:g} px, baseline {b:g} m, disparity error +-{dd:g} px\n\n" + table)
    print(f"stereo exercise: focal {f:g} px, baseline {b:g} m, disparity error +-{dd:g} px\n{table}", flush=True)
    return {"preset": "exercise", "focal_px": f, "baseline": b, "disparity_error": dd,
            "rows": [{k: (None if v == float("inf") else round(v, 6)) for k, v in r.items()} for r in rows]}


@TASKS.register("stereo_depth")
def stereo_depth(cfg, ctx) -> dict:
    """Render the depth, simulate the rig, write pictures, table and plot (or the exercise's table)."""
    preset = str(cfg.get("preset", "scene"))
    if preset not in ("scene", "exercise"):
        raise UserError(f"preset must be scene or exercise, got {preset!r}")
    if preset == "exercise":
        return _exercise(cfg, ctx)
    require_positive(cfg, "image_size", "distance", "fov", "baseline", "sigma_px", "trials")
    if cfg.get("focal_px") is not None:          # null: the camera's
        require_positive(cfg, "focal_px")
    sweep = {k: config_floats(cfg.sweep[k], f"sweep.{k}") for k in ("baselines", "focal_scales", "sigmas_px")}
    if not all(sweep.values()) or min(sweep["baselines"] + sweep["focal_scales"]) <= 0 or min(sweep["sigmas_px"]) < 0:
        raise UserError(f"sweep lists must be non-empty, baselines and focal_scales > 0, sigmas_px >= 0; got {sweep}")
    scene = DATASETS.build(cfg.data, device=ctx.device)
    cams = look_at_cameras(float(cfg.distance), float(cfg.elevation), float(cfg.azimuth), float(cfg.fov),
                           int(cfg.image_size), device=ctx.device)
    with torch.no_grad():
        out = RENDERERS.build(cfg.renderer)(scene, cams)
    mask = (out["alpha"][0] > 0.999).cpu()
    depth = out["depth"][0].cpu().to(torch.float64)
    f0 = float(cfg.focal_px) if cfg.get("focal_px") is not None else float(cams.fx[0])
    b0, s0 = float(cfg.baseline), float(cfg.sigma_px)
    rec = noisy_depth(depth, f0, b0, s0, ctx.generator)
    zmax = float(depth[mask].max())
    err = (rec["depth"] - depth).abs()
    panels = [depth_colormap(depth, mask, vmax=zmax), depth_colormap(rec["disparity"], mask),
              depth_colormap(rec["depth"].clamp(max=zmax), mask, vmax=zmax),
              depth_colormap(err, mask)]
    strip = torch.cat(panels, dim=1)
    save_png(ctx.path("stereo.png"), strip)
    ctx.logger.image("stereo/depth_disparity_recovered_error", strip, 0)
    valid = depth[mask]
    rows = _rows(valid, f0, b0, s0, cfg, ctx.generator)
    (ctx.path("table.md")).write_text(_table(rows))
    z = torch.linspace(float(valid.min()), float(valid.max()), 50, dtype=torch.float64)
    curves, points = {}, {}
    for b in cfg.sweep.baselines:
        b = float(b)
        curves[f"B={b:g}"] = (z.tolist(), (z.square() * s0 / (f0 * b)).tolist())
        sim = noisy_depth(valid.expand(int(cfg.trials), -1), f0, b, s0, ctx.generator)
        finite = torch.isfinite(sim["depth"])
        zz = valid.expand(int(cfg.trials), -1)[finite]
        binned = binned_rmse(zz, (sim["depth"] - valid.expand(int(cfg.trials), -1))[finite])
        points[f"B={b:g} (measured)"] = (binned["depth"], binned["rmse"])
    line_plot(ctx.path("error_vs_depth.png"), curves, points, xlabel="depth Z (world units)",
              ylabel="RMS depth error", title=f"f={f0:.0f} px, disparity noise {s0:g} px", logy=True)
    ref = rows[0]
    return {"focal_px": round(f0, 3), "baseline": b0, "sigma_px": s0, "n_pixels": int(mask.sum()),
            "depth_min": round(float(valid.min()), 4), "depth_max": round(zmax, 4),
            "rmse": ref["rmse"], "rmse_first_order": ref["rmse_first_order"], "ratio": ref["ratio"],
            "rows": rows}
