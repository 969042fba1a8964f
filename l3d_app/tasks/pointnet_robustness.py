"""pointnet_robustness: the course's robustness tables for classification AND segmentation.

    python main.py task=pointnet_robustness                        # trains both first
    python main.py task=pointnet_robustness cls_checkpoint=A/best.pt seg_checkpoint=B/best.pt
    python main.py task=pointnet_robustness augment_rotation=true  # train with rotations

For each kind (cls, seg) the model is read from its ``best.pt`` or, when none is given,
trained first with the shared pointnet knobs (into ``cls/`` and ``seg/`` sub-folders; the
checkpoint is chosen on the validation split, never on test). Then two tables on the test
split:

* rotation: accuracy with every test cloud rotated by each of ``rotation_degrees``
  about ``rotation_axis``, evaluated on ``rotation_points`` points per cloud (0 = all);
* number of points: accuracy on the first-seed random subsets of ``num_points_list``
  points per cloud (sizes above the clouds' size are reported as NaN).

``rotation_pictures`` > 0: for each angle, that many test clouds (the first of each class) drawn rotated
as the model saw them, a row per angle in ``rotation_<kind>.png`` (cls: green where the class was right,
red where wrong; seg: the predicted parts' colours), also per angle in TensorBoard (``rotation/<kind>``).
Figures go to metrics.json (``cls_rot<deg>``, ``cls_pts<n>``, ``seg_rot<deg>``,
``seg_pts<n>``, plus ``tables``; the curves in ``robustness_rotation.png`` and ``robustness_points.png``; ``<kind>_ms_per_cloud``: wall milliseconds per test cloud of
one evaluation pass on all its points, ``<kind>_n_params``), TensorBoard (``robustness/*`` against the degrees or
point count, and the markdown tables as text) and ``robustness.md``.
"""

from __future__ import annotations

import sys
import time
from typing import Any, Dict, List

import torch

from l3d_app.errors import UserError
from l3d_app.geometry.cameras import look_at_cameras
from l3d_app.pipelines.point_nets import evaluate, fit, load_model, require_axis, rotations
from l3d_app.pipelines.point_visuals import rotation_row
from l3d_app.registry import RENDERERS, TASKS
from l3d_app.runtime.config_values import config_floats, config_words
from l3d_app.runtime.context import RunContext
from l3d_app.runtime.logger import RunLogger
from l3d_app.runtime.media import save_png
from l3d_app.runtime.plots import line_plot
from l3d_app.runtime.seed import seed_everything
from l3d_app.tasks.point_common import load_data, training_spec


def _table(title: str, header: str, rows: Dict[Any, float]) -> str:
    lines = [f"| {header} | {title} accuracy |", "|---:|---:|"]
    lines += [f"| {k} | {v:.4f} |" for k, v in rows.items()]
    return "\n".join(lines)


def _model_for(cfg, ctx, kind: str):
    path = cfg.get(f"{kind}_checkpoint")
    data = load_data(cfg, kind)
    if path:
        model, meta = load_model(path, ctx.device)
        if meta["kind"] != kind:
            raise UserError(f"{kind}_checkpoint {path} holds a '{meta['kind']}' model")
        selected_on = str(meta.get("selected_on", "unknown"))
        if selected_on != "val":
            note = f"{kind}_checkpoint {path} does not say it was chosen on the validation split"
            print(f"l3d_app: note: {note}", file=sys.stderr)
            ctx.logger.text(f"{kind}/selected_on", note)
        return model, data, {"source": str(path), "selected_on": selected_on}
    sub = ctx.out_dir / kind
    sub_ctx = RunContext(out_dir=sub, device=ctx.device,
                         generator=seed_everything(int(cfg.seed), ctx.device),
                         logger=RunLogger(sub, enabled=ctx.logger.writer is not None))
    sub.mkdir(parents=True, exist_ok=True)
    try:
        model, info = fit(training_spec(cfg), sub_ctx, data, kind)
    finally:
        sub_ctx.logger.close()
    return model, data, {"source": str(sub / "best.pt"), "train_seconds": info["train_seconds"],
                         "val_accuracy": info["val_accuracy"], "selected_on": info["selected_on"]}


def _rotation_row(cfg, ctx, ev, kind: str, data, degrees: float) -> torch.Tensor:
    """The picture row of one angle (:func:`rotation_row`), logged to TensorBoard at that angle."""
    camera = look_at_cameras(float(cfg.distance), float(cfg.elevation), 30.0, float(cfg.fov), int(cfg.image_size),
                             device=ctx.device)
    row = rotation_row(RENDERERS.build(cfg.point_renderer), camera, ev, kind, data.test.labels,
                       int(cfg.rotation_pictures), len(data.part_names))
    ctx.logger.image(f"rotation/{kind}", row, int(round(degrees)))
    return row


@TASKS.register("pointnet_robustness")
def pointnet_robustness(cfg, ctx) -> dict:
    """Rotation and point-count tables for a classifier and a segmenter (see module doc)."""
    require_axis(cfg.rotation_axis)
    degrees: List[float] = config_floats(cfg.rotation_degrees, "rotation_degrees")
    counts: List[int] = [int(n) for n in cfg.num_points_list]
    if not degrees or not counts or min(counts) < 1:
        raise UserError(f"rotation_degrees and num_points_list must be non-empty, the counts >= 1; got "
                        f"{degrees}, {counts}")
    kinds = config_words(cfg.robust_kinds, "robust_kinds")
    if not kinds or any(k not in ("cls", "seg") for k in kinds):
        raise UserError(f"robust_kinds must list cls and/or seg, got {kinds}")
    metrics: Dict[str, Any] = {"rotation_axis": str(cfg.rotation_axis),
                               "augment_rotation": bool(cfg.augment_rotation), "tables": {}}
    report = [f"# Robustness (rotation about {cfg.rotation_axis}; "
              f"augment_rotation={bool(cfg.augment_rotation)})"]
    seed, batch = int(cfg.seed), int(cfg.eval_batch_points)
    for kind in kinds:
        model, data, info = _model_for(cfg, ctx, kind)
        metrics[f"{kind}_model"] = info["source"]
        metrics[f"{kind}_selected_on"] = info["selected_on"]          # val, or unknown for an older best.pt
        if "val_accuracy" in info:
            metrics[f"{kind}_val_accuracy"] = info["val_accuracy"]
            metrics["selected_on"] = info["selected_on"]
        rot_rows, pts_rows = {}, {}
        metrics[f"{kind}_n_params"] = sum(p.numel() for p in model.parameters())
        with torch.no_grad():  # cost per cloud: one pass over every test cloud, all its points
            t0 = time.perf_counter()
            evaluate(model, data.test, kind, ctx.device, 0, seed, batch_points=batch)
            metrics[f"{kind}_ms_per_cloud"] = round(1000 * (time.perf_counter() - t0) / len(data.test), 3)
        with ctx.stopwatch.stage(f"{kind}_tables"):
            mats = rotations(str(cfg.rotation_axis), degrees)
            rows = []
            for d, mat in zip(degrees, mats):
                ev = evaluate(model, data.test, kind, ctx.device, int(cfg.rotation_points), seed,
                              rotation=mat, batch_points=batch)
                acc = ev.accuracy
                if int(cfg.rotation_pictures) > 0:
                    rows.append(_rotation_row(cfg, ctx, ev, kind, data, d))
                rot_rows[f"{d:g}"] = acc
                metrics[f"{kind}_rot{d:g}"] = acc
                ctx.logger.scalar(f"robustness/{kind}_accuracy_vs_degrees", acc, int(round(d)))
            for n in counts:
                acc = float("nan")
                if n <= data.test.num_points:
                    acc = evaluate(model, data.test, kind, ctx.device, n, seed, batch_points=batch).accuracy
                pts_rows[str(n)] = acc
                metrics[f"{kind}_pts{n}"] = acc
                ctx.logger.scalar(f"robustness/{kind}_accuracy_vs_points", acc, n)
        if rows:
            save_png(ctx.path(f"rotation_{kind}.png"), torch.cat(rows, dim=0))
        metrics["tables"][kind] = {"rotation": rot_rows, "num_points": pts_rows}
        metrics[f"{kind}_seconds"] = ctx.stopwatch.stages[f"{kind}_tables"] + info.get("train_seconds", 0.0)
        name = "classification" if kind == "cls" else "segmentation (point)"
        report += [f"\n## {name} ({metrics[f'{kind}_n_params']} parameters, "
                   f"{metrics[f'{kind}_ms_per_cloud']} ms per test cloud)\n", _table(name, "degrees", rot_rows), "",
                   _table(name, "points", pts_rows)]
    text = "\n".join(report) + "\n"
    ctx.path("robustness.md").write_text(text)
    for table, xlabel, fname in (("rotation", f"rotation about {cfg.rotation_axis} (degrees)", "robustness_rotation.png"),
                                 ("num_points", "points per test cloud", "robustness_points.png")):
        curves = {k: ([float(x) for x in rows], list(rows.values())) for k, t in metrics["tables"].items()
                  for rows in [{x: v for x, v in t[table].items() if v == v}]}
        line_plot(ctx.path(fname), curves, xlabel=xlabel, ylabel="test accuracy (seg: per point)",
                  logx=table == "num_points", title="pointnet_robustness")
    ctx.logger.text("robustness/tables", text)
    if "cls" in kinds:
        metrics["accuracy"] = metrics[f"cls_rot{degrees[0]:g}"] if degrees else float("nan")
    return metrics
