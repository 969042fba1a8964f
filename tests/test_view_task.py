"""task=view rebuilds a finished run's model: from a training camera it draws what the run scored."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from l3d_app.metrics.image import psnr

REPO = Path(__file__).resolve().parents[1]
DATA = ["data.image_size=32", "data.n_train=20", "data.n_val=2", "data.n_test=2", "data.antialias=1",
        "tensorboard=false", "threads=1"]


def _train(tmp: Path, name: str, *overrides: str) -> Path:
    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf

    from l3d_app.app import run_task

    with initialize_config_dir(version_base="1.3", config_dir=str(REPO / "conf")):
        cfg = compose(config_name="config", overrides=[*overrides, *DATA, f"data.cache_dir={tmp / 'cache'}"])
    run_dir = tmp / name
    run_task(cfg, out_dir=run_dir)
    (run_dir / ".hydra").mkdir(exist_ok=True)                      # as Hydra writes it beside every run
    OmegaConf.save(cfg, run_dir / ".hydra" / "config.yaml")
    return run_dir


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    torch.set_num_threads(1)
    tmp = tmp_path_factory.mktemp("view")
    return {"gs_train": _train(tmp, "gs", "task=gs_train", "iters=20", "eval_every=20", "n_init=800", "sh_every=10"),
            "train_nerf": _train(tmp, "nerf", "task=train_nerf", "iters=20", "eval_every=20", "gif_frames=0",
                                 "before_after=false", "batch_rays=512")}


@pytest.mark.parametrize("task", ["gs_train", "train_nerf"])
def test_view_draws_the_runs_final_model(runs, task):
    from l3d_app.tasks.view import _from_run

    run_dir = runs[task]
    (snapshot, render), data, name = _from_run(run_dir, torch.device("cpu"))
    assert name == task
    m = json.loads((run_dir / "metrics.json").read_text())
    with torch.no_grad():
        pred = torch.stack([render(snapshot(0), data.cameras[int(i):int(i) + 1]) for i in data.val])
    # the run's own last validation, re-rendered from the saved model through the viewer's path
    assert float(psnr(pred.clamp(0, 1), data.images[data.val])) == pytest.approx(m["val_psnr"], abs=0.02)


def test_view_refuses_what_it_cannot_serve(tmp_path, runs):
    from l3d_app.errors import UserError
    from l3d_app.tasks.view import _from_run

    with pytest.raises(UserError, match="not a run directory"):
        _from_run(tmp_path, torch.device("cpu"))
    broken = tmp_path / "broken"
    (broken / ".hydra").mkdir(parents=True)
    (broken / ".hydra" / "config.yaml").write_text((runs["train_nerf"] / ".hydra" / "config.yaml").read_text())
    with pytest.raises(UserError, match=r"no checkpoint.pt \(the run did not finish\)"):
        _from_run(broken, torch.device("cpu"))
