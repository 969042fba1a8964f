import csv
import json
import subprocess
import sys

import pytest

from conftest import REPO
from l3d_app.errors import UserError
from l3d_app.report import make_report, pareto_front


def test_pareto_front_higher_and_lower_better():
    seconds = [1.0, 2.0, 3.0, 2.5]
    psnr = [20.0, 25.0, 24.0, 25.0]
    assert pareto_front(seconds, psnr, True) == [True, True, False, False]
    chamfer = [0.3, 0.1, 0.05, 0.2]
    assert pareto_front(seconds, chamfer, False) == [True, True, True, False]


def write_job(root, name, overrides, metrics):
    job = root / name
    (job / ".hydra").mkdir(parents=True)
    (job / ".hydra" / "overrides.yaml").write_text("".join(f"- {o}\n" for o in overrides))
    (job / "metrics.json").write_text(json.dumps(metrics))


def test_report_from_a_sweep_folder(tmp_path):
    write_job(tmp_path, "0", ["beta=0.02"], {"psnr": 24.0, "seconds": 10.0, "n_params": 100})
    write_job(tmp_path, "1", ["beta=0.05"], {"psnr": 26.0, "seconds": 12.0, "n_params": 100})
    write_job(tmp_path, "2", ["beta=0.1"], {"psnr": 25.0, "seconds": 15.0, "n_params": 100})
    paths = make_report(tmp_path)
    rows = list(csv.DictReader(paths["csv"].open()))
    assert [r["overrides"] for r in rows] == ["beta=0.02", "beta=0.05", "beta=0.1"]
    assert [r["pareto"] for r in rows] == ["True", "True", "False"]
    assert "| beta=0.05 |" in paths["md"].read_text()
    assert paths["png"].read_bytes()[:4] == b"\x89PNG"


def test_report_errors_are_clear(tmp_path):
    with pytest.raises(UserError, match="no metrics.json"):
        make_report(tmp_path)
    write_job(tmp_path, "0", [], {"seconds": 1.0})
    with pytest.raises(UserError, match="--error"):
        make_report(tmp_path)
    out = subprocess.run([sys.executable, "-m", "l3d_app.report", str(tmp_path / "missing")],
                         capture_output=True, text=True, cwd=REPO)
    assert out.returncode == 2 and "not found" in out.stderr


def test_report_on_a_real_multirun(tmp_path):
    sweep = tmp_path / "sweep"
    out = subprocess.run([sys.executable, str(REPO / "main.py"), "-m", "image_size=16,32", "num_frames=2",
                          f"hydra.sweep.dir={sweep}"], capture_output=True, text=True, cwd=REPO,
                         env={**__import__("os").environ, "L3D_NO_PROGRESS": "1"})
    assert out.returncode == 0, out.stderr
    paths = make_report(sweep, error="coverage")
    rows = list(csv.DictReader(paths["csv"].open()))
    assert sorted(r["overrides"] for r in rows) == ["image_size=16 num_frames=2", "image_size=32 num_frames=2"]


def test_the_front_is_drawn_on_validation_figures_where_every_job_has_them(tmp_path):
    """psnr (test) would put job b on the front; val_psnr, which may choose, puts a there instead
    (b is slower and worse on val); both columns stay in the table."""
    for name, m in {"a": {"psnr": 30.0, "val_psnr": 31.0, "seconds": 10.0},
                    "b": {"psnr": 32.0, "val_psnr": 30.5, "seconds": 20.0}}.items():
        (tmp_path / name).mkdir()
        (tmp_path / name / "metrics.json").write_text(json.dumps(m))
    paths = make_report(tmp_path)
    rows = list(csv.DictReader(paths["csv"].open()))
    assert [r["pareto"] for r in rows] == ["True", "False"]
    assert {"val_psnr", "psnr"} <= set(rows[0])
    assert "val_psnr" in paths["md"].read_text().splitlines()[0]
