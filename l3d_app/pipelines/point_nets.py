"""Point-cloud networks (pointnet_cls, pointnet_seg, pointnet_robustness): training, evaluation, the best model.

``kind`` is 'cls' (one label per cloud, logits (B, K)) or 'seg' (one part per point, logits
(B, N, K)). :func:`fit` trains through the shared loop (:func:`l3d_app.runtime.training.train`)
and adds, around it:

* epochs: step ``s`` belongs to epoch ``s // steps_per_epoch``; each epoch visits the training
  clouds in a permutation fixed by (seed, epoch), and each visit uses a random ``train_points``
  subset of the cloud's points (seeded by (seed, step, rank)), so a resumed run draws exactly the
  batches an uninterrupted one would;
* best-model keeping on VALIDATION: every ``eval_every_epochs`` epochs the accuracy on a fixed
  ``eval_points`` subset of every validation cloud is logged as ``val/accuracy`` and, when it is the
  best so far, the model is written to ``best.pt`` (self-contained: model config, label names,
  weights);
* data parallelism: under ``torchrun`` each rank takes its share of every global batch and the
  model is wrapped in DistributedDataParallel; rank 0 evaluates.

The test split is read once, by the task, after :func:`fit` returns (:func:`evaluate`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Dict, Mapping, Optional, Sequence, Tuple

import torch
import torch.nn.functional as F

from l3d_app.data.point_sets import PointCloudData, PointSplit
from l3d_app.errors import UserError
from l3d_app.geometry.transforms import axis_rotation
from l3d_app.metrics.accuracy import accuracy
from l3d_app.registry import MODELS
from l3d_app.runtime import distributed
from l3d_app.runtime.budget import TimeBudget
from l3d_app.runtime.files import atomic_path
from l3d_app.runtime.torch_files import read_torch_file
from l3d_app.runtime.training import LoopSpec, Trainable, train

BEST = "best.pt"
TEST_PASS_MARGIN = 1.25   # a test pass takes up to this x its points' share of a validation's seconds


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


@dataclass
class PointTraining:
    """How :func:`fit` trains (a task's knobs, plain).

    Args:
        model_cfg: the model's config (``MODELS`` entry: ``name`` and its parameters).
        lr, weight_decay: Adam's rate (cosine-decayed to 2% over the run) and weight decay.
        batch_size: clouds per global step; epochs / iters: the run's length (``iters`` wins when set).
        train_points: points subsampled per cloud per step.
        augment_degrees: random rotations about ``rotation_axis`` in [-this, this] (0: none).
        jitter: std of Gaussian noise added to training points (world units).
        regulariser_weight: weight of the model's regulariser (feature-transform orthogonality).
        eval_every_epochs, checkpoint_every_epochs: epochs between validations / checkpoints.
        eval_points, eval_batch_points: points per validation cloud, points per forward pass.
        test_points: points per test cloud of the task's test pass (0: all; priced by the budget).
        use_best: the returned model is the best on validation (else the last).
    """

    model_cfg: Mapping[str, Any]
    lr: float = 0.001
    weight_decay: float = 0.0
    batch_size: int = 32
    epochs: int = 5
    iters: Optional[int] = None
    train_points: int = 512
    rotation_axis: str = "z"
    augment_degrees: float = 0.0
    jitter: float = 0.0
    regulariser_weight: float = 0.001
    eval_every_epochs: int = 1
    checkpoint_every_epochs: int = 1
    eval_points: int = 1024
    eval_batch_points: int = 65536
    test_points: int = 0
    use_best: bool = True
    resume: bool = False
    seed: int = 0


def evals_in_the_test_pass(spec: PointTraining, data: PointCloudData) -> Tuple[float, float]:
    """(the test pass's points, a validation's points): test clouds x ``test_points`` (0: all), val
    clouds x ``eval_points``."""
    test_pts = min(int(spec.test_points) or data.test.num_points, data.test.num_points)
    val_pts = min(int(spec.eval_points), data.val.num_points)
    return len(data.test) * test_pts, len(data.val) * val_pts


def fit(spec: PointTraining, ctx, data: PointCloudData, kind: str, dist: Optional[distributed.Dist] = None):
    """Train the network for ``kind`` on ``data`` (see the module docstring).

    Returns (model with the selected weights loaded, info dict: n_params, iters, epochs,
    best_epoch, val_accuracy (of the selected model), last_val_accuracy, selected_on,
    history (val figures per evaluation), train_seconds, interrupted).
    """
    dist = dist or distributed.Dist()
    device, train_split = ctx.device, data.train
    targets, names, seed = train_split.targets(kind), data.names(kind), int(spec.seed)
    torch.manual_seed(seed)  # same initial weights on every rank
    model = build_model(spec.model_cfg, kind, len(names), device)
    net = distributed.wrap(model, dist, device)
    opt = torch.optim.Adam(model.parameters(), lr=float(spec.lr), weight_decay=float(spec.weight_decay))
    batch = int(spec.batch_size)
    if batch < dist.world:
        raise UserError(f"batch_size={batch} is smaller than the number of processes ({dist.world})")
    steps_per_epoch = math.ceil(len(train_split) / batch)
    iters = int(spec.iters) if spec.iters else int(spec.epochs) * steps_per_epoch
    sched = torch.optim.lr_scheduler.LambdaLR(
        opt, lambda s: 0.5 * (1 + math.cos(math.pi * min(s, iters) / iters)) * 0.98 + 0.02)
    best = torch.tensor([-1.0, -1.0])  # (accuracy, epoch), checkpointed with the run
    trainable = Trainable({"model": model}, opt, extra={"best": best}, schedulers=[sched])
    n_sub, axis, aug_deg = int(spec.train_points), str(spec.rotation_axis), float(spec.augment_degrees)
    jitter, reg_weight = float(spec.jitter or 0.0), float(spec.regulariser_weight)

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

    meta = {"model_cfg": dict(spec.model_cfg), "kind": kind, "names": names, "source": data.source}

    def eval_fn(step: int) -> Dict[str, float]:
        """Validation only (the test split is read once, by the caller, after training)."""
        if not dist.is_main:
            return {}
        epoch = step / steps_per_epoch
        acc = evaluate(model, data.val, kind, device, int(spec.eval_points), seed,
                       batch_points=int(spec.eval_batch_points)).accuracy
        if acc > float(best[0]):
            best[0], best[1] = acc, epoch
            save_best(ctx.path(BEST), model, {**meta, "epoch": epoch, "accuracy": acc, "selected_on": "val"})
        return {"accuracy": acc, "epoch": epoch}

    loop = LoopSpec(iters, steps_per_epoch * int(spec.eval_every_epochs),
                    steps_per_epoch * int(spec.checkpoint_every_epochs or 0), bool(spec.resume), f"pointnet_{kind}")
    budget = TimeBudget.of(ctx).keep_renders(*evals_in_the_test_pass(spec, data), margin=TEST_PASS_MARGIN)
    with ctx.stopwatch.stage("train"):
        result = train(ctx, trainable, step_fn, loop, eval_fn, budget)
    use_best = bool(spec.use_best) and dist.is_main and ctx.path(BEST).exists()
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
