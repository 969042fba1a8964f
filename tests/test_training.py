"""The shared training loop: NaN guard, checkpoints, resume, clean stop on a signal."""

import math
import os
import signal

import torch

from l3d_app.runtime.context import RunContext
from l3d_app.runtime.guard import tensors_finite
from l3d_app.runtime.logger import RunLogger
from l3d_app.runtime.lr_schedules import warmup_cosine
from l3d_app.runtime.seed import seed_everything
from l3d_app.runtime.training import CHECKPOINT, LoopSpec, Trainable, train


def make_ctx(out_dir, seed=0):
    return RunContext(out_dir=out_dir, device=torch.device("cpu"), generator=seed_everything(seed),
                      logger=RunLogger(out_dir, enabled=False))


def make_problem(lr=0.1):
    torch.manual_seed(0)
    model = torch.nn.Linear(3, 1)
    return model, Trainable({"model": model}, torch.optim.Adam(model.parameters(), lr=lr))


def regression_step(ctx, model, poison=()):
    target_w = torch.tensor([[1.0, -2.0, 0.5]])

    def step(i):
        x = torch.randn(16, 3, generator=ctx.generator)  # randomness from the run's generator
        loss = ((model(x) - x @ target_w.T) ** 2).mean()
        if i in poison:
            loss = loss * float("nan")
        return {"loss": loss}
    return step


def test_converges_and_evaluates(tmp_path):
    ctx = make_ctx(tmp_path)
    model, trainable = make_problem()
    result = train(ctx, trainable, regression_step(ctx, model), LoopSpec(300, eval_every=100), eval_fn=lambda s: {"w_err": float((model.weight - torch.tensor([[1.0, -2.0, 0.5]])).abs().max())})
    assert result.metrics["w_err"] < 0.05 and result.step == 300 and not result.interrupted
    assert (tmp_path / CHECKPOINT).exists()


def test_nan_steps_are_skipped_not_applied(tmp_path):
    ctx = make_ctx(tmp_path)
    model, trainable = make_problem()
    before = {k: v.clone() for k, v in model.state_dict().items()}
    result = train(ctx, trainable, regression_step(ctx, model, poison={0, 1}), LoopSpec(2))
    assert result.skipped_steps == 2
    for k, v in model.state_dict().items():
        assert torch.equal(v, before[k])


def test_repeated_failures_restore_last_good_state_and_checkpoints_stay_finite(tmp_path):
    """From step 5 on the parameters are corrupted behind the optimiser's back at every step: each
    step restores (non-finite parameters), the second restore goes one good state further back, and
    the third in a row stops the loop on that state (snapshots every step: good states are the
    states after 3 and 4 applied steps when step 5 fails)."""
    ctx = make_ctx(tmp_path)
    model, trainable = make_problem()
    after = {}

    def step(i):
        if i >= 5:
            with torch.no_grad():
                model.weight.fill_(float("inf"))
        return {"loss": (model.weight ** 2).sum() + model.bias.sum()}

    def record(i):
        after[i + 1] = model.weight.detach().clone()
    result = train(ctx, trainable, step, LoopSpec(12, checkpoint_every=1, max_bad_steps=3), after_step=record)
    assert result.guard_stop and result.restores == 3 and result.skipped_steps == 3 and result.step == 8
    assert torch.equal(model.weight.detach(), after[3])
    state = torch.load(tmp_path / CHECKPOINT, weights_only=False)
    for tensor in state["trainable"]["modules"]["model"].values():
        assert torch.isfinite(tensor).all()


def test_a_learning_rate_that_always_blows_up_stops_on_the_first_state(tmp_path, capsys):
    """Adam with lr=1e30: every first step from the start state is finite (1e30 weights), every next
    loss overflows. Three restores in a row stop the run after 3 x (1 + max_bad_steps) steps, on the
    start state exactly, with one warning line."""
    ctx = make_ctx(tmp_path)
    model, trainable = make_problem(lr=1e30)
    start = {k: v.clone() for k, v in model.state_dict().items()}
    result = train(ctx, trainable, regression_step(ctx, model), LoopSpec(300, max_bad_steps=5))
    assert result.guard_stop and result.restores == 3 and result.skipped_steps == 15 and result.step == 18
    for k, v in model.state_dict().items():
        assert torch.equal(v, start[k])
    err = capsys.readouterr().err
    assert err.count("warning: training stopped at step 18 of 300: 3 restores in a row") == 1
    assert ctx.write_metrics({})["guard_stop_step"] == 18


def test_failures_apart_by_a_clean_interval_each_restore_and_training_goes_on(tmp_path):
    """Three bursts of five non-finite losses, 45 clean steps apart (snapshot interval 15): three
    restores, none in a row, so the run neither steps further back nor stops, and converges."""
    ctx = make_ctx(tmp_path)
    model, trainable = make_problem()
    bursts = set(range(50, 55)) | set(range(100, 105)) | set(range(150, 155))
    result = train(ctx, trainable, regression_step(ctx, model, poison=bursts), LoopSpec(300, max_bad_steps=5))
    assert result.restores == 3 and result.skipped_steps == 15 and not result.guard_stop and result.step == 300
    assert float((model.weight.detach() - torch.tensor([[1.0, -2.0, 0.5]])).abs().max()) < 0.05


def test_a_blow_up_that_stays_finite_for_a_whole_interval_is_stepped_over(tmp_path):
    """After step 4 the weights jump to 1e10: the loss stays finite (~1e20) for two whole snapshot
    intervals (15 steps each), so the state after 15 steps becomes a restore point; from step 40 the
    huge weights overflow. The first restore brings back that huge state and fails again, the second
    goes one good state further back (the start) and the fit then converges."""
    ctx = make_ctx(tmp_path)
    model, trainable = make_problem()
    fit = regression_step(ctx, model)

    def step(i):
        out = fit(i)
        if i >= 40 and float(model.weight.detach().abs().max()) > 1e9:
            out["loss"] = out["loss"] * float("nan")
        return out

    def blow_up(i):
        if i == 4:
            with torch.no_grad():
                model.weight.fill_(1e10)
    result = train(ctx, trainable, step, LoopSpec(300, max_bad_steps=5), after_step=blow_up)
    assert result.restores == 2 and result.skipped_steps == 10 and not result.guard_stop and result.step == 300
    assert float((model.weight.detach() - torch.tensor([[1.0, -2.0, 0.5]])).abs().max()) < 0.05


def test_a_blow_up_to_finite_values_is_not_the_state_a_restore_brings_back(tmp_path):
    """After step 4 the parameters jump to 1e30 (finite: the step passes the guard and a snapshot is
    taken), the next losses overflow. The restore goes back to the snapshot before the jump, and the
    fit then converges; restoring the latest snapshot would bring the 1e30 weights back each time."""
    ctx = make_ctx(tmp_path)
    model, trainable = make_problem()
    fit = regression_step(ctx, model)

    def blow_up(step):
        if step == 4:
            with torch.no_grad():
                model.weight.fill_(1e30)
    result = train(ctx, trainable, fit, LoopSpec(300, checkpoint_every=1, max_bad_steps=2), after_step=blow_up)
    assert result.restores == 1 and result.skipped_steps == 2
    assert float((model.weight.detach() - torch.tensor([[1.0, -2.0, 0.5]])).abs().max()) < 0.05


def test_interrupt_then_resume_matches_uninterrupted_run(tmp_path):
    full_dir, cut_dir = tmp_path / "full", tmp_path / "cut"
    full_dir.mkdir(), cut_dir.mkdir()
    ctx = make_ctx(full_dir, seed=3)
    model, trainable = make_problem()
    train(ctx, trainable, regression_step(ctx, model), LoopSpec(40))
    reference = model.weight.detach().clone()

    ctx = make_ctx(cut_dir, seed=3)
    model, trainable = make_problem()
    inner = regression_step(ctx, model)

    def step_with_sigint(i):
        if i == 17:
            os.kill(os.getpid(), signal.SIGINT)  # handled: the loop stops after this step
        return inner(i)
    first = train(ctx, trainable, step_with_sigint, LoopSpec(40))
    assert first.interrupted and first.step == 18

    ctx = make_ctx(cut_dir, seed=99)  # a fresh process: state must come from the checkpoint
    model, trainable = make_problem()
    second = train(ctx, trainable, regression_step(ctx, model), LoopSpec(40, resume=True))
    assert second.step == 40 and not second.interrupted
    torch.testing.assert_close(model.weight.detach(), reference, rtol=0, atol=0)


def test_warmup_cosine_schedule_values():
    f = warmup_cosine(warmup=50, decay_start=50, decay_end=1500, final_ratio=0.05)
    assert f(0) == 1 / 50 and f(24) == 0.5 and f(49) == 1.0 and f(50) == 1.0
    assert f(775) == 0.05 + 0.95 * 0.5 * (1 + math.cos(math.pi * 725 / 1450))
    assert abs(f(1500) - 0.05) < 1e-15 and abs(f(5000) - 0.05) < 1e-15          # held after the end
    assert warmup_cosine(0, 0, 10, 0.5)(0) == 1.0                               # no warm-up
    assert warmup_cosine(10, 0, 100, 1.0)(99) == 1.0                            # constant after warm-up
    g = warmup_cosine(100, 0, 999, 0.05)                                         # decay already during warm-up
    assert g(99) == 0.05 + 0.95 * 0.5 * (1 + math.cos(math.pi * 99 / 999)) < 1.0


def test_a_stage_without_checkpoint_writes_none_and_logs_under_its_prefix(tmp_path):
    """checkpoint=False (a stage before the task's own loop): no checkpoint.pt read or written,
    the step logs under ``log_prefix``; it still converges."""
    ctx = make_ctx(tmp_path)
    model, trainable = make_problem()
    seen = []
    ctx.logger.log_scalars = lambda values, step: seen.extend(values)
    result = train(ctx, trainable, regression_step(ctx, model), LoopSpec(300, checkpoint_every=50, log_prefix="stage", checkpoint=False))
    assert result.step == 300 and not (tmp_path / CHECKPOINT).exists()
    assert float((model.weight.detach() - torch.tensor([[1.0, -2.0, 0.5]])).abs().max()) < 0.05
    assert "stage/loss" in seen and "stage/step_ms" in seen
    assert not any(k.startswith("train/") or k.startswith("time/") for k in seen)


def test_resume_from_another_tasks_or_another_sizes_checkpoint_is_named(tmp_path):
    """A checkpoint whose modules or sizes differ from the run's is one UserError, never a
    KeyError or a 'size mismatch' traceback; the checkpoint file is left as it was."""
    import pytest

    from l3d_app.errors import UserError
    from l3d_app.runtime.checkpoints import load_checkpoint, save_checkpoint

    def trainable(name, width):
        module = torch.nn.Linear(2, width)
        return Trainable({name: module}, torch.optim.Adam(module.parameters(), lr=1e-3))

    gen = torch.Generator().manual_seed(0)
    path = tmp_path / CHECKPOINT
    assert save_checkpoint(path, trainable("field", 3), 5, gen, {"eval": []})
    before = path.read_bytes()
    with pytest.raises(UserError, match="holds field, this run trains gaussians: a checkpoint of another task"):
        load_checkpoint(path, trainable("gaussians", 3), gen)
    with pytest.raises(UserError, match=r"does not fit this run's model \(size mismatch for weight"):
        load_checkpoint(path, trainable("field", 4), gen)
    assert path.read_bytes() == before
    assert load_checkpoint(path, trainable("field", 3), gen)["step"] == 5


def test_resume_without_a_checkpoint_says_so_and_guard_counts_carry_over(tmp_path, capsys):
    """resume=true into a folder with no checkpoint.pt starts at 0 with a note (a typo in
    hydra.run.dir must not restart silently); skipped steps and the step counters are kept
    in the checkpoint, so a resumed run reports the whole run's, with one warning line."""
    ctx = make_ctx(tmp_path)
    model, trainable = make_problem()
    first = train(ctx, trainable, regression_step(ctx, model, poison={1, 2}), LoopSpec(4, resume=True))
    err = capsys.readouterr().err
    assert "resume=true, but there is no" in err and "training starts at step 0" in err
    assert "l3d_app: warning: 2 of 4 steps were skipped as non-finite" in err
    assert first.skipped_steps == 2 and first.steps_run == 4
    again = train(ctx, trainable, regression_step(ctx, model), LoopSpec(6, resume=True))
    err = capsys.readouterr().err
    assert "no checkpoint" not in err and "warning" not in err            # nothing new was skipped
    assert again.skipped_steps == 2 and again.steps_run == 6 and again.train_seconds >= first.train_seconds


def test_an_update_that_overflows_inside_the_optimiser_is_named(tmp_path):
    """Adam at lr=1e38: its step size overflows float32 inside optimizer.step (a RuntimeError the
    NaN guard never sees): one UserError naming the step."""
    import pytest

    from l3d_app.errors import UserError

    ctx = make_ctx(tmp_path)
    model, trainable = make_problem(lr=1e38)
    with pytest.raises(UserError, match="optimiser's update overflowed at step 0"):
        train(ctx, trainable, regression_step(ctx, model), LoopSpec(3))


def test_the_finite_check_agrees_with_the_elementwise_test_on_hard_cases():
    """tensors_finite (a sum first) against the naive per-element reference: NaN, +-inf, both
    infinities in one tensor (their sum is NaN), huge finite values whose sum overflows (finite
    all the same), subnormals, empty tensors, None, float64 / bfloat16."""
    big = torch.full((4,), 3e38)                      # sum overflows to inf; every element finite
    cases = [
        [torch.zeros(3), torch.ones(2, 2)],
        [torch.tensor([1.0, float("nan")])],
        [torch.tensor([float("inf"), 1.0])],
        [torch.tensor([-float("inf")]), torch.zeros(2)],
        [torch.tensor([float("inf"), -float("inf")])],
        [big], [big, torch.tensor([float("nan")])], [-big, big],
        [torch.tensor([1e-45, -1e-45])], [torch.zeros(0)], [None, torch.ones(1)], [None], [],
        [torch.tensor([1e308, 1e308], dtype=torch.float64)],
        [torch.tensor([3e38, 3e38], dtype=torch.bfloat16)], [torch.tensor([float("nan")], dtype=torch.bfloat16)],
    ]
    for ts in cases:
        naive = all(bool(torch.isfinite(t).all()) for t in ts if t is not None)
        assert tensors_finite(ts) is naive, ts
    assert tensors_finite([big]) is True and tensors_finite([torch.tensor([float("inf"), -float("inf")])]) is False
