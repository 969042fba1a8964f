"""A time-budgeted run's horizon: the loop predicts the step the budget stops it at, and the
schedules that read the prediction end there. A fake clock (steps 1 s, a 10 s validation every
20 steps) makes the stop step a matter of arithmetic; the LR factors are checked against
torch's own schedulers, built independently."""

import math
import types

import pytest
import torch

from l3d_app.runtime import training
from l3d_app.runtime.budget import TimeBudget
from l3d_app.runtime.context import RunContext
from l3d_app.runtime.horizon import Horizon, scheduled_event
from l3d_app.runtime.logger import RunLogger
from l3d_app.runtime.lr_schedules import exponential, on_horizon, step_decay, warmup_cosine
from l3d_app.runtime.optim import build_optimizer
from l3d_app.runtime.seed import seed_everything
from l3d_app.runtime.training import LoopSpec


def test_nominal_step_compresses_the_schedule_into_the_predicted_steps():
    h = Horizon(1000)
    assert h.nominal(250) == 250                 # no prediction yet: the schedule is read by step
    h.update(done=10, predicted=400.0)
    assert h.nominal(200) == pytest.approx(500.0) and h.nominal(400) == pytest.approx(1000.0)
    h.update(done=10, predicted=5000.0)          # never past iters ...
    assert h.steps == 1000
    h.update(done=300, predicted=12.0)           # ... nor before the steps already done
    assert h.steps == 301
    g = Horizon(7)
    g.load_state_dict(h.state_dict())
    assert (g.iters, g.steps) == (1000, 301)


@pytest.mark.parametrize("name,factor,reference", [
    ("step", step_decay(0.33, 7), lambda opt: torch.optim.lr_scheduler.StepLR(opt, 7, 0.33)),
    ("exp", exponential(0.01, 40), lambda opt: torch.optim.lr_scheduler.ExponentialLR(opt, 0.01 ** (1 / 40))),
    ("cos", warmup_cosine(0, 0, 40, 0.05),
     lambda opt: torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=40, eta_min=0.1 * 0.05)),
])
def test_factor_schedules_match_torchs_schedulers(name, factor, reference):
    p = torch.nn.Parameter(torch.zeros(1))
    ours = torch.optim.SGD([p], lr=0.1)
    ref = torch.optim.SGD([torch.nn.Parameter(torch.zeros(1))], lr=0.1)
    sched, ref_sched = torch.optim.lr_scheduler.LambdaLR(ours, factor), reference(ref)
    for _ in range(40):
        assert ours.param_groups[0]["lr"] == pytest.approx(ref.param_groups[0]["lr"], rel=1e-9)
        ours.step(), ref.step(), sched.step(), ref_sched.step()


def test_on_horizon_reads_the_factor_at_the_nominal_step():
    h = Horizon(100)
    h.update(done=0, predicted=50.0)
    f = on_horizon(warmup_cosine(0, 0, 100, 0.05), h)
    assert f(50) == pytest.approx(0.05) and f(25) == pytest.approx(0.05 + 0.95 * 0.5)


def run_budgeted(tmp_path, monkeypatch, with_horizon: bool, eval_cost=lambda n: 10.0, eval_price=10.0):
    """Budget 300 s, reserve 10 s, 3 evaluations' worth of rendering after the loop; steps
    1 s, a 10 s validation after every 20th step. The loop stops at the first k with
    k + 10 floor(k / 20) + 1 + 10 (1 + 3) + 10 >= 300: k = 169. ``eval_price``: a validation the
    task timed before training (so the loop runs no pricing validation of its own; the horizon
    reads only the loop's validations)."""
    clock = types.SimpleNamespace(elapsed=0.0)
    ctx = RunContext(out_dir=tmp_path, device=torch.device("cpu"), generator=seed_everything(0),
                     logger=RunLogger(tmp_path, enabled=False), stopwatch=clock,
                     time_budget=300.0, reserve=10.0)
    model = torch.nn.Linear(2, 1)
    horizon = Horizon(1000)
    opt, scheds = build_optimizer({"name": "warmup_cosine", "lr": 0.1, "warmup_steps": 5, "final_ratio": 0.05},
                                  model.parameters(), 1000, horizon=horizon if with_horizon else None)
    trainable = training.Trainable({"model": model}, opt, schedulers=scheds)
    seen = {"lr": [], "steps": []}

    def step_fn(i):
        clock.elapsed += 1.0
        seen["lr"].append(opt.param_groups[0]["lr"])
        seen["steps"].append(horizon.steps)
        return {"loss": model(torch.ones(1, 2)).pow(2).sum()}

    def eval_fn(step):
        clock.elapsed += eval_cost(len(seen.setdefault("evals", [])))
        seen["evals"].append(step)
        return {"x": 0.0}
    result = training.train(ctx, trainable, step_fn, LoopSpec(1000, eval_every=20), eval_fn=eval_fn, budget=TimeBudget.of(ctx, evals_after=3.0, eval_price=eval_price, horizon=horizon if with_horizon else None))
    return result, seen


def test_the_horizon_predicts_the_budget_stop_and_the_schedule_ends_there(tmp_path, monkeypatch):
    result, seen = run_budgeted(tmp_path, monkeypatch, with_horizon=True)
    assert result.budget_stop and result.step == 169
    # until the first validation is timed the loop knows no evaluation cost: after step k it
    # predicts k + (300 - k - 10) / 1 = 290 steps; from then on it is within 3% of where the run
    # stops: it spreads the validations over the steps (1.5 s each), so it reads 166.7 after
    # each one and up to 173.3 just before the next
    assert seen["steps"][1:20] == pytest.approx([290.0] * 19)
    assert all(abs(s - 169) <= 0.03 * 169 for s in seen["steps"][20:])
    # the LR reached its final ratio (0.05) at the last step, where an uncompressed cosine
    # over 1000 steps would still be near its top
    assert seen["lr"][-1] <= 0.1 * (0.05 + 0.01)
    plain_result, plain = run_budgeted(tmp_path / "plain", monkeypatch, with_horizon=False)
    assert plain_result.step == 169
    expected = 0.05 + 0.95 * 0.5 * (1 + math.cos(math.pi * (168 - 5) / 995))
    assert plain["lr"][-1] == pytest.approx(0.1 * expected) and plain["lr"][-1] > 0.09


def test_the_next_evaluation_costs_what_the_latest_one_did(tmp_path, monkeypatch):
    """The first validation takes 30 s (a fuzzy field skips no empty space), the later ones 2 s.
    The loop budgets the final validation and the 3 evaluations after it at the latest cost:
    it stops at the first k with k + 30 + 2 (floor(k / 20) - 1) + 1 + 2 (1 + 3) + 10 >= 300,
    k = 231 (the mean of the costs so far, 50 / 11 s, would stop it at 221)."""
    result, seen = run_budgeted(tmp_path, monkeypatch, with_horizon=True,
                                eval_cost=lambda n: 30.0 if n == 0 else 2.0, eval_price=30.0)
    assert result.budget_stop and result.step == 231
    # after the second validation the prediction is k + (300 - elapsed - 8 - 10) / 1.1: 230.9 at k = 40
    assert seen["steps"][40] == pytest.approx(40 + (300 - 72 - 8 - 10) / 1.1)
    assert all(abs(s - 231) <= 0.03 * 231 for s in seen["steps"][40:])


def test_without_a_budget_the_horizon_stays_at_iters(tmp_path):
    ctx = RunContext(out_dir=tmp_path, device=torch.device("cpu"), generator=seed_everything(0),
                     logger=RunLogger(tmp_path, enabled=False), time_budget=0.0)
    model = torch.nn.Linear(2, 1)
    horizon = Horizon(30)
    opt, scheds = build_optimizer({"name": "warmup_cosine", "lr": 0.1, "warmup_steps": 0, "final_ratio": 0.05},
                                  model.parameters(), 30, horizon=horizon)
    training.train(ctx, training.Trainable({"model": model}, opt, schedulers=scheds), lambda i: {"loss": model(torch.ones(1, 2)).pow(2).sum()}, LoopSpec(30), budget=TimeBudget.of(ctx, horizon=horizon))
    assert horizon.steps == 30 and opt.param_groups[0]["lr"] == pytest.approx(0.1 * 0.05)


def test_a_checkpoint_of_the_older_torch_schedulers_resumes_into_the_factor_schedule():
    # before the schedules were LambdaLR factors, adam_step saved a StepLR state: resuming it
    # must carry the step count over (lr 0.1 x 0.33 after 12 steps of decay_every 10), not fail
    def built():
        model = torch.nn.Linear(2, 1)
        opt = torch.optim.Adam(model.parameters(), lr=0.1)
        return model, opt
    model, opt = built()
    old = torch.optim.lr_scheduler.StepLR(opt, step_size=10, gamma=0.33)
    for _ in range(12):
        opt.step(), old.step()
    state = training.Trainable({"m": model}, opt, schedulers=[old]).state_dict()
    model2 = torch.nn.Linear(2, 1)
    opt2, scheds = build_optimizer({"name": "adam_step", "lr": 0.1, "decay": 0.33, "decay_every": 10},
                                   model2.parameters(), 100)
    training.Trainable({"m": model2}, opt2, schedulers=scheds).load_state_dict(state)
    assert scheds[0].last_epoch == 12 and opt2.param_groups[0]["lr"] == pytest.approx(0.1 * 0.33)
    opt2.step(), scheds[0].step()
    assert opt2.param_groups[0]["lr"] == pytest.approx(0.1 * 0.33)


@pytest.mark.parametrize("every,first,last", [(1, 1, math.inf), (4, 1, math.inf), (7, 5, 30), (10, 10, 30)])
def test_scheduled_event_on_integer_steps_is_the_modulo_rule(every, first, last):
    for done in range(1, 61):
        assert scheduled_event(done - 1, done, every, first, last) == (first <= done <= last and done % every == 0)


def test_advance_covers_the_nominal_steps_once_and_never_moves_back():
    h = Horizon(100)
    assert [h.advance(d) for d in (1, 2, 3)] == [(0.0, 1.0), (1.0, 2.0), (2.0, 3.0)]   # no prediction: by step
    h.update(done=3, predicted=50.0)                   # half the steps fit: each covers two nominal ones
    assert h.advance(4) == pytest.approx((3.0, 8.0)) and h.advance(5) == pytest.approx((8.0, 10.0))
    h.update(done=5, predicted=100.0)                  # the prediction rises again: nominal(6) = 6 < 10
    assert h.advance(6) == (10.0, 10.0)                # nothing covered twice, nothing moves back
    g = Horizon(1)
    g.load_state_dict(h.state_dict())
    assert (g.iters, g.steps, g.reached) == (100, 100.0, 10.0)
    old = Horizon(100)                                  # a checkpoint written before advance() existed
    old.load_state_dict({"iters": 100, "steps": 50.0})
    assert old.advance(31) == pytest.approx((60.0, 62.0))  # from nominal(30), not from 0: no burst of events


def test_events_keep_their_count_when_the_schedule_is_compressed():
    """Densify every 10 nominal steps within [10, 60] of a 100-step schedule: 6 events by step,
    and the same 6 when only 37 steps fit (each at the first step whose nominal interval holds it)."""
    def events(fit):
        h, at = Horizon(100), []
        for done in range(1, fit + 1):
            h.update(done - 1, fit)
            if scheduled_event(*h.advance(done), 10, first=10, last=60):
                at.append(done)
        return at
    assert events(100) == [10, 20, 30, 40, 50, 60]
    assert events(37) == [math.ceil(k * 37 / 100) for k in (10, 20, 30, 40, 50, 60)] == [4, 8, 12, 15, 19, 23]
