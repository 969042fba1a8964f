"""Launcher and sweeper configs compose (skipped with a reason when a plugin is absent)."""

import importlib.util

import pytest
from hydra import compose, initialize_config_dir

from conftest import REPO


def needs(module):
    if importlib.util.find_spec(module) is None:
        pytest.skip(f"optional plugin not installed: {module} (pip install -e '.[sweep]')")


def compose_hydra(*overrides):
    with initialize_config_dir(version_base="1.3", config_dir=str(REPO / "conf")):
        return compose(config_name="config", overrides=list(overrides), return_hydra_config=True)


def test_local_parallel_launcher_composes():
    needs("hydra_plugins.hydra_joblib_launcher")
    cfg = compose_hydra("hydra/launcher=local_parallel")
    assert cfg.hydra.launcher.n_jobs == 2 and "JoblibLauncher" in cfg.hydra.launcher._target_


def test_slurm_launcher_composes():
    needs("hydra_plugins.hydra_submitit_launcher")
    cfg = compose_hydra("hydra/launcher=slurm", "hydra.launcher.partition=gpu")
    assert cfg.hydra.launcher.partition == "gpu" and "Slurm" in cfg.hydra.launcher._target_


@pytest.mark.parametrize("sweeper, param", [("optuna_volsdf", "density.beta"), ("optuna_nerf", "optim.lr")])
def test_optuna_sweepers_compose(sweeper, param):
    needs("hydra_plugins.hydra_optuna_sweeper")
    cfg = compose_hydra(f"hydra/sweeper={sweeper}", "objective=val_psnr")
    assert param in cfg.hydra.sweeper.params and cfg.hydra.sweeper.direction == "maximize"
    assert cfg.objective == "val_psnr"


def test_experiment_nerf_baseline_is_the_task_alias(compose):
    """`experiment=nerf_baseline` (the variant filed as an experiment) composes exactly the
    config `task=nerf_baseline` does, and command-line knobs still override it."""
    from omegaconf import OmegaConf

    as_task = OmegaConf.to_container(compose("task=nerf_baseline"), resolve=False)
    as_experiment = OmegaConf.to_container(compose("experiment=nerf_baseline"), resolve=False)
    assert as_experiment == as_task
    assert as_experiment["task_name"] == "train_nerf" and as_experiment["sampler"]["name"] == "hierarchical"
    assert compose("experiment=nerf_baseline", "iters=5").iters == 5
    assert compose().task_name == "render360"          # no experiment by default
