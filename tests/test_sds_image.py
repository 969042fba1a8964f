"""sds_image end to end: an analytic oracle prior (SDS must reach its image), a tiny built-in
prior checkpoint (outputs, metrics, errors), and the checker's verdict in metrics.json."""

from __future__ import annotations

import json

import pytest
import torch

from l3d_app.app import run_task
from l3d_app.diffusion.builtin_prior import BuiltinPrior, export_state
from l3d_app.diffusion.registry import PRIORS
from l3d_app.errors import UserError
from sds_oracles import OraclePrior
from sds_task_runs import run_metrics



if "sds_test_oracle" not in PRIORS:
    PRIORS.register("sds_test_oracle")(OraclePrior)

SMALL = ("threads=1", "tensorboard=false", "frame_every=5")


def _run(compose, out, *overrides):
    cfg = compose("task=sds_image", *SMALL, *overrides)
    run_task(cfg, out)
    return json.loads((out / "metrics.json").read_text())


def test_sds_reaches_the_oracle_image_and_the_checker_agrees(compose, tmp_path):
    m = _run(compose, tmp_path, "prompt='a blue square on black'", "prior.name=sds_test_oracle",
             "iters=150", "lr=0.05", "guidance_scale=1.0", "t_max=0.5")
    assert m["match"] == 1 and m["skipped_steps"] == 0
    assert (m["seen_colour"], m["seen_shape"], m["seen_background"]) == ("blue", "square", "black")
    for name in ("final.png", "final_x8.png", "progress.gif"):
        assert (tmp_path / name).stat().st_size > 0


def test_oracle_unguided_result_is_the_unconditional_image(compose, tmp_path):
    m = _run(compose, tmp_path, "prompt='a blue square on black'", "prior.name=sds_test_oracle",
             "iters=150", "lr=0.05", "guidance_scale=0.0", "t_max=0.5")
    assert m["match"] == 0 and m["seen_shape"] is None  # flat grey: no shape at all


def test_shipped_prior_paints_the_prompt_the_checker_reads(compose, tmp_path):
    """The shipped built-in prior, 60 steps (a few CPU seconds): the prompt checker must read
    the prompt's colour and shape in the result. (Seed 0 chosen for this test; seeds 1-3 matched
    too when it was written. A broken guidance, loss sign or prior gives a grey or wrong image.)"""
    m = run_metrics(compose, tmp_path, "task=sds_image", *SMALL, "prompt='a red circle'", "iters=60", "seed=0")
    assert (m["seen_colour"], m["seen_shape"]) == ("red", "circle"), m
    assert m["match"] == 1 and m["skipped_steps"] == 0


@pytest.fixture
def tiny_checkpoint(tmp_path):
    torch.manual_seed(0)
    priors = {s: BuiltinPrior(s, image_size=16, channels=8) for s in ("pixel", "latent")}
    path = tmp_path / "tiny_prior.pt"
    torch.save(export_state(priors, {"test": True}), path)
    return path


@pytest.mark.parametrize("space", ["pixel", "latent"])
def test_builtin_prior_run_writes_outputs(compose, tmp_path, tiny_checkpoint, space):
    out = tmp_path / space
    m = _run(compose, out, f"space={space}", f"prior.checkpoint={tiny_checkpoint}", "iters=12",
             "guidance_scale=100")
    assert m["iters"] == 12 and m["skipped_steps"] == 0 and "match" in m   # a random prior: no quality claim
    assert m["space"] == space and m["seconds"] > 0 and m["final_grad_norm"] == m["final_grad_norm"]
    assert (out / "final.png").exists() and (out / "progress.gif").exists()


def test_bad_inputs_are_user_errors(compose, tmp_path, tiny_checkpoint):
    with pytest.raises(UserError, match="vocabulary"):
        _run(compose, tmp_path, "prompt='a red dragon'", f"prior.checkpoint={tiny_checkpoint}", "iters=2")
    with pytest.raises(UserError, match="not found"):
        _run(compose, tmp_path, f"prior.checkpoint={tmp_path / 'nope.pt'}", "iters=2")
    with pytest.raises(UserError, match="t_min"):
        _run(compose, tmp_path, f"prior.checkpoint={tiny_checkpoint}", "iters=2", "t_min=0.9", "t_max=0.1")
    with pytest.raises(UserError, match="t_max_end"):
        _run(compose, tmp_path, f"prior.checkpoint={tiny_checkpoint}", "iters=2", "t_max_end=0.99")
    with pytest.raises(UserError, match="space=latent"):
        _run(compose, tmp_path, f"prior.checkpoint={tiny_checkpoint}", "iters=2", "space=latent",
             "prior.space=pixel")
