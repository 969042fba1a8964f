"""The time budget: the training loop stops on the whole task's wall clock, read from the run's
``time_budget`` / ``reserve`` knobs unless a task passes its own. A fake stopwatch advances 10 s
per step, so the stopping step follows from arithmetic, not from this machine's speed."""

import torch

from l3d_app.runtime.context import RunContext
from l3d_app.runtime.logger import RunLogger
from l3d_app.runtime.seed import seed_everything
from l3d_app.runtime.training import Trainable, train


class FakeStopwatch:
    elapsed = 0.0


def setup(tmp_path, budget=0.0, reserve=0.0):
    ctx = RunContext(out_dir=tmp_path, device=torch.device("cpu"), generator=seed_everything(0),
                     logger=RunLogger(tmp_path, enabled=False), stopwatch=FakeStopwatch(),
                     time_budget=budget, reserve=reserve)
    model = torch.nn.Linear(2, 1)
    trainable = Trainable({"model": model}, torch.optim.SGD(model.parameters(), lr=0.01))

    def step(i):
        ctx.stopwatch.elapsed = 10.0 * (i + 1)  # step i ends at 10 (i + 1) seconds
        return {"loss": model(torch.ones(1, 2)).pow(2).sum()}
    return ctx, trainable, step


def test_the_run_budget_stops_every_loop(tmp_path):
    # budget 55 s, no reserve: after step 5 the clock reads 60 s >= 55 -> 6 steps, not 100
    ctx, trainable, step = setup(tmp_path, budget=55.0)
    result = train(ctx, trainable, step, iters=100)
    assert result.step == 6 and result.budget_stop


def test_the_reserve_is_kept_for_what_follows(tmp_path):
    # budget 55 s with 20 s reserved: stop once elapsed + 20 >= 55, i.e. at 40 s -> 4 steps
    ctx, trainable, step = setup(tmp_path, budget=55.0, reserve=20.0)
    result = train(ctx, trainable, step, iters=100)
    assert result.step == 4 and result.budget_stop


def test_a_task_argument_overrides_the_run_budget(tmp_path):
    ctx, trainable, step = setup(tmp_path, budget=55.0)
    result = train(ctx, trainable, step, iters=12, time_budget=0.0)
    assert result.step == 12 and not result.budget_stop


def test_no_budget_runs_every_step(tmp_path):
    ctx, trainable, step = setup(tmp_path)
    result = train(ctx, trainable, step, iters=12)
    assert result.step == 12 and not result.budget_stop


def test_the_knob_reaches_a_task_that_never_names_it(compose, tmp_path):
    # fit_vox passes no budget of its own; a budget far below one step's cost stops it after
    # its first step (the loop always takes one), where 40 steps were asked for
    from l3d_app.app import run_task
    import json
    run_task(compose("task=fit_vox", "iters=40", "eval_every=20", "num_frames=2", "image_size=16",
                     "time_budget=1e-6"), out_dir=tmp_path)
    assert json.loads((tmp_path / "metrics.json").read_text())["iters"] == 1


def test_the_reserve_in_evaluations_follows_the_measured_evaluation_cost(tmp_path):
    # steps cost 10 s and every 2nd step a validation costs 30 s on the fake clock, so after
    # step k it reads 10 k + 30 floor(k / 2); 3 evaluations' worth of rendering follow the loop.
    # Stop at the first k with 10 k + 30 floor(k / 2) + 30 (1 + 3) >= 300: k = 7 reads 160
    # (+120 = 280), k = 8 reads 200 (+120 = 320) -> 8 steps
    ctx, trainable, step = setup(tmp_path, budget=300.0)
    evals = {"n": 0}

    def step_fn(i):
        out = step(i)
        ctx.stopwatch.elapsed += 30.0 * evals["n"]
        return out

    def eval_fn(s):
        ctx.stopwatch.elapsed += 30.0
        evals["n"] += 1
        return {"x": 0.0}
    result = train(ctx, trainable, step_fn, iters=100, eval_fn=eval_fn, eval_every=2, reserve_evals=3.0)
    assert result.step == 8 and result.budget_stop
    # without the evaluations' reserve the same loop runs on: 10 k + 30 floor(k / 2) + 30 >= 300 at k = 11
    ctx, trainable, step = setup(tmp_path / "b", budget=300.0)
    evals["n"] = 0
    result = train(ctx, trainable, step_fn, iters=100, eval_fn=eval_fn, eval_every=2)
    assert result.step > 8 and result.budget_stop


def test_a_stale_evaluation_price_is_refreshed_before_a_budget_stop(tmp_path):
    # steps cost 10 s; a validation every 50 steps, the first 40 s, later ones 5 s (a fuzzy model
    # renders slower than the sharp one); 10 evaluations' worth follow the loop; budget 1100 s.
    # After step k (50 < k) the clock reads 10 k + 40. Priced at 40 s the loop stops at the first k
    # with 10 k + 40 + 40 x 11 >= 1100: k = 62. That price is 12 steps old (>= max(1, 50 // 5) = 10),
    # so the loop validates again (5 s: 665 s) and re-prices: 665 + 5 x 11 = 720 < 1100 -> on.
    # Then 10 k + 45 + 55 >= 1100 first at k = 100, where the periodic validation (5 s) is fresh:
    # 1050 + 55 = 1105 -> stop, no further refresh and no second final validation.
    ctx, trainable, step = setup(tmp_path, budget=1100.0)
    seen = {"extra": 0.0, "steps": []}

    def step_fn(i):
        out = step(i)
        ctx.stopwatch.elapsed += seen["extra"]
        return out

    def eval_fn(s):
        cost = 5.0 if seen["steps"] else 40.0
        seen["extra"] += cost
        ctx.stopwatch.elapsed += cost
        seen["steps"].append(s)
        return {"x": 0.0}
    result = train(ctx, trainable, step_fn, iters=1000, eval_fn=eval_fn, eval_every=50, reserve_evals=10.0)
    assert result.budget_stop and result.step == 100
    assert seen["steps"] == [50, 62, 100]
    assert [s for s, _ in result.history] == [50, 62, 100]
