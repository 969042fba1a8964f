"""Shared machinery of the point-cloud learning tasks (pointnet_cls, pointnet_seg, robustness).

``kind`` is 'cls' (one label per cloud, logits (B, K)) or 'seg' (one part per point,
logits (B, N, K)). Training runs through the shared loop
(:func:`l3d_app.runtime.training.train`) and adds, around it:

* epochs: step ``s`` belongs to epoch ``s // steps_per_epoch``; each epoch visits the
  training clouds in a permutation fixed by (seed, epoch), and each visit uses a random
  ``train_points`` subset of the cloud's points (seeded by (seed, step, rank)), so a
  resumed run draws exactly the batches an uninterrupted one would;
* best-checkpoint keeping on VALIDATION: every ``eval_every_epochs`` epochs the accuracy on
  a fixed ``eval_points`` subset of every validation cloud (``data.val_fraction`` of the
  training clouds, carved by the dataset) is logged as ``val/accuracy`` and, when it is the
  best so far, the model is written to ``best.pt`` (self-contained: model config, label
  names, weights);
* data parallelism: under ``torchrun`` each rank takes its share of every global batch
  and the model is wrapped in DistributedDataParallel; rank 0 evaluates and writes the
  artefacts, other ranks write only into ``rank<r>/`` (their checkpoints, for resume).

The test split is read ONCE, after training: the selected model (``best.pt`` with
``use_best``, else the last weights) on ``test_points`` points of every test cloud
(0 = all points), logged as ``test/...``; metrics.json carries ``accuracy`` (test),
``val_accuracy`` (the selected model's) and ``"selected_on": "val"``.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence, Tuple

import numpy as np
import torch
import torch.nn.functional as F
from omegaconf import OmegaConf

from l3d_app.data.point_sets import PointCloudData, PointSplit
from l3d_app.errors import UserError
from l3d_app.geometry.camera_paths import turntable
from l3d_app.geometry.pointcloud import PointCloud
from l3d_app.geometry.transforms import axis_rotation
from l3d_app.metrics.accuracy import accuracy, confusion_matrix
from l3d_app.registry import DATASETS, MODELS, RENDERERS
from l3d_app.render.charts import confusion_image
from l3d_app.render.palette import palette
from l3d_app.runtime import distributed
from l3d_app.runtime.budget import TimeBudget
from l3d_app.runtime.files import atomic_path
from l3d_app.runtime.media import save_gif, save_png
from l3d_app.runtime.torch_files import read_torch_file
from l3d_app.runtime.training import LoopSpec, Trainable, log_test, train
from l3d_app.tasks.common import check_output_knobs, require_nonnegative, require_positive

BEST = "best.pt"


# ----------------------------------------------------------------------------- data

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


def subsample_index(num_clouds: int, total: int, n: int, generator: torch.Generator) -> torch.Tensor:
    """(num_clouds, n) long indices of ``n`` distinct points per cloud out of ``total``
    (all points, in order, when ``n`` is 0 or >= ``total``)."""
    if n <= 0 or n >= total:
        return torch.arange(total).expand(num_clouds, total)
    return torch.rand(num_clouds, total, generator=generator).argsort(dim=1)[:, :n]


def gather_points(points: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """points (B, P, C) or (B, P) gathered at index (B, n) -> (B, n, C) or (B, n)."""
    if points.dim() == 2:
        return torch.gather(points, 1, index)
    return torch.gather(points, 1, index[..., None].expand(-1, -1, points.shape[-1]))


def require_axis(axis) -> str:
    """``axis`` as 'x', 'y' or 'z', or :class:`UserError`."""
    if axis not in ("x", "y", "z"):
        raise UserError(f"rotation axis must be x, y or z, got {axis!r}")
    return axis


def rotations(axis: str, degrees: Sequence[float]) -> torch.Tensor:
    """(B, 3, 3) rotations by ``degrees[b]`` about the world ``axis`` ('x', 'y' or 'z')."""
    require_axis(axis)
    return torch.stack([axis_rotation(axis, float(d)) for d in degrees])


def rotate(points: torch.Tensor, rot: torch.Tensor) -> torch.Tensor:
    """Rotate (B, N, 3) points by (B, 3, 3) or (3, 3) matrices (column vectors: x -> R x)."""
    return points @ rot.transpose(-1, -2)


# ----------------------------------------------------------------------------- models

def build_model(model_cfg, kind: str, num_outputs: int, device) -> torch.nn.Module:
    """The configured model (``model=pointnet|dgcnn``) for ``kind`` with ``num_outputs``."""
    return MODELS.build(model_cfg, task=kind, num_outputs=int(num_outputs), device=device)


def n_params(model: torch.nn.Module) -> int:
    return sum(p.numel() for p in model.parameters())


def save_best(path: Path, model: torch.nn.Module, meta: Dict[str, Any]) -> None:
    """Write a self-contained model checkpoint (weights + what rebuilds the model)."""
    with atomic_path(path) as tmp:
        torch.save({"state": model.state_dict(), **meta}, tmp)


def load_model(path, device) -> Tuple[torch.nn.Module, Dict[str, Any]]:
    """Rebuild the model stored by :func:`save_best` at ``path``; returns (model, meta)."""
    path = Path(str(path)).expanduser()
    if not path.is_file():
        raise UserError(f"model checkpoint not found: {path}")
    meta = read_torch_file(path, "pointnet best.pt checkpoint")
    if not isinstance(meta, dict) or "model_cfg" not in meta:
        raise UserError(f"{path} is not a pointnet_cls/pointnet_seg best.pt checkpoint")
    model = build_model(meta["model_cfg"], meta["kind"], len(meta["names"]), device)
    model.load_state_dict(meta.pop("state"))
    return model.eval(), meta


@torch.no_grad()
def predict(model: torch.nn.Module, points: torch.Tensor, device, batch_points: int = 65536,
            rotation: Optional[torch.Tensor] = None) -> torch.Tensor:
    """Predicted labels for CPU points (N, P, 3): (N,) for a classifier, (N, P) for a
    segmenter; clouds go through the model (eval mode) ``batch_points // P`` at a time,
    rotated first by ``rotation`` (3, 3) if given."""
    was_training = model.training
    model.eval()
    per_batch = max(1, int(batch_points) // max(1, points.shape[1]))
    out = []
    for s in range(0, points.shape[0], per_batch):
        x = points[s:s + per_batch].to(device)
        if rotation is not None:
            x = rotate(x, rotation.to(x))
        out.append(model(x)["logits"].argmax(-1).cpu())
    model.train(was_training)
    return torch.cat(out)


@dataclass
class Evaluation:
    """Predictions on a test split: ``pred``/``target`` (N,) or (N, n), the points used
    (N, n, 3), and the accuracy (fraction; point accuracy for segmentation)."""

    points: torch.Tensor
    pred: torch.Tensor
    target: torch.Tensor
    accuracy: float


def evaluate(model, split: PointSplit, kind: str, device, num_points: int = 0, seed: int = 0,
             rotation: Optional[torch.Tensor] = None, batch_points: int = 65536) -> Evaluation:
    """Evaluate on ``num_points`` points of every cloud of ``split`` (0: all), the subset
    fixed by ``seed``; ``rotation`` (3, 3) rotates the clouds first."""
    gen = torch.Generator().manual_seed(int(seed))
    idx = subsample_index(len(split), split.num_points, int(num_points), gen)
    pts = gather_points(split.points, idx)
    target = split.targets(kind)
    if kind == "seg":
        target = gather_points(target, idx)
    pred = predict(model, pts, device, batch_points, rotation)
    return Evaluation(pts if rotation is None else rotate(pts, rotation), pred, target,
                      accuracy(pred, target))


# ----------------------------------------------------------------------------- training

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


# The test pass against the validations that price it: pointnet_seg at time_budget=60 on 2 AVX2 cores
# (2026-11-28, four runs without the margin) spent 0.93-1.27x the seconds the loop had left for it
# after its final validation, on a pass of 24 validations' points; the margin covers most of that
# spread (a budget stop comes a few steps earlier instead of 1-4 s late).
TEST_PASS_MARGIN = 1.25


def evals_in_the_test_pass(cfg, data: PointCloudData) -> float:
    """The test pass in validations: test clouds x ``test_points`` (0: all) over val clouds x
    ``eval_points``, times :data:`TEST_PASS_MARGIN` (what the loop keeps time for under a budget;
    the pictures take what is left)."""
    test_pts = min(int(cfg.test_points) or data.test.num_points, data.test.num_points)
    val_pts = min(int(cfg.eval_points), data.val.num_points)
    return TEST_PASS_MARGIN * len(data.test) * test_pts / max(1, len(data.val) * val_pts)


def fit(cfg, ctx, data: PointCloudData, kind: str, dist: Optional[distributed.Dist] = None):
    """Train the configured model for ``kind`` on ``data`` (see module docstring).

    Returns (model with the selected weights loaded, info dict: n_params, iters, epochs,
    best_epoch, val_accuracy (of the selected model), last_val_accuracy, selected_on,
    history (val figures per evaluation), train_seconds, interrupted).
    """
    check_train_knobs(cfg)
    dist = dist or distributed.Dist()
    device = ctx.device
    train_split = data.train
    targets = train_split.targets(kind)
    names = data.names(kind)
    seed = int(cfg.seed)
    torch.manual_seed(seed)  # same initial weights on every rank
    model = build_model(cfg.model, kind, len(names), device)
    net = distributed.wrap(model, dist, device)
    opt = torch.optim.Adam(model.parameters(), lr=float(cfg.lr), weight_decay=float(cfg.weight_decay))
    batch = int(cfg.batch_size)
    if batch < dist.world:
        raise UserError(f"batch_size={batch} is smaller than the number of processes ({dist.world})")
    steps_per_epoch = math.ceil(len(train_split) / batch)
    iters = int(cfg.iters) if cfg.get("iters") else int(cfg.epochs) * steps_per_epoch
    sched = torch.optim.lr_scheduler.LambdaLR(
        opt, lambda s: 0.5 * (1 + math.cos(math.pi * min(s, iters) / iters)) * 0.98 + 0.02)
    best = torch.tensor([-1.0, -1.0])  # (accuracy, epoch), checkpointed with the run
    trainable = Trainable({"model": model}, opt, extra={"best": best}, schedulers=[sched])
    n_sub = int(cfg.train_points)
    axis = str(cfg.rotation_axis)
    aug_deg = float(cfg.augment_degrees) if cfg.augment_rotation else 0.0
    jitter = float(cfg.get("jitter", 0.0) or 0.0)
    reg_weight = float(cfg.get("regulariser_weight", 0.001))

    def step_fn(step: int) -> Dict[str, torch.Tensor]:
        epoch, pos = divmod(step, steps_per_epoch)
        perm = torch.randperm(len(train_split), generator=torch.Generator().manual_seed(seed * 1_000_003 + epoch))
        chosen = perm[(torch.arange(batch) + pos * batch) % len(train_split)][dist.rank::dist.world]
        gen = torch.Generator().manual_seed((seed * 7919 + step) * 64 + dist.rank)
        idx = subsample_index(len(chosen), train_split.num_points, n_sub, gen)
        pts = gather_points(train_split.points[chosen], idx)
        tgt = targets[chosen] if kind == "cls" else gather_points(targets[chosen], idx)
        if aug_deg > 0:
            angles = (torch.rand(len(chosen), generator=gen) * 2 - 1) * aug_deg
            pts = rotate(pts, rotations(axis, angles.tolist()))
        if jitter > 0:
            pts = pts + jitter * torch.randn(pts.shape, generator=gen)
        out = net(pts.to(device))
        logits, tgt = out["logits"], tgt.to(device)
        loss = F.cross_entropy(logits.reshape(-1, logits.shape[-1]), tgt.reshape(-1))
        if "regulariser" in out:
            loss = loss + reg_weight * out["regulariser"]
        return {"loss": loss, "accuracy": (logits.detach().argmax(-1) == tgt).float().mean()}

    meta = {"model_cfg": OmegaConf.to_container(cfg.model, resolve=True), "kind": kind,
            "names": names, "source": data.source}
    eval_points = int(cfg.eval_points)

    def eval_fn(step: int) -> Dict[str, float]:
        """Validation only (the test split is read once, by the caller, after training)."""
        if not dist.is_main:
            return {}
        epoch = step / steps_per_epoch
        acc = evaluate(model, data.val, kind, device, eval_points, seed,
                       batch_points=int(cfg.eval_batch_points)).accuracy
        if acc > float(best[0]):
            best[0], best[1] = acc, epoch
            save_best(ctx.path(BEST), model, {**meta, "epoch": epoch, "accuracy": acc, "selected_on": "val"})
        return {"accuracy": acc, "epoch": epoch}

    spe_eval = steps_per_epoch * int(cfg.eval_every_epochs)
    with ctx.stopwatch.stage("train"):
        spec = LoopSpec(iters, spe_eval, steps_per_epoch * int(cfg.checkpoint_every_epochs or 0), bool(cfg.resume),
                        f"pointnet_{kind}")
        result = train(ctx, trainable, step_fn, spec, eval_fn, TimeBudget.of(ctx, evals_after=evals_in_the_test_pass(cfg, data)))
    use_best = bool(cfg.use_best) and dist.is_main and ctx.path(BEST).exists()
    if use_best:
        model.load_state_dict(torch.load(ctx.path(BEST), map_location="cpu", weights_only=False)["state"])
    model.eval()
    last = float(result.metrics.get("accuracy", float("nan")))
    info = {"n_params": n_params(model), "iters": result.step, "epochs": result.step / steps_per_epoch,
            "best_epoch": float(best[1]) if use_best else result.step / steps_per_epoch,
            "val_accuracy": round(float(best[0]) if use_best else last, 5),
            "last_val_accuracy": round(last, 5),
            "selected_on": "val" if use_best else "last",
            "n_val": len(data.val), "history": result.history_rows(),
            "train_seconds": result.train_seconds, "interrupted": result.interrupted}
    return model, info


# ----------------------------------------------------------------------------- pictures

def _safe(name: str) -> str:
    """A label usable in a file name ('chair/seat' -> 'chair-seat')."""
    return "".join(ch if ch.isalnum() or ch in "._-" else "-" for ch in str(name))


class Turntable:
    """Renders point clouds as turntable frames with the run's point renderer."""

    def __init__(self, cfg, device):
        self.renderer = RENDERERS.build(cfg.point_renderer)
        self.cams = turntable(int(cfg.num_frames), float(cfg.distance), float(cfg.elevation),
                              float(cfg.fov), int(cfg.image_size), device=device)
        self.max_points = int(cfg.vis_points)
        self.device = device

    def __call__(self, points: torch.Tensor, colors: torch.Tensor) -> torch.Tensor:
        """points (P, 3), colors (P, 3) -> frames (F, H, W, 3) on the CPU (cloud normalised)."""
        keep = torch.randperm(points.shape[0], generator=torch.Generator().manual_seed(0))[:self.max_points]
        cloud = PointCloud(points[keep].float(), colors=colors[keep].float()).normalized().to(self.device)
        return self.renderer(cloud, self.cams)["image"].cpu()


def write_visuals(cfg, ctx, ev: Evaluation, kind: str, names: List[str],
                  class_of: Optional[torch.Tensor], class_names: List[str]) -> Dict[str, Any]:
    """Confusion matrix PNG, gifs of random test clouds coloured by prediction (seg: truth |
    prediction side by side) and of one failure per class. Returns counts for metrics."""
    k = len(names)
    cm = confusion_matrix(ev.pred, ev.target, k)
    image = confusion_image(cm, names, f"pointnet_{kind}: test accuracy {ev.accuracy:.4f}")
    save_png(ctx.path("confusion_matrix.png"), image)
    ctx.logger.image("test/confusion_matrix", image)
    if int(cfg.num_vis) <= 0 and not cfg.vis_failures:
        return {}
    left = ctx.seconds_left()
    if left is not None and left <= 0:         # gifs are previews: under a spent budget, none
        ctx.logger.text("test/gifs", f"time budget {ctx.time_budget:g} s: spent before the gifs (not written)")
        return {"gifs_skipped": True}
    colors = palette(k)
    table = Turntable(cfg, ctx.device)

    def gif(name: str, i: int) -> None:
        if kind == "cls":
            frames = table(ev.points[i], colors[ev.pred[i]].expand(ev.points.shape[1], 3))
        else:
            frames = torch.cat([table(ev.points[i], colors[ev.target[i]]),
                                table(ev.points[i], colors[ev.pred[i]])], dim=2)
        save_gif(ctx.path(name), frames, fps=float(cfg.fps))

    gen = torch.Generator().manual_seed(int(cfg.seed))
    chosen = torch.randperm(ev.pred.shape[0], generator=gen)[:int(cfg.num_vis)].tolist()
    jobs = []                                   # (file name, cloud index, is a failure gif)
    for n, i in enumerate(chosen):
        truth = class_names[int(class_of[i])] if class_of is not None else "cloud"
        pred = names[int(ev.pred[i])] if kind == "cls" else f"acc{float((ev.pred[i] == ev.target[i]).float().mean()):.3f}"
        jobs.append((f"vis/sample{n}_{_safe(truth)}_pred-{_safe(pred)}.gif", i, False))
    if cfg.vis_failures:
        groups = class_of if class_of is not None else torch.zeros(ev.pred.shape[0], dtype=torch.long)
        for c in torch.unique(groups).tolist():
            members = torch.nonzero(groups == c).squeeze(1)
            if kind == "cls":
                wrong = members[ev.pred[members] != ev.target[members]]
                if wrong.numel() == 0:
                    continue
                i = int(wrong[0])
                label = f"{class_names[c]}_as_{names[int(ev.pred[i])]}"
            else:
                acc = (ev.pred[members] == ev.target[members]).float().mean(1)
                i = int(members[acc.argmin()])
                label = f"{class_names[c] if class_of is not None else 'worst'}_acc{float(acc.min()):.3f}"
            jobs.append((f"vis/failure_{_safe(label)}.gif", i, True))
    written, last = [], 0.0
    for name, i, failure in jobs:     # under a budget, each gif only while the last one's cost still fits
        left = ctx.seconds_left()
        if left is not None and left < last:
            ctx.logger.text("test/gifs", f"time budget {ctx.time_budget:g} s: {len(written)} of {len(jobs)} gifs "
                                         f"fit ({left:.1f} s left at {last:.2f} s per gif)")
            break
        t0 = time.perf_counter()
        gif(name, i)
        last = time.perf_counter() - t0
        written.append(failure)
    return {"n_vis": written.count(False), "n_failure_gifs": written.count(True)}


# ----------------------------------------------------------------------------- task

def per_label_accuracy(ev: Evaluation, names: List[str], kind: str) -> Dict[str, float]:
    """Accuracy per true class (cls) and IoU per part plus their mean ``miou`` (seg)."""
    out = {}
    k = len(names)
    cm = confusion_matrix(ev.pred, ev.target, k).double()
    if kind == "cls":
        for c in range(k):
            if cm[c].sum() > 0:
                out[f"accuracy_{names[c]}"] = float(cm[c, c] / cm[c].sum())
    else:
        ious = []
        for c in range(k):
            union = cm[c].sum() + cm[:, c].sum() - cm[c, c]
            if union > 0:
                ious.append(float(cm[c, c] / union))
                out[f"iou_{names[c].replace('/', '_')}"] = ious[-1]
        out["miou"] = float(np.mean(ious)) if ious else float("nan")
    return out


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
        model, info = fit(cfg, ctx, data, kind, dist)
        metrics: Dict[str, Any] = {**info, "n_train": len(data.train), "n_test": len(data.test),
                                   "world_size": dist.world, "data": data.source}
        if not dist.is_main or info["interrupted"]:  # a stopped run keeps its figures so far
            return metrics
        names = data.names(kind)
        with ctx.stopwatch.stage("test"):
            ev = evaluate(model, data.test, kind, ctx.device, int(cfg.test_points), int(cfg.seed),
                          batch_points=int(cfg.eval_batch_points))
        test_figures = {"accuracy": ev.accuracy, **per_label_accuracy(ev, names, kind)}
        metrics.update(test_figures, test_points=int(ev.points.shape[1]),
                       test_seconds=ctx.stopwatch.stages["test"])
        log_test(ctx, test_figures, info["iters"])
        ctx.logger.text("test/summary", f"test accuracy {ev.accuracy:.4f} on {len(data.test)} clouds "
                                        f"x {ev.points.shape[1]} points")
        with ctx.stopwatch.stage("visuals"):
            metrics.update(write_visuals(cfg, ctx, ev, kind, names, data.test.labels, data.class_names))
        return metrics
    finally:
        distributed.teardown(dist)
