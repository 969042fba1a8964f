"""Every optimiser of conf/optim/ builds for every task that offers optim= (the task's own schedule
knobs reach only the optimiser that has them: nerf_baseline's lr_decay, volsdf's warm-up, box's
lr_final_factor, neural_sdf's lr_final_ratio)."""

from pathlib import Path

import pytest
import torch

from conftest import REPO
from l3d_app.runtime.optim import build_optimizer

OPTIMS = sorted(p.stem for p in (REPO / "conf" / "optim").glob("*.yaml"))
TASKS = ("train_nerf", "nerf_baseline", "volsdf", "box", "neural_sdf", "sds_nerf")


@pytest.mark.parametrize("task", TASKS)
@pytest.mark.parametrize("optim", OPTIMS)
def test_every_optimiser_builds_for_every_task_that_offers_the_group(compose, task, optim):
    import l3d_app.runtime.optim  # noqa: F401  (registers the optimisers)

    cfg = compose(f"task={task}", f"optim={optim}")
    params = [torch.nn.Parameter(torch.zeros(3))]
    optim_cfg = cfg.optim
    if task == "volsdf":                    # warmup_steps=auto becomes the density's number, as the task does
        from l3d_app.render.sdf.density_choice import with_density_warmup
        from l3d_app.render.sdf.densities import VolSDFDensity
        from l3d_app.render.sdf.neus import NeuSDensity
        optim_cfg = with_density_warmup(cfg.optim, NeuSDensity())
        if "warmup_steps" in optim_cfg:
            assert optim_cfg["warmup_steps"] == 150
            assert with_density_warmup(cfg.optim, VolSDFDensity())["warmup_steps"] == 50
    opt, _ = build_optimizer(optim_cfg, params, 100)
    assert opt.param_groups[0]["lr"] > 0


@pytest.mark.parametrize("task, optim, expected", [
    ("train_nerf", "adam_step", {"decay": 0.33, "decay_every": 1000}),          # the group's own values
    ("nerf_baseline", "adam_step", {"decay": 0.8, "decay_every": 20000}),
    ("volsdf", "warmup_cosine", {"warmup_steps": "auto", "final_ratio": 0.05}),   # the task resolves auto
    ("volsdf", "adam_cosine", {"final_ratio": 0.05}),
    ("box", "adam_exp", {"lr": 0.02, "final_factor": 0.01}),
    ("neural_sdf", "adam_cosine", {"lr": 0.001, "final_ratio": 0.05}),
    ("neural_sdf", "warmup_cosine", {"final_ratio": 0.05}),
    ("sds_nerf", "adam", {"lr": 0.01, "eps": 1e-15}),
])
def test_task_schedule_knobs_reach_the_optimiser_that_has_them(compose, task, optim, expected):
    cfg = compose(f"task={task}", f"optim={optim}", "seed=0")
    assert {k: cfg.optim[k] for k in expected} == expected
