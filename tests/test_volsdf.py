"""Neural surfaces: eikonal loss at kinks, SDF network init, SDF volume rendering, tasks volsdf / neural_sdf."""

import json
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from l3d_app.app import run_task
from l3d_app.errors import UserError
from l3d_app.geometry.sdf import Box, Sphere
from l3d_app.losses.eikonal import eikonal_at, eikonal_loss, sdf_gradient
from l3d_app.models.sdf_net import SDFField, SDFNetwork, pretrain_sphere
from l3d_app.render.sdf.densities import LaplaceDensity
from l3d_app.render.volume.estimators import SDFCacheProposal
from l3d_app.render.sdf.neus import NeuSDensity
from l3d_app.render.sdf.volume import render_sdf_rays
from conftest import VOLSDF_TINY


def _true_mesh_diagonal() -> float:
    """Bounding-box diagonal of the built-in scene's vertices, computed here (numpy), not by
    the metric under test; test_builtin_scene_extent.py checks it against the scene's
    construction (about 2.135)."""
    from l3d_app.data.nerf_views import nerf_scene

    v = nerf_scene().verts.double().numpy()
    return float(np.linalg.norm(v.max(0) - v.min(0)))


TINY = [*VOLSDF_TINY, "tensorboard=false", "stages.free_space.steps=0",   # the stage: test_volsdf_free_space.py
        "losses.ncc.weight=0"]   # the patch loss (5 x 5 patches, a large share of a 32 px image): volsdf_run


def test_eikonal_loss_is_finite_at_kinks_and_zero_for_exact_sdfs():
    # a sphere's centre, a box's centre / medial planes / edges, a zero gradient
    pts = torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.3, 0.3, 0.0], [0.5, 0.5, 0.2]], dtype=torch.float64)
    for sdf in (Sphere(1.0), Box((1.0, 1.0, 1.0))):
        g = sdf_gradient(sdf, pts, create_graph=False)
        assert torch.isfinite(g).all()
    grad = torch.zeros(4, 3, dtype=torch.float64, requires_grad=True)
    loss = eikonal_loss(grad)
    (gg,) = torch.autograd.grad(loss, grad)
    assert float(loss.detach()) == 1.0 and torch.isfinite(gg).all()
    # away from kinks an exact SDF has loss ~0; a scaled one does not
    x = torch.randn(256, 3, dtype=torch.float64) + 2.0
    assert float(eikonal_loss(sdf_gradient(Sphere(0.5), x)).detach()) < 1e-20
    assert float(eikonal_loss(sdf_gradient(lambda p: 2 * Sphere(0.5)(p), x)).detach()) == pytest.approx(1.0)


def test_eikonal_through_a_network_has_finite_parameter_gradients():
    net = SDFNetwork(n_frequencies=2, hidden=16, n_layers=2, n_features=0).double()
    pts = torch.zeros(8, 3, dtype=torch.float64)                 # the init sphere's centre: a kink
    loss = eikonal_at(net.sdf, pts)
    grads = torch.autograd.grad(loss, list(net.parameters()), allow_unused=True)  # output bias: unused
    assert torch.isfinite(loss) and all(g is None or torch.isfinite(g).all() for g in grads)
    assert sum(g is not None for g in grads) >= len(grads) - 1


def test_geometric_init_and_pretraining_give_a_sphere():
    torch.manual_seed(0)
    net = SDFNetwork(n_frequencies=4, hidden=32, n_layers=2, radius=0.5)
    x = torch.rand(2000, 3) * 2 - 1
    ref = x.norm(dim=-1) - 0.5
    with torch.no_grad():
        f0 = net(x)[0]
    r = x.norm(dim=-1)
    assert (f0[r < 0.2] < 0).float().mean() > 0.9 and (f0[r > 0.9] > 0).float().mean() > 0.9   # a sphere-ish start
    err = pretrain_sphere(net, 0.5, ((-1,) * 3, (1,) * 3), steps=100, n_points=1024, generator=torch.Generator().manual_seed(0))
    assert err < 0.03 and float((net(x)[0] - ref).abs().mean().detach()) < 0.03
    assert float((net.gradient(x, create_graph=False)[1].norm(dim=-1) - 1).abs().mean().detach()) < 0.1


@pytest.mark.parametrize("density", ["volsdf", "neus"])
def test_sdf_volume_rendering_of_an_exact_sphere(density):
    """An opaque analytic sphere: hits are opaque at the analytic depth, misses transparent,
    the fine samples concentrate at the surface."""
    sph = Sphere(0.5)
    o = torch.tensor([[0.0, 0.0, -2.0], [0.0, 0.2, -2.0], [0.0, 0.9, -2.0]])
    d = torch.tensor([[0.0, 0.0, 1.0]]).expand(3, 3)
    colour = lambda p, v: (sph(p), torch.full((p.shape[0], 3), 0.25))  # noqa: E731
    est = SDFCacheProposal(((-1, -1, -1), (1, 1, 1)), n_coarse=64, n_fine=32, resolution=0)
    dens = LaplaceDensity(0.005, 200.0, learnable=False, beta_min=0.0) if density == "volsdf" else NeuSDensity(400.0)
    out = render_sdf_rays(colour, o, d, est, dens, field=SimpleNamespace(sdf=sph), background=(1.0, 1.0, 1.0))
    out["t"] = out["t"].reshape(3, 32)
    ref_t = 2.0 - torch.sqrt(0.25 - torch.tensor([0.0, 0.2]) ** 2)
    assert out["opacity"][:2].min() > 0.99 and out["opacity"][2] < 1e-3
    torch.testing.assert_close(out["depth"][:2] / out["opacity"][:2], ref_t, atol=0.02, rtol=0)
    torch.testing.assert_close(out["color"][:2], torch.full((2, 3), 0.25), atol=0.01, rtol=0)
    torch.testing.assert_close(out["color"][2], torch.ones(3), atol=1e-3, rtol=0)
    near_surface = (out["t"][:2] - ref_t[:, None]).abs() < 0.1
    assert near_surface.float().mean() > 0.5        # samples are placed near the zero level set
    assert float(out["samples_per_ray"]) == 96.0 and float(out["fine_samples_per_ray"]) == 32.0


def test_sdf_field_config_builds_and_rejects_unknown_encoding():
    field = SDFField(scene_box=((-1,) * 3, (1,) * 3), sdf_net={"encoding": "grid", "grid": {"n_levels": 2}})
    f, rgb = field(torch.rand(5, 3), torch.rand(5, 3))
    assert f.shape == (5,) and rgb.shape == (5, 3)
    with pytest.raises(UserError):
        SDFNetwork(encoding="fourier")


def test_volsdf_short_run_improves_psnr_and_writes_everything(volsdf_run):
    cfg, m, run = volsdf_run.cfg, volsdf_run.metrics, volsdf_run.dir
    assert (cfg.density.beta, cfg.density.alpha, cfg.density.mode, cfg.density.name) == (0.1, None, "anneal", "auto")
    for key in ("psnr", "ssim", "chamfer", "chamfer_rel_diag", "f1", "chamfer_observed",
                "chamfer_observed_rel_diag", "f1_observed", "observed_fraction", "seconds", "samples_per_ray",
                "fine_samples_per_ray", "iters", "n_params", "beta", "beta_final", "cpu_seconds_per_step",
                "val_psnr", "val_ssim"):
        assert key in m, key
    hist = [h["psnr"] for h in m["history"]]          # validation views only
    assert m["history"][-1]["psnr"] == pytest.approx(m["val_psnr"], abs=1e-3)
    # against the untrained field (12.4 dB here): +3.0 dB; a margin over the first validation (step 40) instead
    # depends on how much the first 40 steps already gained
    before = m["before_val_psnr"]
    assert len(hist) == 2 and hist[-1] > hist[0] and hist[-1] > before + 2.0 and hist[-1] > 14.5, (before, hist)
    assert np.isfinite(m["chamfer"]) and 0 <= m["f1"] <= 1
    # density=auto: 16 of the 100 built-in training cameras lie below the scene's centre: under a quarter, VolSDF
    assert m["density"] == "volsdf" and m["cameras_below_fraction"] == pytest.approx(0.16, abs=0.02)
    assert m["warmup_steps"] == 50                    # optim.warmup_steps=auto with VolSDF
    assert (run / "before_after.png").exists() and m["before_val_psnr"] < m["val_psnr"]
    assert 0 < m["fine_samples_per_ray"] <= cfg.sampler.n_fine
    assert m["samples_per_ray"] <= cfg.sampler.n_coarse + cfg.sampler.n_fine + 8     # + the anchored refinement
    diag = _true_mesh_diagonal()
    assert m["chamfer_rel_diag"] == pytest.approx(m["chamfer"] / diag, abs=1e-6)  # both rounded to 6 decimals
    # the training cameras (elevations -10..70 degrees) never see the plinth's underside
    assert 0.6 < m["observed_fraction"] < 0.8
    assert m["chamfer_observed_rel_diag"] == pytest.approx(m["chamfer_observed"] / diag, abs=1e-6)
    import trimesh
    glb = trimesh.load(run / "mesh.glb", force="mesh")
    assert glb.visual.vertex_colors.shape[0] == len(glb.vertices) and glb.visual.vertex_colors[:, :3].std() > 0
    for name in ("render.gif", "geometry.gif", "mesh.obj", "mesh.glb", "test_views.png", "checkpoint.pt"):
        assert (run / name).exists(), name


def test_the_patch_loss_acts_until_its_fraction_of_the_steps(volsdf_run):
    """The default patch consistency is wired into the training step: logged with textured rays counting
    while its weight is above zero, and absent from the log once ``losses.ncc.until`` x iters is reached."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    assert (volsdf_run.cfg.losses.ncc.weight, volsdf_run.cfg.losses.ncc.until) == (0.1, 0.5)
    events = EventAccumulator(str(next(volsdf_run.dir.glob("events.out.tfevents.*"))), size_guidance={"scalars": 0})
    events.Reload()
    rays = {e.step: e.value for e in events.Scalars("train/ncc_rays")}
    ncc = {e.step: e.value for e in events.Scalars("train/ncc")}
    assert sorted(rays) == [0, 10, 20, 30] and min(rays.values()) > 0.02   # logged every 10 steps while it acts
    assert all(-1.0 <= v <= 1.0 for v in ncc.values())
    assert {0, 70} <= {e.step for e in events.Scalars("train/color_loss")}        # the run went on without it
    assert {e.step for e in events.Scalars("train/ncc_loss")} == set(rays)


def test_volsdf_neus_variant_learns(compose, tmp_path, data_cache):
    """The NeuS variant must LEARN, as VolSDF does (a shorter run of the same kind as volsdf_run)."""
    assert compose("task=volsdf", "density=neus", "s=1000").density.s == 1000.0
    cfg = compose("task=volsdf", *TINY, f"data.cache_dir={data_cache}", "density=neus", "iters=80",
                  "eval_every=40", "batch_rays=256", "optim.lr=0.005", "stages.sphere_init.steps=50", "gif_frames=0",
                  "mesh_resolution=24", "eval_points=500")
    run_task(cfg, out_dir=tmp_path / "run")
    m = json.loads((tmp_path / "run" / "metrics.json").read_text())
    hist = [h["psnr"] for h in m["history"]]
    assert m["density"] == "neus" and np.isfinite(m["psnr"]) and len(hist) == 2
    assert m["warmup_steps"] == 150                   # optim.warmup_steps=auto with NeuS (a ramp longer than this run)
    assert hist[-1] > hist[0] + 0.25, hist
    from hydra.errors import MissingConfigException
    from l3d_app.registry import DENSITIES

    with pytest.raises(MissingConfigException, match="unisurf"):      # no conf/density/unisurf.yaml
        compose("task=volsdf", *TINY, "density=unisurf")
    with pytest.raises(UserError, match="unisurf"):                   # nor a registered density
        DENSITIES.build({"name": "unisurf"})


def test_neural_sdf_fits_the_builtin_torus(compose, tmp_path):
    cfg = compose("task=neural_sdf", "tensorboard=false", "threads=1", "iters=150", "eval_every=50",
                  "batch_points=512", "mesh_resolution=32", "eval_points=2000", "gif_frames=2", "turntable_size=24")
    run_task(cfg, out_dir=tmp_path / "run")
    m = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert m["f1"] > 0.6 and m["chamfer"] < 0.15 and m["val_surface_abs"] < 0.02, m
    for name in ("mesh.ply", "mesh.gif", "metrics.json"):
        assert (tmp_path / "run" / name).exists(), name


def test_bunny_loader(tmp_path):
    from l3d_app.data.bunny import bunny_points

    pts = np.random.default_rng(0).normal(size=(10, 3)).astype(np.float32) + 5
    np.savez(tmp_path / "b.npz", verts=pts)
    cloud = bunny_points(str(tmp_path / "b.npz"))
    assert cloud.points.shape == (5, 3)
    torch.testing.assert_close(cloud.points.mean(0), torch.zeros(3), atol=1e-5, rtol=0)
    torch.testing.assert_close(cloud.points[1] - cloud.points[0], torch.from_numpy(pts[2] - pts[0]))
    with pytest.raises(UserError):
        bunny_points(str(tmp_path / "missing.npz"))


def test_tensorboard_shows_where_the_time_budget_has_moved_the_schedules(compose, tmp_path, monkeypatch):
    """The loop's prediction faked to 20 of 40 steps (the run cut at 15): step 0 runs before the
    loop has predicted (40 steps, nominal 0); by step 10 train/predicted_steps reads 20 and
    train/nominal_step, the step the schedules (beta, LR, grid levels) are read at, twice the
    step (step * iters / steps = 20)."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator
    from l3d_app.app import RunInterrupted
    from l3d_app.runtime.budget import TimeBudget

    monkeypatch.setattr(TimeBudget, "predicted_steps", lambda self, *a: 20.0)
    monkeypatch.setenv("L3D_STOP_AT_STEP", "15")
    cfg = compose("task=volsdf", *[o for o in TINY if not o.startswith(("tensorboard", "data.n_train"))],
                  "tensorboard=true", "data.n_train=8", "data.image_size=16", f"data.cache_dir={tmp_path / 'cache'}",
                  "iters=40", "eval_every=40", "batch_rays=64", "stages.sphere_init.steps=5", "gif_frames=0",
                  "mesh_resolution=16", "eval_points=200", "time_budget=100000")
    with pytest.raises(RunInterrupted):
        run_task(cfg, out_dir=tmp_path / "run")
    events = EventAccumulator(str(next((tmp_path / "run").glob("events.out.tfevents.*"))), size_guidance={"scalars": 0})
    events.Reload()
    nominal = {e.step: e.value for e in events.Scalars("train/nominal_step")}
    predicted = {e.step: e.value for e in events.Scalars("train/predicted_steps")}
    assert nominal == pytest.approx({0: 0.0, 10: 20.0}) and predicted == pytest.approx({0: 40.0, 10: 20.0})


def test_warmup_steps_auto_follows_the_density_and_bad_values_are_refused(compose):
    import l3d_app.tasks  # noqa: F401
    from l3d_app.registry import TASKS
    from l3d_app.render.sdf.densities import VolSDFDensity

    assert (VolSDFDensity.warmup_steps, NeuSDensity.warmup_steps) == (50, 150)   # docs/measured/volsdf.md
    assert compose("task=volsdf").optim.warmup_steps == "auto"
    for bad in (-1, 2.5, "fast", True):
        cfg = compose("task=volsdf", "data=blender", "data.root=/no/such/folder")
        cfg.warmup_steps = bad
        with pytest.raises(UserError, match="warmup_steps must be auto or an integer >= 0"):
            TASKS.get("volsdf")(cfg, None)
    cfg = compose("task=volsdf", "data=blender", "data.root=/no/such/folder", "warmup_steps=80")
    with pytest.raises(UserError, match="/no/such/folder"):      # an integer passes: the run reaches the data
        TASKS.get("volsdf")(cfg, None)
