"""Config glue of the point-cloud tasks (pointnet_cls, pointnet_seg, pointnet_robustness).

The training, evaluation and best-model keeping are :mod:`l3d_app.pipelines.point_nets`, the
pictures :mod:`l3d_app.pipelines.point_visuals`. Splits: ``best.pt`` is chosen on the validation
clouds (``data.val_fraction`` of the training clouds, carved by the dataset); the test split is
read ONCE, after training: the selected model (``best.pt`` with ``use_best``, else the last weights)
on ``test_points`` points of every test cloud (0 = all points), logged as ``test/...``;
metrics.json carries ``accuracy`` (test), ``val_accuracy`` (the selected model's) and
``"selected_on": "val"``. Under ``torchrun`` rank 0 evaluates and writes the artefacts, other ranks
write only into ``rank<r>/`` (their checkpoints, for resume).
"""

from __future__ import annotations

from typing import Any, Dict

from omegaconf import OmegaConf

from l3d_app.data.point_sets import PointCloudData
from l3d_app.errors import UserError
from l3d_app.geometry.camera_paths import turntable as orbit
from l3d_app.metrics.accuracy import per_label_accuracy
from l3d_app.pipelines.point_nets import PointTraining, evaluate, fit, require_axis
from l3d_app.pipelines.point_visuals import Turntable, write_visuals
from l3d_app.registry import DATASETS, RENDERERS
from l3d_app.runtime import distributed
from l3d_app.runtime.budget import TimeBudget
from l3d_app.runtime.training import log_test
from l3d_app.tasks.common import check_output_knobs, require_nonnegative, require_positive


def load_data(cfg, kind: str) -> PointCloudData:
    """The configured data source, checked to carry the labels ``kind`` needs."""
    data = DATASETS.build(cfg.data, kind=kind)
    if data.val is None:
        raise UserError(f"the {data.source} dataset has no validation split")
    for split in (data.train, data.val, data.test):
        split.targets(kind)
        if len(split) == 0:
            raise UserError(f"the {data.source} dataset has an empty split "
                            f"(train {len(data.train)}, val {len(data.val)}, test {len(data.test)}); "
                            f"raise data.val_fraction or the number of clouds")
    return data


def check_train_knobs(cfg) -> None:
    """Sizes and rates > 0; counts where 0 means all / off (``test_points``, checkpoints), the
    augmentation amounts and the weights >= 0 (a negative regulariser weight would reward it)."""
    require_positive(cfg, "batch_size", "lr", "train_points", "eval_every_epochs", "eval_points", "eval_batch_points")
    require_nonnegative(cfg, *(k for k in ("test_points", "checkpoint_every_epochs", "augment_degrees", "jitter",
                                           "regulariser_weight", "weight_decay", "num_vis", "vis_points") if k in cfg))
    if cfg.get("iters") is None:
        require_positive(cfg, "epochs")
    require_axis(cfg.rotation_axis)
    check_output_knobs(cfg)


def training_spec(cfg) -> PointTraining:
    """The trainer's knobs of a point task's config (:class:`~l3d_app.pipelines.point_nets.PointTraining`)."""
    check_train_knobs(cfg)
    return PointTraining(
        model_cfg=OmegaConf.to_container(cfg.model, resolve=True), lr=float(cfg.lr),
        weight_decay=float(cfg.weight_decay), batch_size=int(cfg.batch_size), epochs=int(cfg.get("epochs") or 0),
        iters=int(cfg.iters) if cfg.get("iters") else None, train_points=int(cfg.train_points),
        rotation_axis=str(cfg.rotation_axis),
        augment_degrees=float(cfg.augment_degrees) if cfg.augment_rotation else 0.0,
        jitter=float(cfg.get("jitter", 0.0) or 0.0), regulariser_weight=float(cfg.get("regulariser_weight", 0.001)),
        eval_every_epochs=int(cfg.eval_every_epochs), checkpoint_every_epochs=int(cfg.checkpoint_every_epochs or 0),
        eval_points=int(cfg.eval_points), eval_batch_points=int(cfg.eval_batch_points),
        test_points=int(cfg.test_points), use_best=bool(cfg.use_best), resume=bool(cfg.resume), seed=int(cfg.seed))


def turntable(cfg, ctx) -> Turntable:
    """The test gifs' turntable: ``point_renderer`` on ``num_frames`` cameras orbiting at ``distance``,
    ``elevation``, ``fov``, ``image_size``, at most ``vis_points`` points a cloud."""
    cams = orbit(int(cfg.num_frames), float(cfg.distance), float(cfg.elevation), float(cfg.fov), int(cfg.image_size),
                 device=ctx.device)
    return Turntable(RENDERERS.build(cfg.point_renderer), cams, int(cfg.vis_points), ctx.device)


def run_point_task(cfg, ctx, kind: str) -> Dict[str, Any]:
    """pointnet_cls / pointnet_seg: train (or resume), evaluate, visualise; the metrics."""
    check_train_knobs(cfg)
    dist = distributed.setup(ctx.device)
    try:
        ctx.device = distributed.device_for(dist, ctx.device)
        if not dist.is_main:  # other ranks: own folder, no TensorBoard
            ctx.out_dir = ctx.out_dir / f"rank{dist.rank}"
            ctx.out_dir.mkdir(parents=True, exist_ok=True)
            ctx.logger.close()
        data = load_data(cfg, kind)
        model, info = fit(training_spec(cfg), ctx, data, kind, dist)
        metrics: Dict[str, Any] = {**info, "n_train": len(data.train), "n_test": len(data.test),
                                   "world_size": dist.world, "data": data.source}
        if not dist.is_main or info["interrupted"]:  # a stopped run keeps its figures so far
            return metrics
        names = data.names(kind)
        with ctx.stopwatch.stage("test"):
            ev = evaluate(model, data.test, kind, ctx.device, int(cfg.test_points), int(cfg.seed),
                          batch_points=int(cfg.eval_batch_points))
        test_figures = {"accuracy": ev.accuracy, **per_label_accuracy(ev.pred, ev.target, names, kind)}
        metrics.update(test_figures, test_points=int(ev.points.shape[1]),
                       test_seconds=ctx.stopwatch.stages["test"])
        log_test(ctx, test_figures, info["iters"])
        ctx.logger.text("test/summary", f"test accuracy {ev.accuracy:.4f} on {len(data.test)} clouds "
                                        f"x {ev.points.shape[1]} points")
        with ctx.stopwatch.stage("visuals"):
            metrics.update(write_visuals(ctx, ev, kind, names, data.test.labels, data.class_names, turntable(cfg, ctx),
                                         int(cfg.num_vis), bool(cfg.vis_failures), float(cfg.fps), int(cfg.seed),
                                         TimeBudget.of(ctx)))
        return metrics
    finally:
        distributed.teardown(dist)
