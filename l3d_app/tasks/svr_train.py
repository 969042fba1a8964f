"""svr_train: train an image -> 3D model (``encoder=cnn|resnet18`` + ``decoder=vox|point|mesh|implicit|pseudo``).

``encoder=resnet18`` is the course's encoder (ResNet-18 without its classifier, 512 features,
:mod:`l3d_app.models.resnet_encoder`), randomly initialised or, with ``encoder_weights=FILE``
(``encoder.weights=FILE``), started from a local state dict; nothing is downloaded.

Each step draws ``batch_size`` (object, view) pairs from the training objects (the run's
seeded generator, so a resumed run draws what an uninterrupted one would), encodes the
images and minimises the decoder's loss (:mod:`l3d_app.losses.svr`) with Adam
(cosine-decayed to ``lr_floor`` x ``lr``). Every ``eval_every`` steps F1@0.05 and chamfer
on ``quick_eval_objects`` VALIDATION objects (``data.val_fraction`` of the training
objects) are logged (``val/...``) against step and wall time. Runs through the shared loop
(checkpoints, ``resume=true``, NaN guard). The model kept is the last one (nothing is
chosen).

At the end it writes ``svr_model.pt`` (self-contained: ``task=svr_eval checkpoint=...``)
and, with ``eval_at_end`` (default), evaluates the TEST objects once (as ``svr_eval``
does) into the same folder: f1_curve.png, predictions.png/.gif, metrics.json with ``f1``
(= F1@0.05 on test), the F1 curve, chamfer, seconds per image, ``val_f1`` /
``val_chamfer`` (the last validation) and the val-only ``history``.
"""

from __future__ import annotations

import torch

from l3d_app.errors import UserError
from l3d_app.losses.svr import svr_loss
from l3d_app.metrics.f1_curve import f1_table
from l3d_app.models.resnet_encoder import load_resnet18_weights
from l3d_app.models.svr_model import MODEL_FILE, build_svr_model, n_params, save_svr_model
from l3d_app.pipelines.svr import geometry_of, make_batch, predict_points
from l3d_app.registry import TASKS
from l3d_app.runtime.budget import TimeBudget
from l3d_app.runtime.random import randint
from l3d_app.runtime.training import Trainable, train
from l3d_app.tasks.common import loop_spec, require_nonnegative, require_positive
from l3d_app.tasks.svr_common import (evaluate_and_report, load_data, plain, require_eval_view, require_thresholds,
                                      test_objects)

VAL_SEED_OFFSET = 99  # the validation stream: seed + this (any fixed value; chosen once)


@TASKS.register("svr_train")
def svr_train(cfg, ctx) -> dict:
    require_positive(cfg, "iters", "batch_size", "lr", "eval_points", "turntable_size", "vis_points", "error_max")
    require_thresholds(cfg)
    require_nonnegative(cfg, "lr_floor", "w_smooth", "eval_every", "quick_eval_objects", "eval_objects", "eval_view",
                        "num_vis")
    with ctx.stopwatch.stage("data"):
        data = load_data(cfg.data)
    require_eval_view(cfg, data)
    geometry = geometry_of(data)
    encoder_cfg, decoder_cfg = plain(cfg.encoder), plain(cfg.decoder)
    weights = encoder_cfg.pop("weights", None) or cfg.get("encoder_weights")     # resnet18: a local file, read here
    model = build_svr_model(encoder_cfg, decoder_cfg, geometry)
    if weights:
        if encoder_cfg.get("name") != "resnet18":
            raise UserError(f"encoder weights are read by encoder=resnet18 only, not encoder={encoder_cfg.get('name')}")
        load_resnet18_weights(model.encoder, weights)
    model = model.to(ctx.device)
    opt = torch.optim.Adam(model.parameters(), lr=float(cfg.lr))
    iters = int(cfg.iters)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=iters, eta_min=float(cfg.lr) * float(cfg.lr_floor))
    trainable = Trainable({"model": model}, opt, schedulers=[sched])
    train_ids, V, B = data.train, data.images.shape[1], int(cfg.batch_size)
    quick = data.val[: int(cfg.quick_eval_objects)]
    quick_views = torch.zeros_like(quick)

    def step(_i):
        pick = randint(0, len(train_ids), (B,), ctx.generator)
        views = randint(0, V, (B,), ctx.generator)
        batch = make_batch(data, train_ids[pick], views, ctx.device)
        return svr_loss(model.decoder, model(batch["images"]), batch, ctx.generator)

    def validate(_i):
        gen = torch.Generator().manual_seed(int(cfg.seed) + VAL_SEED_OFFSET)  # same points at every evaluation
        preds, per_image = predict_points(model, data, quick, quick_views, ctx.device, int(cfg.eval_points), gen)
        table = f1_table(preds, [data.points[o] for o in quick.tolist()], [0.05])
        out = {"f1": float(table["f1"][0]), "ms_per_image": per_image * 1000}
        if table["chamfer"] is not None:
            out["chamfer"] = table["chamfer"]
        return out

    use_val = int(cfg.eval_every) > 0 and len(quick) > 0
    with ctx.stopwatch.stage("train"):
        budget = TimeBudget.of(ctx).keep_renders(test_objects(cfg, data) if bool(cfg.eval_at_end) else 0, len(quick))
        result = train(ctx, trainable, step, loop_spec(cfg, "svr_train", iters), validate if use_val else None, budget)
    meta = {"encoder_cfg": encoder_cfg, "decoder_cfg": decoder_cfg, "geometry": geometry,
            "data_cfg": plain(cfg.data), "step": result.step}
    save_svr_model(ctx.path(MODEL_FILE), model, meta)
    metrics = {"decoder": str(decoder_cfg["name"]), "iters": result.step, "n_params": n_params(model),
               "train_seconds": round(result.train_seconds, 4),   # steps only, resumed parts included
               "data_seconds": round(ctx.stopwatch.stages["data"], 4),
               "train_objects": int(len(train_ids)), "val_objects": int(len(quick)),
               "skipped_steps": result.skipped_steps, "interrupted": result.interrupted,
               "history": result.history_rows(),
               **{k: v for k, v in result.val_metrics(5).items() if k in ("val_f1", "val_chamfer")}}
    if bool(cfg.eval_at_end) and not result.interrupted:
        metrics.update(evaluate_and_report(model, data, cfg, ctx, f"svr_train {decoder_cfg['name']}", result.step))
    return metrics
