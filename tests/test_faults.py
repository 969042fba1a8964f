"""Faults: reproducibility, interrupt + resume at task level, bad data at the CLI."""

import json
import os

import pytest

from l3d_app.app import RunInterrupted, run_task

VOLATILE = {"seconds", "train_seconds", "render_seconds", "frames_per_second", "rays_per_second",
            "steps_per_second", "device", "interrupted", "eval_seconds", "points_per_second"}


def stable(metrics):
    """The metrics that must repeat: wall times dropped, also from each ``history`` entry."""
    out = {k: v for k, v in metrics.items() if k not in VOLATILE and "second" not in k}
    if "history" in out:
        out["history"] = [{k: v for k, v in h.items() if k != "seconds"} for h in out["history"]]
    return out


def read(path):
    return json.loads((path / "metrics.json").read_text())


FIT_POINT = ("task=fit_point", "num_points=400", "iters=30", "eval_every=10", "image_size=16",
             "num_frames=2")
FIT_VOX = ("task=fit_vox", "voxel_size=12", "iters=20", "eval_every=10", "image_size=16", "num_frames=2")


@pytest.mark.parametrize("overrides", [FIT_POINT, FIT_VOX], ids=["fit_point", "fit_vox"])
def test_same_config_and_seed_give_the_same_metrics(compose, tmp_path, overrides):
    run_task(compose(*overrides), out_dir=tmp_path / "a")
    run_task(compose(*overrides), out_dir=tmp_path / "b")
    assert stable(read(tmp_path / "a")) == stable(read(tmp_path / "b"))


def test_interrupted_run_resumes_to_the_uninterrupted_result(compose, tmp_path, monkeypatch):
    full, cut = tmp_path / "full", tmp_path / "cut"
    run_task(compose(*FIT_POINT), out_dir=full)
    monkeypatch.setenv("L3D_STOP_AT_STEP", "12")
    with pytest.raises(RunInterrupted):
        run_task(compose(*FIT_POINT), out_dir=cut)
    partial = read(cut)
    assert partial["interrupted"] is True and (cut / "checkpoint.pt").exists()
    monkeypatch.delenv("L3D_STOP_AT_STEP")
    run_task(compose(*FIT_POINT, "resume=true"), out_dir=cut)
    resumed = read(cut)
    assert not resumed.get("interrupted")
    a, b = stable(resumed), stable(read(full))
    # the resumed history also holds the evaluation made when the run was interrupted (step 12);
    # every evaluation of the uninterrupted run is in it with the same figures
    assert [h for h in a.pop("history") if h["step"] != 12] == b.pop("history")
    assert a == b


def test_bad_data_folders_exit_2_with_one_line(tmp_path):
    from cli_batch import run_batch

    bad_nerf = tmp_path / "nerf"
    bad_nerf.mkdir()
    (bad_nerf / "transforms_train.json").write_text(json.dumps({"frames": []}))  # no camera_angle_x
    cases = [["task=box", f"data.root={tmp_path / 'nothing'}"], ["task=train_nerf", "data=blender", f"data.root={bad_nerf}"]]
    for out in run_batch([[*args, f"hydra.run.dir={tmp_path / 'run'}"] for args in cases], tmp_path / "batch"):
        assert out["returncode"] == 2, out["stderr"]
        assert len(out["stderr"].strip().splitlines()) == 1 and "Traceback" not in out["stderr"]
        assert not (tmp_path / "run").exists()       # nothing written: the run directory is removed too


def test_a_resumed_train_nerf_run_keeps_its_before_picture_and_figure(compose, tmp_path, monkeypatch, data_cache):
    """before_val_psnr and before_after.png come from the untrained field: a resumed run carries
    them in its checkpoint (it cannot render them again), equal to the uninterrupted run's."""
    args = ("task=train_nerf", "iters=6", "eval_every=3", "gif_frames=0", "data.image_size=16", "data.n_train=4", "batch_rays=64",
            "data.n_val=1", "data.n_test=1", "time_budget=0", "tensorboard=false", f"data.cache_dir={data_cache}")
    run_task(compose(*args), out_dir=tmp_path / "full")
    monkeypatch.setenv("L3D_STOP_AT_STEP", "2")
    with pytest.raises(RunInterrupted):
        run_task(compose(*args), out_dir=tmp_path / "cut")
    monkeypatch.delenv("L3D_STOP_AT_STEP")
    run_task(compose(*args, "resume=true"), out_dir=tmp_path / "cut")
    full, cut = read(tmp_path / "full"), read(tmp_path / "cut")
    assert cut["before_val_psnr"] == full["before_val_psnr"] and (tmp_path / "cut" / "before_after.png").exists()


RESUMED_RATES = {
    "train_nerf": ("task=train_nerf", "iters=6", "eval_every=3", "gif_frames=0", "data.image_size=16",
                   "data.n_train=4", "data.n_val=1", "data.n_test=1", "time_budget=0", "batch_rays=64",
                   "sampler.resolution=16"),
    "volsdf": ("task=volsdf", "iters=6", "eval_every=3", "gif_frames=0", "data.image_size=16", "data.n_train=4",
               "data.n_val=1", "data.n_test=1", "time_budget=0", "batch_rays=64", "stages.free_space.steps=0",
               "stages.sphere_init.steps=5", "mesh_resolution=16", "eval_points=500", "before_after=false",
               "+sampler.resolution=16"),
    "fit_point": FIT_POINT,
}


@pytest.mark.parametrize("task", sorted(RESUMED_RATES))
def test_a_resumed_runs_timings_cover_the_whole_run(compose, tmp_path, monkeypatch, task, data_cache):
    """train_seconds (and a task's rays_per_second) of a resumed run count every step, the
    interrupted part's too: rays_per_second x train_seconds / batch_rays gives back all the steps."""
    cache = () if task == "fit_point" else (f"data.cache_dir={data_cache}",)
    args = (*RESUMED_RATES[task], "tensorboard=false", *cache)
    monkeypatch.setenv("L3D_STOP_AT_STEP", "2")
    with pytest.raises(RunInterrupted):
        run_task(compose(*args), out_dir=tmp_path)
    first = read(tmp_path)["train_seconds"]
    monkeypatch.delenv("L3D_STOP_AT_STEP")
    run_task(compose(*args, "resume=true"), out_dir=tmp_path)
    whole = read(tmp_path)
    assert whole["train_seconds"] > first > 0
    if "rays_per_second" in whole:
        steps = whole["rays_per_second"] * whole["train_seconds"] / 64
        assert steps == pytest.approx(whole["iters"], rel=1e-3), steps


def test_resuming_a_finished_neus_anneal_run_gives_back_its_figures(compose, tmp_path, data_cache):
    """resume=true on a finished volsdf run with an annealed NeuS density runs no step and evaluates the
    loaded field again: with the checkpoint's last s (not the configured start) its figures are the run's
    own (not those of the configured starting s = 3.0)."""
    args = (*RESUMED_RATES["volsdf"], "density=neus", "s=3.0", "density.mode=anneal", "density.s_end=100",
            "losses.ncc.weight=0", "tensorboard=false", f"data.cache_dir={data_cache}")
    run_task(compose(*args), out_dir=tmp_path)
    first = read(tmp_path)
    run_task(compose(*args, "resume=true"), out_dir=tmp_path)
    again = read(tmp_path)
    assert first["s_final"] == pytest.approx(100.0, rel=1e-5) and again["s_final"] == pytest.approx(100.0, rel=1e-5)
    assert again["psnr"] == pytest.approx(first["psnr"], abs=1e-3) and again["val_psnr"] == pytest.approx(first["val_psnr"], abs=1e-3)
