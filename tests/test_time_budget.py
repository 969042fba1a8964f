"""The time budget: the training loop stops on the whole task's wall clock, read from the run's
``time_budget`` / ``reserve`` knobs unless a task passes its own. A fake stopwatch advances 10 s
per step (the policy times steps and validations on it too), so the stopping step follows from
arithmetic, not from this machine's speed."""

import pytest
import torch

from l3d_app.runtime.budget import TimeBudget
from l3d_app.runtime.context import RunContext
from l3d_app.runtime.logger import RunLogger
from l3d_app.runtime.seed import seed_everything
from l3d_app.runtime.training import LoopSpec, Trainable, train


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


def test_the_run_budget_stops_every_loop(tmp_path, capsys):
    # budget 65 s, no reserve: after step 6 the clock reads 60 s and one more 10 s step reaches 70 >= 65
    # -> 6 steps, not 100
    ctx, trainable, step = setup(tmp_path, budget=65.0)
    result = train(ctx, trainable, step, LoopSpec(100))
    assert result.step == 6 and result.budget_stop
    # under a tenth of the steps asked for: one line says so, with what the budget kept after training
    assert "stopped train at step 6 of 100: what follows training is priced at 0.0 s" in capsys.readouterr().err
    ctx, trainable, step = setup(tmp_path / "b", budget=65.0)
    train(ctx, trainable, step, LoopSpec(50))                  # 6 of 50: more than a tenth, no line
    assert "stopped" not in capsys.readouterr().err


def test_the_reserve_is_kept_for_what_follows(tmp_path):
    # budget 65 s with 20 s reserved: stop once elapsed + 10 (a step) + 20 >= 65, i.e. at 40 s -> 4 steps
    ctx, trainable, step = setup(tmp_path, budget=65.0, reserve=20.0)
    result = train(ctx, trainable, step, LoopSpec(100))
    assert result.step == 4 and result.budget_stop


def test_a_task_argument_overrides_the_run_budget(tmp_path):
    ctx, trainable, step = setup(tmp_path, budget=55.0)
    result = train(ctx, trainable, step, LoopSpec(12), budget=TimeBudget.of(ctx, seconds=0.0))
    assert result.step == 12 and not result.budget_stop


def test_no_budget_runs_every_step(tmp_path):
    ctx, trainable, step = setup(tmp_path)
    result = train(ctx, trainable, step, LoopSpec(12))
    assert result.step == 12 and not result.budget_stop


def test_the_knob_reaches_a_task_that_never_names_it(compose, tmp_path):
    # fit_vox passes no budget of its own; a budget far below one step's cost stops it after
    # its first step (the loop always takes one), where 40 steps were asked for
    from l3d_app.app import run_task
    import json
    run_task(compose("task=fit_vox", "voxel_size=8", "iters=40", "eval_every=20", "num_frames=2", "image_size=16",
                     "time_budget=1e-6"), out_dir=tmp_path)
    metrics = json.loads((tmp_path / "metrics.json").read_text())
    assert metrics["iters"] == 1
    # what the budget did not hold is reported, not hidden; the preview gif, spent, is not written
    assert metrics["over_budget_seconds"] == pytest.approx(metrics["seconds"] - 1e-6, abs=0.02)
    assert not (tmp_path / "fit_vox.gif").exists()


def test_a_run_within_its_budget_reports_no_overrun(compose, tmp_path):
    from l3d_app.app import run_task
    import json
    run_task(compose("task=fit_vox", "voxel_size=8", "iters=4", "eval_every=2", "num_frames=2", "image_size=16",
                     "time_budget=3600", "tensorboard=false"), out_dir=tmp_path)
    metrics = json.loads((tmp_path / "metrics.json").read_text())
    assert metrics["iters"] == 4 and "over_budget_seconds" not in metrics and (tmp_path / "fit_vox.gif").is_file()


def test_a_preview_gif_gets_the_evenly_spread_frames_that_fit():
    from l3d_app.geometry.camera_paths import turntable
    from l3d_app.render.previews import frames_within_budget

    cams = turntable(36, 3.0, 10.0, 60.0, 8)
    clock, seen, notes = {"t": 90.0}, [], []
    timer = TimeBudget(100.0, clock=lambda: clock["t"], note=lambda tag, text: notes.append(text))

    def render(c):
        seen.append(c.R.clone())
        clock["t"] += 0.5 * len(c)
        return torch.arange(len(c), dtype=torch.float32)[:, None, None, None].expand(len(c), 2, 2, 3) + len(seen)
    frames = frames_within_budget(timer, cams, render, "g/budget")
    # 10 s left: the first frame (0.5 s) priced, then 9.5 s // 0.5 = 19 more -> 20 frames of 36, spread
    assert frames.shape[0] == 20 and clock["t"] <= 100.0
    idx = (torch.arange(1, 20) * 36) // 20
    assert torch.equal(seen[0], cams.R[:1]) and torch.equal(seen[1], cams.R[idx])
    assert "20 of 36" in notes[0]
    # no budget: every frame, no note; a spent budget: none, not even the priced first frame
    assert frames_within_budget(TimeBudget(0.0, clock=lambda: clock["t"]), cams, render, "g").shape[0] == 36
    clock["t"], calls = 10.5, len(seen)
    assert frames_within_budget(TimeBudget(10.0, clock=lambda: clock["t"], note=lambda tag, text: notes.append(text)),
                                cams, render, "g") is None and len(seen) == calls
    assert "spent" in notes[-1]


def test_the_reserve_in_evaluations_follows_the_measured_evaluation_cost(tmp_path):
    # steps cost 10 s and a validation 30 s on the fake clock: one before the first step (under a
    # budget the loop prices the final validation and the test views from the start), then every
    # 2nd step, so after step k it reads 10 k + 30 (1 + floor(k / 2)); 3 evaluations' worth of
    # rendering follow the loop. Stop at the first k with 10 k + 30 (1 + floor(k / 2)) + 10 (one more
    # step) + 30 (1 + 3) >= 300: k = 5 reads 140 (+130 = 270), k = 6 reads 180 (+130 = 310) -> 6 steps
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
    result = train(ctx, trainable, step_fn, LoopSpec(100, eval_every=2), eval_fn,
                   TimeBudget.of(ctx, evals_after=3.0))
    assert result.step == 6 and result.budget_stop
    assert [s for s, _ in result.history][:2] == [0, 2]          # the pricing validation, logged at step 0
    # without the evaluations' reserve the same loop runs on: 10 k + 30 (1 + floor(k / 2)) + 10 + 30 >= 300
    # at k = 10 (320; k = 9: 280)
    ctx, trainable, step = setup(tmp_path / "b", budget=300.0)
    evals["n"] = 0
    result = train(ctx, trainable, step_fn, LoopSpec(100, eval_every=2), eval_fn)
    assert result.step == 10 and result.budget_stop


def test_a_budget_stop_before_the_first_periodic_validation_keeps_time_for_the_test_views(tmp_path):
    # steps cost 10 s, a validation 30 s, the first periodic one at step 50 (never reached); 3
    # evaluations' worth follow the loop, budget 310 s. Priced from the start (30 s: the pricing
    # validation, or a task's own timed validation via eval_price), the loop stops at the first k
    # with 10 k + 30 + 10 + 30 (1 + 3) >= 310: k = 15. Unpriced it would run to 10 k + 10 >= 310,
    # k = 30, and the final validation and test views would overrun the budget by 120 s.
    ctx, trainable, step = setup(tmp_path, budget=310.0)

    def step_fn(i):
        out = step(i)
        ctx.stopwatch.elapsed += 30.0                # the pricing validation's seconds
        return out

    def eval_fn(s):
        ctx.stopwatch.elapsed += 30.0
        return {"x": 0.0}
    result = train(ctx, trainable, step_fn, LoopSpec(100, eval_every=50), eval_fn, TimeBudget.of(ctx, evals_after=3.0))
    assert result.step == 15 and result.budget_stop
    assert [s for s, _ in result.history] == [0, 15]
    # a task's own timed validation (30 s, before training) prices it instead: no step-0 validation
    ctx, trainable, step = setup(tmp_path / "b", budget=310.0)
    ctx.stopwatch.elapsed = 30.0
    result = train(ctx, trainable, step_fn, LoopSpec(100, eval_every=50), eval_fn,
                   TimeBudget.of(ctx, evals_after=3.0, eval_price=30.0))
    assert result.step == 15 and [s for s, _ in result.history] == [15]


def _timed_validations(tmp_path, budget, cost):
    """The fake-clock loop of :func:`setup` whose validation at step ``s`` takes ``cost(s, steps validated
    before)`` seconds; every step also carries the validations' seconds so far. The validation returns
    ``x``: how many validations have run."""
    ctx, trainable, step = setup(tmp_path, budget=budget)
    seen = {"extra": 0.0, "steps": []}

    def step_fn(i):
        out = step(i)
        ctx.stopwatch.elapsed += seen["extra"]
        return out

    def eval_fn(s):
        seconds = cost(s, list(seen["steps"]))
        seen["extra"] += seconds
        ctx.stopwatch.elapsed += seconds
        seen["steps"].append(s)
        return {"x": float(len(seen["steps"]))}
    return ctx, trainable, step_fn, eval_fn, seen


def test_a_stale_evaluation_price_is_refreshed_before_a_budget_stop(tmp_path):
    # steps cost 10 s; a validation every 50 steps, the first 40 s, later ones 5 s (a fuzzy model
    # renders slower than the sharp one); 10 evaluations' worth follow the loop; budget 1110 s. The
    # pricing validation before the first step costs 5 s. After step k (50 < k) the clock reads
    # 10 k + 45. Priced at 40 s the loop stops at the first k with 10 k + 45 + 10 + 40 x 11 >= 1110:
    # k = 62. That price is 12 steps old (>= max(1, 50 // 5) = 10), so the loop validates again (5 s:
    # 670 s) and re-prices: 670 + 10 + 5 x 11 = 735 < 1110 -> on. Then 10 k + 50 + 10 + 55 >= 1110 first
    # at k = 100, where the periodic validation (5 s) has been measured once: the loop repeats it (5 s,
    # the step's entry replaced): 1060 + 65 = 1125 -> stop, and no third validation as the final one.
    ctx, trainable, step_fn, eval_fn, seen = _timed_validations(tmp_path, 1110.0,
                                                                lambda s, before: 40.0 if s == 50 else 5.0)
    result = train(ctx, trainable, step_fn, LoopSpec(1000, eval_every=50), eval_fn, TimeBudget.of(ctx, evals_after=10.0))
    assert result.budget_stop and result.step == 100
    assert seen["steps"] == [0, 50, 62, 100, 100]
    assert [s for s, _ in result.history] == [0, 50, 62, 100]


@pytest.mark.parametrize("repeat_cost, stop_step, evals", [(5.0, 80, [50, 50, 80]), (40.0, 50, [50, 50])])
def test_one_slow_validation_does_not_end_a_run(tmp_path, repeat_cost, stop_step, evals):
    # steps cost 10 s, a validation every 50 steps 5 s (priced so before training: eval_price), 10
    # evaluations' worth follow the loop, budget 910 s. The step-50 validation takes 40 s (a stall):
    # 540 + 10 + 40 x 11 = 990 >= 910 would stop the run at step 50. The loop validates again first.
    # A 5 s repeat (the stall passed): the cheaper price, 5 s, counts: 545 + 10 + 55 < 910 -> on, until
    # 10 k + 45 + 10 + 55 >= 910 at k = 80, where the step-50 price is 30 >= 10 steps old: a fresh
    # validation (5 s): 850 + 65 = 915 -> stop. A 40 s repeat (the model is that dear): both
    # timings say 40 s -> stop at 50, the repeat its final validation (one entry at step 50).
    ctx, trainable, step_fn, eval_fn, seen = _timed_validations(
        tmp_path, 910.0, lambda s, before: (40.0 if s == 50 and s not in before else repeat_cost if s == 50 else 5.0))
    result = train(ctx, trainable, step_fn, LoopSpec(1000, eval_every=50), eval_fn,
                   TimeBudget.of(ctx, evals_after=10.0, eval_price=5.0))
    assert result.budget_stop and result.step == stop_step
    assert seen["steps"] == evals
    assert [s for s, _ in result.history] == sorted(set(evals))       # a repeat replaces its step's entry
    assert result.history[0][1]["x"] == 2.0                            # ... with the repeat's figures


def _priced_before_training(tmp_path, budget, cost):
    """:func:`_timed_validations` after a task's own 50 s validation before training (``eval_price``):
    the clock starts at 50 s and every step also carries those 50 s."""
    ctx, trainable, step_fn, eval_fn, seen = _timed_validations(tmp_path, budget, cost)
    seen["extra"] = ctx.stopwatch.elapsed = 50.0
    return ctx, trainable, step_fn, eval_fn, seen


def _priced_run(tmp_path, budget, eval_every, cost):
    """The loop over :func:`_priced_before_training` (validations every ``eval_every`` steps, 5
    evaluations' worth after the loop, the 50 s price from before training): its result and the steps
    it validated at."""
    ctx, trainable, step_fn, eval_fn, seen = _priced_before_training(tmp_path, budget, cost)
    result = train(ctx, trainable, step_fn, LoopSpec(1000, eval_every=eval_every), eval_fn,
                   TimeBudget.of(ctx, evals_after=5.0, eval_price=50.0))
    return result, seen["steps"]


@pytest.mark.parametrize("later_cost, stop_step, evals", [(5.0, 17, [10, 17]), (50.0, 10, [10])])
def test_an_untrained_models_price_that_loses_the_budget_is_measured_again_after_training(
        tmp_path, later_cost, stop_step, evals):
    # steps cost 10 s; the task validated the untrained model before training (50 s: eval_price),
    # the loop validates every 50 steps; 5 evaluations' worth follow the loop; budget 260 s. After step
    # k the clock reads 10 k + 50, and at the 50 s price what follows is 300 s: stopping at any step
    # passes the budget. The price is an untrained model's, so the loop trains on to step
    # max(1, 50 // 5) = 10 and validates there. A trained model that renders in 5 s (train_nerf's
    # occupancy grid after its warm-up): 155 + 10 + 30 < 260 -> on, until 10 k + 55 + 10 + 30 >= 260 at
    # k = 17, whose price (7 steps old, confirmed) stands: stop, the final validation at 17. A model that
    # stays that dear (50 s at step 10): 200 + 10 + 300 -> stop at 10, that validation the final one.
    # Stopping at step 1 would score the untrained model's test views.
    result, validated = _priced_run(tmp_path, 260.0, 50, lambda s, before: 50.0 if s < 10 else later_cost)
    assert result.budget_stop and result.step == stop_step
    assert validated == evals


def test_a_price_from_before_training_is_measured_again_before_a_budget_stop(tmp_path):
    # as above with budget 1010 s and validations every 100 steps: at the 50 s price the loop stops
    # at the first k with 10 k + 50 + 10 + 300 >= 1010: k = 65 (stopping there keeps the budget, so no
    # wait). That price is 65 >= max(1, 100 // 5) = 20 steps old: validated again (5 s): 705 + 10 + 30 <
    # 1010 -> on, to 10 k + 55 + 10 + 30 >= 1010 at k = 92, where the step-65 price is 27 >= 20 steps old:
    # validated again (5 s): 980 + 40 -> stop. Stopping at 65 would trust the untrained model's price.
    result, validated = _priced_run(tmp_path, 1010.0, 100, lambda s, before: 50.0 if s < 20 else 5.0)
    assert result.budget_stop and result.step == 92
    assert validated == [65, 92]


class _Reserved(Exception):
    pass


@pytest.mark.parametrize("overrides, expected", [((), 5.0), (("extract_mesh=true",), 35.0),
                                                 (("extract_mesh=true", "reserve=0"), 30.0)])
def test_train_nerf_keeps_its_mesh_seconds_only_when_it_extracts_a_mesh(compose, tmp_path, monkeypatch,
                                                                       overrides, expected):
    # the 30 s (mesh_reserve) used to be kept whether or not a mesh was written: without one, a
    # 60 s budget left train_nerf a single step and the gif took the rest
    from l3d_app.app import run_task
    from l3d_app.tasks import train_nerf as task

    seen = {}

    def fake_train(ctx, trainable, step_fn, spec, eval_fn=None, budget=None, after_step=None):
        seen["reserve"] = budget.reserve
        raise _Reserved
    monkeypatch.setattr(task, "train", fake_train)
    with pytest.raises(_Reserved):
        run_task(compose("task=train_nerf", "data.image_size=16", "data.n_train=4", "data.n_val=1", "data.n_test=1",
                         "before_after=false", "tensorboard=false", *overrides), out_dir=tmp_path)
    assert seen["reserve"] == expected


@pytest.mark.parametrize("slow", [False, True], ids=["fits", "too_dear"])
def test_train_nerf_draws_its_picture_before_training_only_when_it_fits(compose, tmp_path, monkeypatch, capsys, slow):
    # the picture is priced on a part of its rays first: a part that says a whole one would take at
    # least 0.05 s / 1e-5 = 5000 s does not fit 590 s, so no picture; its price is the loop's first
    import time

    from l3d_app.app import run_task
    from l3d_app.tasks import train_nerf as task

    seen = {}

    def fake_train(ctx, trainable, step_fn, spec, eval_fn=None, budget=None, after_step=None):
        seen["price"], seen["pictures"] = budget.eval_price, set(trainable.extra["before_after"].pictures)
        raise _Reserved
    if slow:
        monkeypatch.setattr(task, "render_part", lambda *a, **k: (time.sleep(0.05), 1e-5)[1])
    monkeypatch.setattr(task, "train", fake_train)
    with pytest.raises(_Reserved):
        run_task(compose("task=train_nerf", "data.image_size=16", "data.n_train=4", "data.n_val=1", "data.n_test=1",
                         "time_budget=590", "tensorboard=false"), out_dir=tmp_path)
    err = capsys.readouterr().err
    if slow:
        assert seen["pictures"] == set() and seen["price"] >= 5000.0
        assert "before_after: the picture before training would take about" in err and "not drawn" in err
    else:
        assert seen["pictures"] == {"before"} and seen["price"] < 590.0 and "not drawn" not in err


def test_a_part_of_a_validation_is_a_spread_share_of_its_rays():
    from l3d_app.geometry.cameras import look_at_cameras
    from l3d_app.geometry.rays import camera_rays
    from l3d_app.render.evaluation import render_part

    cams = look_at_cameras(3.0, torch.tensor([10.0, 20.0]), torch.tensor([0.0, 90.0]), 50.0, 40)   # 2 views, 40 x 40
    got = []
    share = render_part(lambda o, d: got.append((o, d)), cams, share=1.0 / 16, most=16384)
    assert len(got) == 1 and got[0][0].shape == (200, 3) and share == 200 / 3200
    o, d = camera_rays(cams, normalize=True)
    # the first pixel of the first view and the last of the last: spread over every view
    assert torch.equal(got[0][1][0], d[0, 0, 0]) and torch.equal(got[0][1][-1], d[1, -1, -1])
    assert torch.equal(got[0][0][-1], o[1, -1, -1])
    assert render_part(lambda o, d: got.append(o), cams, share=0.5, most=100) == 100 / 3200      # at most ``most``


def test_a_price_from_before_training_does_not_stop_the_loop_before_it_is_measured_on_a_trained_model(tmp_path):
    # steps cost 10 s; the task timed the untrained model's validation before training (50 s: eval_price,
    # the clock starts at 50 s); validations every 200 steps, so the price is untrained until step
    # max(1, 200 // 5) = 40; 5 evaluations' worth follow the loop; budget 660 s. At that price one more
    # step passes the budget first after step 30 (350 + 10 + 300 >= 660), where stopping at once would
    # still keep it (350 + 300 < 660): a stop there would rest on one reading of the untrained model.
    # The loop trains on to step 40 (those 10 steps fit: 450 < 660) and validates there: the trained
    # model renders in 5 s (455 + 10 + 30 < 660) -> on, to 10 k + 55 + 10 + 30 >= 660 at k = 57,
    # whose price (17 steps old, confirmed at 40) stands: stop, the final validation at 57.
    result, validated = _priced_run(tmp_path, 660.0, 200, lambda s, before: 50.0 if s < 40 else 5.0)
    assert result.budget_stop and result.step == 57
    assert validated == [40, 57]
