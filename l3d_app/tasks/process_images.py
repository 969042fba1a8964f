"""process_images: structure-from-motion alone, on ``data=images`` or ``data=video``.

``python main.py task=process_images data=images data.root=DIR`` solves (or finds in the
cache) the capture's cameras (:mod:`l3d_app.data.photos`) and prints what a user needs to
judge them: images registered of images given, mean reprojection error (px), sparse points,
seconds, and where the model is. ``metrics.json``: ``given``, ``registered``,
``reprojection_error``, ``points``, ``models``, ``sfm_seconds`` (the solve, per stage;
0 stages when reused), ``model_dir``, ``reused``.
"""

from __future__ import annotations

import inspect

from l3d_app.data.photos import images_capture, video_capture
from l3d_app.errors import UserError
from l3d_app.registry import TASKS, plain


@TASKS.register("process_images")
def process_images(cfg, ctx) -> dict:
    knobs = {k: v for k, v in plain(cfg.data).items() if k != "name"}
    kind = str(cfg.data.name)
    if kind not in ("images", "video"):
        raise UserError(f"process_images solves data=images or data=video, got data={kind}")
    solve = images_capture if kind == "images" else video_capture
    args = {k: v for k, v in knobs.items() if k in inspect.signature(solve).parameters}   # the SfM knobs; the rest are data=colmap's
    folder, report, reused = solve(**args)
    how = "reused from the cache" if reused else "solved now"
    print(f"{report.line()} ({how}; the sparse model: {folder / 'sparse'})", flush=True)
    if report.models > 1:
        print(f"note: {report.models} separate models; the largest is kept", flush=True)
    return {"given": report.given, "registered": report.registered,
            "reprojection_error": round(report.reprojection_error, 4), "points": report.points,
            "models": report.models, "sfm_seconds": report.seconds, "model_dir": str(folder), "reused": reused}
