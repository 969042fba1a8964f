"""End-to-end: the app through Hydra's compose API and through main.py itself."""

import json
import os
import subprocess
import sys

import imageio.v2 as imageio
import pytest

from cli_batch import run_batch
from conftest import REPO
from l3d_app.app import run_task
from l3d_app.errors import UserError


def test_render360_writes_gif_metrics_and_events(compose, tmp_path):
    cfg = compose("image_size=32", "num_frames=4", "batch_frames=3")
    run_task(cfg, out_dir=tmp_path)
    metrics = json.loads((tmp_path / "metrics.json").read_text())
    for key in ("seconds", "frames_per_second", "num_frames", "n_faces", "coverage"):
        assert key in metrics
    assert metrics["num_frames"] == 4 and 0.02 < metrics["coverage"] < 0.9
    frames = imageio.mimread(tmp_path / "turntable.gif")
    assert len(frames) == 4 and frames[0].shape[:2] == (32, 32)
    assert any(name.startswith("events.out.tfevents") for name in os.listdir(tmp_path))


def test_objective_is_returned_and_checked(compose, tmp_path):
    value = run_task(compose("image_size=16", "num_frames=2", "objective=coverage"), out_dir=tmp_path)
    assert value == json.loads((tmp_path / "metrics.json").read_text())["coverage"]
    with pytest.raises(UserError, match="objective 'psnr'"):
        run_task(compose("image_size=16", "num_frames=2", "objective=psnr"), out_dir=tmp_path)


@pytest.mark.parametrize("override", ["num_frames=0", "image_size=-4", "fov=0"])
def test_bad_sizes_are_user_errors(compose, tmp_path, override):
    with pytest.raises(UserError):
        run_task(compose("image_size=16", "num_frames=2", override), out_dir=tmp_path)
    assert not (tmp_path / "metrics.json").exists()


def test_unknown_data_key_is_rejected(compose, tmp_path):
    with pytest.raises(UserError, match="unknown key 'colour'"):
        run_task(compose("image_size=16", "num_frames=2", "+data.colour=red"), out_dir=tmp_path)


def test_dolly_keeps_subject_width(compose, tmp_path):
    """The subject's projected width is constant across the zoom (within 2%)."""
    cfg = compose("task=dolly", "data.scene=icosphere", "image_size=128", "num_frames=6",
                  "backdrop=false", "renderer.antialias=2", "fov_start=10", "fov_end=90")
    metrics = (run_task(cfg, out_dir=tmp_path), json.loads((tmp_path / "metrics.json").read_text()))[1]
    assert metrics["subject_width_spread"] < 0.02
    assert metrics["subject_width_px"] == pytest.approx(0.45 * 128, rel=0.03)
    assert len(imageio.mimread(tmp_path / "dolly.gif")) == 6


def main_py(*args, cwd=None):
    env = dict(os.environ, L3D_NO_PROGRESS="1")
    return subprocess.run([sys.executable, str(REPO / "main.py"), *args], cwd=cwd or REPO,
                          capture_output=True, text=True, env=env, timeout=300)


def test_cli_dolly_with_backdrop(tmp_path):
    out = main_py("task=dolly", "num_frames=3", "image_size=48", f"hydra.run.dir={tmp_path}")
    assert out.returncode == 0, out.stderr
    assert (tmp_path / "dolly.gif").exists() and (tmp_path / "metrics.json").exists()


def test_cli_multirun_writes_one_directory_per_job(tmp_path):
    out = main_py("-m", "task=render360", "image_size=16,24", "num_frames=2", "objective=seconds",
                  f"hydra.sweep.dir={tmp_path}")
    assert out.returncode == 0, out.stderr                  # seconds, a cost, is an accepted sweep objective
    sizes = sorted(json.loads((tmp_path / str(i) / "metrics.json").read_text())["image_size"]
                   for i in range(2))
    assert sizes == [16, 24]


def test_cli_sweep_runs_every_job_past_bad_input(tmp_path):
    """A job with bad input prints its line and the sweep goes on; exit 2 at the end."""
    out = main_py("-m", "task=render360", "image_size=16,-4,24,0", "num_frames=2", f"hydra.sweep.dir={tmp_path}")
    assert out.returncode == 2, out.stderr
    errors = [line for line in out.stderr.splitlines() if "HYDRA" not in line]
    assert errors == [
        "l3d_app: error: sweep job #1 (task=render360 image_size=-4 num_frames=2): "
        "image_size must be a positive number, got -4",
        "l3d_app: error: sweep job #3 (task=render360 image_size=0 num_frames=2): "
        "image_size must be a positive number, got 0",
        "l3d_app: error: 2 sweep jobs stopped on bad input (#1, #3: the lines above); the other jobs ran to the end"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["0", "2", "multirun.yaml"]   # no folder for a bad job
    sizes = [json.loads((tmp_path / job / "metrics.json").read_text())["image_size"] for job in ("0", "2")]
    assert sizes == [16, 24]


def test_cli_sweep_refuses_a_test_figure_as_objective(tmp_path):
    """A sweeper chooses by the objective: not by the test split where a validation figure exists
    (fit_point reports val_chamfer beside chamfer); the job's outputs are kept. (val_chamfer is accepted:
    test_a_sweep_objective_is_a_validation_figure_or_a_cost; a sweep with an accepted objective:
    test_cli_multirun_writes_one_directory_per_job.)"""
    args = ("task=fit_point", "num_points=300", "iters=4", "eval_every=2", "image_size=16", "num_frames=2",
            "tensorboard=false")
    out = main_py("-m", *args, "objective=chamfer", f"hydra.sweep.dir={tmp_path / 'test'}")
    assert out.returncode == 2, out.stderr
    assert "objective 'chamfer' is not a validation figure" in out.stderr and "objective=val_chamfer" in out.stderr
    assert (tmp_path / "test" / "0" / "metrics.json").exists() and "Traceback" not in out.stderr


def test_a_sweep_refuses_a_refused_objective_before_its_later_jobs_run(tmp_path):
    """Job #0 runs and has its objective refused; jobs #1 and #2 (the same task) are refused before they
    run: one line each naming job #0, no folder; the summary counts all three."""
    out = main_py("-m", "task=fit_point", "num_points=300,301,302", "iters=4", "eval_every=2", "image_size=16",
                  "num_frames=2", "tensorboard=false", "objective=chamferr", f"hydra.sweep.dir={tmp_path}")
    assert out.returncode == 2, out.stderr
    errors = [line for line in out.stderr.splitlines() if line.startswith("l3d_app: error:")]
    assert "objective 'chamferr' is not a metric of this task" in errors[0], errors
    for job, line in zip((1, 2), errors[1:3]):
        assert line.startswith(f"l3d_app: error: sweep job #{job} "), errors
        assert line.endswith("objective 'chamferr' was refused after sweep job #0 of this sweep ran fit_point "
                             "(its line above says why): this job is not run"), errors
    assert errors[3].startswith("l3d_app: error: 3 sweep jobs stopped on bad input (#0, #1, #2"), errors
    assert sorted(p.name for p in tmp_path.iterdir()) == ["0", "multirun.yaml"] and "Traceback" not in out.stderr


def test_a_sweep_objective_is_a_validation_figure_or_a_cost():
    """precision has no val_ twin in fit_point's metrics and is still a test figure; seconds is a cost."""
    from l3d_app.app import require_choosing_objective

    metrics = {"chamfer": 0.1, "precision": 0.9, "val_chamfer": 0.2, "val_f1": 0.8, "seconds": 3.0, "n_points": 5}
    with pytest.raises(UserError, match="optimises one of val_chamfer, val_f1"):
        require_choosing_objective("precision", metrics)
    for ok in ("val_chamfer", "val_f1", "seconds", "n_points"):
        require_choosing_objective(ok, metrics)
    require_choosing_objective("coverage", {"coverage": 0.3, "seconds": 1.0})   # no validation split: nothing to prefer


def test_cli_sweep_of_only_bad_jobs_leaves_nothing(tmp_path):
    out = main_py("-m", "task=render360", "image_size=-4,0", "num_frames=2", f"hydra.sweep.dir={tmp_path / 'sweep'}")
    assert out.returncode == 2, out.stderr
    assert out.stderr.strip().splitlines()[-1].endswith("no job ran, no sweep directory left")
    assert "Traceback" not in out.stderr and not (tmp_path / "sweep").exists()


BAD_INPUT = [
    (["task=nope"], "task"),
    (["image_sise=64"], "image_sise"),
    (["data=mesh"], "data.path"),
    (["data=mesh", "data.path=/no/such/mesh.obj"], "not found"),
    (["data=builtin", "data.scene=teapot"], "teapot"),
    # a value of the wrong type for its default: refused before anything runs (command_line.py)
    (["task=fit_point", "iters=2.5"], "iters must be an integer, got 2.5"),
    (["elevation=abc"], "elevation must be a number, got 'abc'"),
    (["tensorboard=no"], "tensorboard must be true or false, got 'no'"),
    (["renderer.antialias=1.5"], "renderer.antialias must be an integer, got 1.5"),    # a key of a config group
]
CONFIG_ERRORS = [
    (["task=gs_train", "gif_frames=0"], "gif_frames"),            # a key this task does not have
    (["image_size==3"], "image_size==3"),                          # a malformed override
    (["-m", "task=render360", "image_sise=16,24"], "image_sise"),  # a typo in a sweep
]


@pytest.fixture(scope="module")
def cli_errors(tmp_path_factory):
    """Every bad command line below, run as ``python main.py ...`` in one interpreter (tests/cli_batch.py):
    case name -> (its run / sweep folder, {"returncode", "stderr"})."""
    root = tmp_path_factory.mktemp("cli")
    bad = root / "bad.obj"
    bad.write_text("v 0 0 0\nv 1 0 0\nf 1 2 7\n")
    (root / "taken").write_text("not a folder")
    cases = {f"bad{i}": [*args, "num_frames=2", "image_size=16"] for i, (args, _) in enumerate(BAD_INPUT)}
    cases.update({f"config{i}": list(args) for i, (args, _) in enumerate(CONFIG_ERRORS)})
    cases.update({"malformed_obj": ["data=mesh", f"data.path={bad}", "num_frames=2", "image_size=16"],
                  "run_dir_is_a_file": ["num_frames=2", "image_size=16", f"hydra.run.dir={root / 'taken'}"],
                  "flag_conflict": ["-m", "task=render360", "--cfg", "job"]})
    folders = {name: root / name for name in cases}
    argv = [args if name in ("run_dir_is_a_file", "flag_conflict") else
            [*args, f"hydra.run.dir={folders[name] / 'run'}", f"hydra.sweep.dir={folders[name] / 'sweep'}"]
            for name, args in cases.items()]
    results = run_batch(argv, root / "batch")
    return root, {name: (folders[name], res) for name, res in zip(cases, results)}


@pytest.mark.parametrize("case", range(len(BAD_INPUT)))
def test_cli_bad_input_is_one_clear_line(cli_errors, case):
    folder, out = cli_errors[1][f"bad{case}"]
    assert out["returncode"] == 2, out["stderr"]
    assert BAD_INPUT[case][1] in out["stderr"]
    assert len(out["stderr"].strip().splitlines()) == 1, out["stderr"]
    assert "Traceback" not in out["stderr"]
    assert not (folder / "run").exists()      # no run directory left behind: nothing was written


@pytest.mark.parametrize("case", range(len(CONFIG_ERRORS)))
def test_cli_config_errors_are_one_line_exit_2(cli_errors, case):
    """Hydra's own errors (composition, override grammar) end like every other bad input."""
    folder, out = cli_errors[1][f"config{case}"]
    assert out["returncode"] == 2, out["stderr"]
    assert CONFIG_ERRORS[case][1] in out["stderr"] and out["stderr"].startswith("l3d_app: error:")
    assert len(out["stderr"].strip().splitlines()) == 1, out["stderr"]
    assert not (folder / "run").exists()


def test_cli_hydra_flag_conflict_is_one_line_exit_2(cli_errors):
    out = cli_errors[1]["flag_conflict"][1]
    assert out["returncode"] == 2 and out["stderr"].strip() == (
        "l3d_app: error: Only one of --run, --multirun, --cfg, --info and --shell_completion can be specified")


def test_cli_run_directory_that_is_a_file_exits_2(cli_errors):
    root, out = cli_errors[0], cli_errors[1]["run_dir_is_a_file"][1]
    assert out["returncode"] == 2, out["stderr"]
    assert out["stderr"].startswith("l3d_app: error: File exists:") and "hydra.run.dir" in out["stderr"]
    assert len(out["stderr"].strip().splitlines()) == 1 and (root / "taken").read_text() == "not a folder"


def test_cli_malformed_obj_exits_2(cli_errors):
    out = cli_errors[1]["malformed_obj"][1]
    assert out["returncode"] == 2
    assert len(out["stderr"].strip().splitlines()) == 1, out["stderr"]


@pytest.mark.parametrize("overrides", [["camera=side_view"], ["camera=relative", "camera.translation=[0,0,2]"],
                                       ["retexture.enabled=true", "retexture.axis=y"]])
def test_render360_camera_and_retexture_options(compose, tmp_path, overrides):
    run_task(compose("image_size=24", "num_frames=2", *overrides), out_dir=tmp_path)
    metrics = json.loads((tmp_path / "metrics.json").read_text())
    assert metrics["num_frames"] == (2 if "retexture" in overrides[0] else 1)
    assert metrics["coverage"] > 0.01 and (tmp_path / "frame0.png").exists()


@pytest.mark.parametrize("data", [["data=mesh_points", "data.num_samples=3000", "data.color=normals"],
                                  ["data=torus_parametric", "data.num_samples=3000"],
                                  ["data=torus_implicit", "data.resolution=24"],
                                  ["data=rgbd", "data.image_size=32", "data.num_views=2"]])
def test_render360_surfaces_and_point_clouds(compose, tmp_path, data):
    run_task(compose("image_size=32", "num_frames=2", *data), out_dir=tmp_path)
    metrics = json.loads((tmp_path / "metrics.json").read_text())
    assert metrics["coverage"] > 0.02 and (tmp_path / "turntable.gif").exists()


@pytest.mark.parametrize("exc", [ValueError("bad radius -1 (must be > 0)\nsecond line"),
                                 TypeError("expected a Mesh, got PointCloud")])
def test_library_value_and_type_errors_are_one_line_exit_2(compose, tmp_path, monkeypatch, capsys, exc):
    """Library code raises plain ValueError / TypeError; the app prints one line, exits 2,
    writes no metrics; L3D_DEBUG=1 lets the exception (and its traceback) through."""
    from l3d_app.app import run
    from l3d_app.registry import TASKS

    def failing_task(cfg, ctx):
        raise exc

    monkeypatch.setitem(TASKS._entries, "failing_probe", failing_task)
    cfg = compose("image_size=16", "num_frames=2")
    cfg.task_name = "failing_probe"
    monkeypatch.delenv("L3D_DEBUG", raising=False)
    with pytest.raises(SystemExit) as stop:
        run(cfg, out_dir=tmp_path)
    assert stop.value.code == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and str(exc).split("\n")[0] in err
    assert type(exc).__name__ in err and "L3D_DEBUG=1" in err and "Traceback" not in err
    assert not (tmp_path / "metrics.json").exists()
    monkeypatch.setenv("L3D_DEBUG", "1")
    with pytest.raises(type(exc)):
        run(cfg, out_dir=tmp_path)


def test_user_error_message_is_printed_as_is(compose, tmp_path, monkeypatch, capsys):
    from l3d_app.app import run

    monkeypatch.delenv("L3D_DEBUG", raising=False)
    with pytest.raises(SystemExit) as stop:
        run(compose("image_size=16", "num_frames=2", "+renderer.shadng=flat"), out_dir=tmp_path)
    err = capsys.readouterr().err.strip()
    assert stop.value.code == 2 and err.startswith("l3d_app: error: unknown key 'shadng'")
    assert "Did you mean 'shading'" in err and "L3D_DEBUG" not in err


def test_registry_builds_from_omegaconf_without_importing_it():
    """Registry.build converts nested config containers to plain dicts / lists (duck-typed)."""
    from omegaconf import OmegaConf

    from l3d_app.registry import Registry, plain

    reg = Registry("probe")
    reg.register("echo")(lambda **kw: kw)
    cfg = OmegaConf.create({"x": 2, "probe": {"name": "echo", "sizes": [1, "${x}"], "sub": {"a": (1, 2)}}})
    out = reg.build(cfg.probe)
    assert out == {"sizes": [1, 2], "sub": {"a": [1, 2]}}
    assert type(out["sizes"]) is list and type(out["sub"]) is dict
    assert plain({"t": (1, [2])}) == {"t": (1, [2])} and plain("abc") == "abc"


@pytest.mark.parametrize("how", ["sigint", "sigterm"])
def test_a_stop_outside_the_training_loop_is_one_line_and_130(compose, tmp_path, monkeypatch, capsys, how):
    """Ctrl-C (or SIGTERM) while a task sets up or writes its pictures: exit 130 and one line,
    not a KeyboardInterrupt traceback or a silent 143."""
    import signal
    import time

    from l3d_app import app

    def task(cfg, ctx):
        if how == "sigint":
            raise KeyboardInterrupt
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(5)                                   # the handler raises before this ends
        return {}

    monkeypatch.setattr(app.TASKS, "get", lambda name: task)
    before = signal.getsignal(signal.SIGTERM)
    with pytest.raises(SystemExit) as stop:
        app.run(compose("tensorboard=false"), out_dir=tmp_path)
    err = capsys.readouterr().err
    assert stop.value.code == 130 and err.startswith("l3d_app: interrupted outside the training loop")
    assert len(err.strip().splitlines()) == 1
    assert signal.getsignal(signal.SIGTERM) == before                   # the app's handler is gone again
