"""svr_train: train an image -> 3D model (small CNN encoder + ``decoder=vox|point|mesh|implicit|pseudo``).

Each step draws ``batch_size`` (object, view) pairs from the training split (the run's
seeded generator, so a resumed run draws what an uninterrupted one would), encodes the
images and minimises the decoder's own loss (see :mod:`l3d_app.models.svr_decoders` and
:mod:`l3d_app.models.svr_pseudo`) with Adam (cosine-decayed). Every ``eval_every`` steps
F1@0.05 and chamfer on ``quick_eval_objects`` test objects are logged against step and
wall time. Runs through the shared loop (checkpoints, ``resume=true``, NaN guard).

At the end it writes ``svr_model.pt`` (self-contained: ``task=svr_eval checkpoint=...``)
and, with ``eval_at_end`` (default), runs the full evaluation of ``svr_eval`` into the
same folder: f1_curve.png, predictions.png/.gif, metrics.json with f1 (= F1@0.05), the
F1 curve, chamfer, seconds per image, training seconds.
"""

from __future__ import annotations

import torch

from l3d_app.registry import TASKS
from l3d_app.runtime.training import Trainable, train
from l3d_app.tasks.common import require_positive
from l3d_app.tasks.svr_common import (MODEL_FILE, build_model, evaluate_and_report, f1_table, geometry_of,
                                      load_data, make_batch, n_params, plain, predict_points, save_model)


@TASKS.register("svr_train")
def svr_train(cfg, ctx) -> dict:
    require_positive(cfg, "iters", "batch_size", "lr", "eval_points", "vis_size")
    with ctx.stopwatch.stage("data"):
        data = load_data(cfg.data)
    geometry = geometry_of(data)
    encoder_cfg, decoder_cfg = plain(cfg.encoder), plain(cfg.decoder)
    model = build_model(encoder_cfg, decoder_cfg, geometry).to(ctx.device)
    opt = torch.optim.Adam(model.parameters(), lr=float(cfg.lr))
    iters = int(cfg.iters)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=iters, eta_min=float(cfg.lr) * 0.05)
    trainable = Trainable({"model": model}, opt, schedulers=[sched])
    train_ids, V, B = data.train, data.images.shape[1], int(cfg.batch_size)
    quick = data.test[: int(cfg.quick_eval_objects)]
    quick_views = torch.zeros_like(quick)
    gen_eval = torch.Generator(device=ctx.device).manual_seed(int(cfg.seed) + 99)

    def step(_i):
        pick = torch.randint(len(train_ids), (B,), generator=ctx.generator, device=ctx.generator.device).cpu()
        views = torch.randint(V, (B,), generator=ctx.generator, device=ctx.generator.device).cpu()
        batch = make_batch(data, train_ids[pick], views, ctx.device)
        return model.decoder.loss(model(batch["images"]), batch, ctx.generator)

    def evaluate(_i):
        preds, per_image = predict_points(model, data, quick, quick_views, ctx.device, int(cfg.eval_points), gen_eval)
        table = f1_table(preds, [data.points[o] for o in quick.tolist()], [0.05])
        out = {"f1": float(table["f1"][0]), "ms_per_image": per_image * 1000}
        if table["chamfer"] is not None:
            out["chamfer"] = table["chamfer"]
        return out

    with ctx.stopwatch.stage("train"):
        result = train(ctx, trainable, step, iters, evaluate if int(cfg.eval_every) > 0 else None,
                       int(cfg.eval_every), int(cfg.checkpoint_every), bool(cfg.resume), desc="svr_train")
    meta = {"encoder_cfg": encoder_cfg, "decoder_cfg": decoder_cfg, "geometry": geometry,
            "data_cfg": plain(cfg.data), "step": result.step}
    save_model(ctx.path(MODEL_FILE), model, meta)
    metrics = {"decoder": str(decoder_cfg["name"]), "iters": result.step, "n_params": n_params(model),
               "train_seconds": round(ctx.stopwatch.stages["train"], 4),
               "data_seconds": round(ctx.stopwatch.stages["data"], 4),
               "train_objects": int(len(train_ids)), "skipped_steps": result.skipped_steps,
               "interrupted": result.interrupted, "history": result.history_rows()}
    if bool(cfg.eval_at_end) and not result.interrupted:
        metrics.update(evaluate_and_report(model, data, cfg, ctx, f"svr_train {decoder_cfg['name']}"))
    elif result.metrics:
        metrics.update({k: v for k, v in result.metrics.items() if k in ("f1", "chamfer")})
    return metrics
