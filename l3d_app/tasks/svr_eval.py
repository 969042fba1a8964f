"""svr_eval: evaluate an ``svr_model.pt`` (from svr_train) on its dataset's test split.

The model file carries its data config, so the test objects are those the model never saw
(and never chose anything on: svr_train's periodic evaluation reads the validation objects).
Writes f1_curve.png (F1 against the distance threshold, also logged to TensorBoard as
``test/...``), predictions.png (input | truth | prediction | prediction points coloured by
the distance to the nearest true point, blue -> red), predictions.gif (turntables) and
metrics.json (``f1`` = ``f1@0.05``, ``f1@t`` per threshold, chamfer, milliseconds per
image, seconds). A missing checkpoint is a one-line error (exit status 2).
"""

from __future__ import annotations

from l3d_app.models.svr_model import load_svr_model, n_params
from l3d_app.registry import TASKS
from l3d_app.tasks.common import require_positive
from l3d_app.tasks.svr_common import evaluate_and_report, load_data, require_eval_view, require_thresholds


@TASKS.register("svr_eval")
def svr_eval(cfg, ctx) -> dict:
    model, meta = load_svr_model(cfg.get("checkpoint"), ctx.device)
    require_positive(cfg, "eval_points", "turntable_size")
    require_thresholds(cfg)
    with ctx.stopwatch.stage("data"):
        data = load_data(meta["data_cfg"])
    require_eval_view(cfg, data)
    name = str(meta["decoder_cfg"]["name"])
    step = int(meta.get("step", 0))
    metrics = evaluate_and_report(model, data, cfg, ctx, f"svr_eval {name}", step)
    return {"decoder": name, "trained_iters": step, "n_params": n_params(model), **metrics}
