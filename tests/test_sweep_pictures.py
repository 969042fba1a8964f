"""A sweep's report beside its table: each job's loss curve (and its end value), each job's picture, and the
callback that writes the report when a sweep ends."""

from __future__ import annotations

import json

import numpy as np
import pytest
from omegaconf import OmegaConf

from l3d_app.report import make_report


def _job(root, name, overrides, losses, psnr, picture_shape=None):
    from torch.utils.tensorboard import SummaryWriter

    run = root / name
    (run / ".hydra").mkdir(parents=True)
    (run / ".hydra" / "overrides.yaml").write_text("".join(f"- {o}\n" for o in overrides))
    (run / "metrics.json").write_text(json.dumps({"psnr": psnr, "val_psnr": psnr, "seconds": 10.0 + psnr}))
    writer = SummaryWriter(str(run))
    for step, value in enumerate(losses):
        writer.add_scalar("train/loss", value, step)
    writer.close()
    if picture_shape is not None:
        import imageio.v2 as imageio
        imageio.imwrite(run / "test_views.png", np.full(picture_shape, 128, np.uint8))


def test_report_has_loss_curves_their_end_and_each_jobs_picture(tmp_path):
    a = np.linspace(1.0, 0.1, 40)
    b = np.linspace(2.0, 0.5, 20)
    _job(tmp_path, "0", ["beta=0.01"], a, 20.0, (16, 64, 3))
    _job(tmp_path, "1", ["beta=0.5"], b, 18.0, (16, 64, 3))
    paths = make_report(tmp_path)
    rows = {r["job"]: r for r in __import__("csv").DictReader(open(paths["csv"]))}
    assert float(rows["0"]["train_loss_end"]) == pytest.approx(a[-4:].mean(), rel=1e-5)     # last tenth of 40
    assert float(rows["1"]["train_loss_end"]) == pytest.approx(b[-2:].mean(), rel=1e-5)
    assert paths["loss"].stat().st_size > 0 and paths["views"].stat().st_size > 0
    import imageio.v2 as imageio
    views = imageio.imread(paths["views"])
    assert views.shape[0] > views.shape[1] / 4                 # two rows stacked, titled by their overrides
    md = paths["md"].read_text()
    assert "![loss](report_loss.png)" in md and "![views](report_views.png)" in md and "beta=0.5" in md


def test_pictures_are_labelled_by_what_differs_between_jobs():
    from l3d_app.runtime.sweep_pictures import varying_labels

    jobs = ["experiment=course_volsdf density.beta=0.01 iters=5", "experiment=course_volsdf density.beta=0.5 iters=5"]
    assert varying_labels(jobs) == ["density.beta=0.01", "density.beta=0.5"]
    assert varying_labels(["a=1 b=2"]) == ["a=1 b=2"]                     # one job: its whole line
    assert varying_labels(["a=1", "a=1 b=2"]) == ["a=1", "b=2"]             # nothing of its own: the whole line


def test_the_sweep_callback_writes_the_report_and_notes_what_it_cannot(tmp_path, capsys):
    from l3d_app.app import SweepReport

    _job(tmp_path, "0", ["lr=1"], [1.0, 0.5], 21.0)
    SweepReport().on_multirun_end(OmegaConf.create({"hydra": {"sweep": {"dir": str(tmp_path)}}}))
    assert (tmp_path / "report.md").is_file() and (tmp_path / "report_loss.png").is_file()
    assert "sweep report" in capsys.readouterr().err
    other = tmp_path / "other"
    (other / "0").mkdir(parents=True)
    (other / "0" / "metrics.json").write_text(json.dumps({"rmse": 1.0}))          # no error figure to compare
    SweepReport().on_multirun_end(OmegaConf.create({"hydra": {"sweep": {"dir": str(other)}}}))
    assert "no sweep report" in capsys.readouterr().err and not (other / "report.md").exists()
