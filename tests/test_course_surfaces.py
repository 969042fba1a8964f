"""The course's surface-rendering settings as experiments: experiment=course_volsdf (alpha 10, beta 0.05 fixed) and
experiment=course_neus (s 20 fixed) on an MLP SDF with 128 stratified samples; their shorthands (beta=, s=) under
``experiment=`` as under ``task=volsdf``; a short run of each learns."""

from __future__ import annotations

import json

import pytest

from l3d_app.aliases import expand_aliases, experiment_task
from l3d_app.app import run_task


def test_course_volsdf_is_the_course_setting(compose):
    cfg = compose("experiment=course_volsdf")
    assert cfg.task_name == "volsdf" and cfg.model.name == "sdf_field"
    net = cfg.model.sdf_net
    assert (net.encoding, net.n_frequencies, net.hidden, net.n_layers) == ("harmonic", 6, 128, 6)
    assert (cfg.model.color_net.hidden, cfg.model.color_net.n_layers) == (128, 2)
    assert (cfg.density.name, cfg.density.beta, cfg.density.alpha, cfg.density.mode) == ("volsdf", 0.05, 10.0, "fixed")
    assert (cfg.sampler.name, cfg.sampler.n_samples) == ("stratified", 128)
    assert (cfg.optim.name, cfg.optim.lr, cfg.optim.decay, cfg.optim.decay_every) == ("adam_step", 5e-4, 0.8, 5000)
    assert sorted(cfg.losses) == ["color", "eikonal"] and cfg.losses.eikonal.weight == 0.02
    assert list(cfg.stages) == ["sphere_init"] and cfg.stages.sphere_init.steps == 1000
    assert cfg.batch_rays == 1024


def test_course_neus_shares_the_setting_with_its_own_density(compose):
    volsdf, neus = compose("experiment=course_volsdf"), compose("experiment=course_neus")
    assert (neus.density.name, neus.density.s, neus.density.mode) == ("neus", 20.0, "fixed")
    assert "beta" not in neus.density and "alpha" not in neus.density
    for key in ("model", "sampler", "optim", "losses", "stages", "iters", "batch_rays"):
        assert neus[key] == volsdf[key], key
    logistic = compose("experiment=course_neus", "density=neus_logistic")
    assert (logistic.density.name, logistic.density.s) == ("neus_logistic", 20.0)


def test_shorthands_follow_the_experiments_task(compose):
    assert experiment_task("course_volsdf") == "volsdf" and experiment_task("course_neus") == "volsdf"  # included
    assert experiment_task("no_such_experiment") is None
    assert expand_aliases(["-m", "experiment=course_volsdf", "beta=0.01,0.5", "iters=5"]) == \
        ["-m", "experiment=course_volsdf", "density.beta=0.01,0.5", "iters=5"]
    assert expand_aliases(["experiment=course_neus", "s=50"]) == ["experiment=course_neus", "density.s=50"]
    assert expand_aliases(["experiment=nerf_baseline", "beta=1"]) == ["experiment=nerf_baseline", "beta=1"]
    for beta in (0.01, 0.5):
        cfg = compose("experiment=course_volsdf", f"beta={beta}")
        assert cfg.density.beta == beta and cfg.density.alpha == 10.0
    assert compose("experiment=course_neus", "density=neus_logistic", "s=50").density.s == 50


TINY = ["data.image_size=16", "data.n_train=10", "data.n_val=1", "data.n_test=1", "supersample=1", "batch_rays=128",
        "iters=20", "eval_every=10", "stages.sphere_init.steps=20", "gif_frames=0", "mesh_resolution=16",
        "eval_points=500", "time_budget=0", "tensorboard=false", "threads=1"]


@pytest.mark.parametrize("experiment, density", [("course_volsdf", "volsdf"), ("course_neus", "neus_logistic")])
def test_a_short_course_run_learns_with_its_fixed_density(compose, tmp_path, data_cache, experiment, density):
    cfg = compose(f"experiment={experiment}", f"density={density}", *TINY, f"data.cache_dir={data_cache}")
    run_task(cfg, out_dir=tmp_path)
    m = json.loads((tmp_path / "metrics.json").read_text())
    assert m["density"] == density and m["iters"] == 20
    # the white-background sphere of the start reads ~14 dB; the views are learnt within 20 steps
    assert m["val_psnr"] > m["before_val_psnr"] + 3.0, (m["before_val_psnr"], m["val_psnr"])
    fixed = {"volsdf": ("beta_final", 0.05), "neus_logistic": ("s_final", 20.0)}[density]
    assert m[fixed[0]] == pytest.approx(fixed[1])
    assert 0 < m["samples_per_ray"] <= 128 and "fine_samples_per_ray" not in m
