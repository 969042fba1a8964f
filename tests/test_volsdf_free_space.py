"""volsdf's free-space stage end to end on the built-in scene (tiny): the free stretches it reads
off its radiance field stop at the TRUE surface (the scene's mesh, rendered independently by
true_depth_maps), not before it by much and not beyond it; bad settings fail up front."""

import pytest
import torch

from l3d_app.app import run_task
from l3d_app.errors import UserError
from l3d_app.geometry.rays import camera_rays
from l3d_app.registry import DATASETS, TASKS
from l3d_app.render.mesh.rgbd import true_depth_maps

TINY = ["data.image_size=64", "data.n_train=48", "data.n_val=2", "data.n_test=2", "data.antialias=1",
        "tensorboard=false", "threads=1"]


def test_free_stretches_end_at_the_true_surface(compose, tmp_path):
    """Built-in scene at 64 px, 300 stage steps. Measured when written (this test, threads=1): 5.4% of
    the covered pixels' stretches end more than 0.02 inside the true solid (a bright object over the
    white background, which the radiance field leaves partly transparent), the median stretch ends
    0.044 in front of the surface (0.05 of it the margin), 99.2% of the empty pixels are free through the box."""
    from l3d_app.geometry.point_mesh_distance import point_mesh_distance

    cfg = compose("task=volsdf", *TINY, f"data.cache_dir={tmp_path / 'cache'}", "iters=20", "eval_every=20",
                  "pretrain_steps=20", "free_space.steps=300", "gif_frames=0", "mesh_resolution=32",
                  "eval_points=1000", "before_after=false", "free_space.save_levels=[0.1,0.3,0.9]")
    run_task(cfg, out_dir=tmp_path / "run")
    saved = torch.load(tmp_path / "run" / "free_space.pt")          # every training pixel (under max_rays)
    dist = saved["distance"]                                         # (R,) along unit rays
    # save_levels: the same rays' distances at other levels, from the same render (0.3 is the stage's own level)
    assert saved["levels"].tolist() == pytest.approx([0.1, 0.3, 0.9])
    lv = saved["level_distances"]
    assert lv.shape == (dist.shape[0], 3) and torch.equal(lv[:, 1], dist)
    fin = torch.isfinite(lv[:, 2])
    assert fin.any() and (lv[fin, 0] <= lv[fin, 1]).all() and (lv[fin, 1] <= lv[fin, 2]).all()
    assert torch.equal(saved["index"], torch.arange(dist.shape[0]))
    data = DATASETS.build(cfg.data)
    cams = data.cameras[data.train]
    truth = true_depth_maps(data.mesh, cams, scale=1).reshape(-1)  # camera-Z depth, +inf where no surface
    o, d = camera_rays(cams, normalize=False)                      # camera Z = 1: |d| converts t to Z
    norm = d.reshape(-1, 3).norm(dim=-1)
    end_t = dist - float(cfg.free_space.margin)
    hit = torch.isfinite(truth)
    past = hit & (end_t / norm > truth) & torch.isfinite(end_t)     # the stretch ends behind the first surface ...
    ends = o.reshape(-1, 3)[past] + end_t[past, None] * d.reshape(-1, 3)[past] / norm[past, None]
    through = (hit & torch.isinf(end_t)).sum()                       # (or never ends: free through the solid)
    inside = ((point_mesh_distance(ends, data.mesh).distance > 0.02).sum() + through) / hit.sum()   # ... deep in it
    short = (truth[hit] - end_t[hit] / norm[hit]).median()
    empty = torch.isinf(dist[~hit]).float().mean()
    assert inside < 0.08           # free stretches that cut into the true solid
    assert 0.0 < short < 0.12      # where the surface is, the stretch reaches close to it (margin 0.05)
    assert empty > 0.95            # rays that meet no surface are free through the box


def test_resume_reads_the_saved_stretches_instead_of_fitting_again(tmp_path):
    from types import SimpleNamespace

    from omegaconf import OmegaConf

    from l3d_app.tasks.free_space_common import fit_free_rays

    torch.save({"index": torch.tensor([0, 2]), "distance": torch.tensor([3.2, float("inf")])}, tmp_path / "free_space.pt")
    ctx = SimpleNamespace(path=lambda name: tmp_path / name, device=torch.device("cpu"))
    o = torch.tensor([[-3.0, 0.0, 0.0], [-3.0, 9.0, 0.0], [-3.0, 0.5, 0.0]])
    d = torch.tensor([[1.0, 0.0, 0.0]] * 3)
    box = ((-1.0, -1.0, -1.0), (1.0, 1.0, 1.0))
    free = fit_free_rays(OmegaConf.create({"margin": 0.05}), ctx, None, box, o, d, None, "auto", 0.0, resume=True)
    torch.testing.assert_close(free.origins, o[[0, 2]])
    torch.testing.assert_close(free.near, torch.tensor([2.0, 2.0]))
    torch.testing.assert_close(free.far, torch.tensor([3.15, 4.0]))


def test_the_front_prior_acts_only_where_the_images_alpha_is_known():
    from omegaconf import OmegaConf

    from l3d_app.tasks.free_space_common import front_weight

    cfg = OmegaConf.create({"w_front": 0.01})
    assert front_weight(cfg, None) == 0.0                       # RGB data: no covered rays, the prior is off
    assert front_weight(cfg, torch.tensor([True, False])) == 0.01
    assert front_weight(OmegaConf.create({}), torch.tensor([True])) == 0.0


def test_the_front_prior_pulls_the_covered_rays_stretch_ends_forward(compose, tmp_path, monkeypatch):
    """The built-in scene given masks (its mesh's coverage), 60 stage steps with and without a large
    w_front: the prior is evaluated once per step and not at all at 0, and the covered rays' stretches end
    clearly earlier with it (measured when written: median 3.19 -> 2.46 along the ray; the density moved to the front)."""
    import l3d_app.tasks.free_space_common as stage
    from l3d_app.registry import DATASETS as registry

    build = registry.build

    def with_masks(cfg):
        data = build(cfg)
        data.masks = torch.isfinite(true_depth_maps(data.mesh, data.cameras, scale=1)).float()
        return data

    monkeypatch.setattr(registry, "build", with_masks)
    calls = []
    real = stage.termination_distance

    def spy(depth, opacity, near, far):
        calls.append(depth.shape[0])
        return real(depth, opacity, near, far)

    monkeypatch.setattr(stage, "termination_distance", spy)
    ends = {}
    for w in (0.0, 2.0):
        cfg = compose("task=volsdf", *[o for o in TINY if not o.startswith("data.n_train")], "data.n_train=16",
                      f"data.cache_dir={tmp_path / 'cache'}", "iters=1", "gif_frames=0", "free_space.batch_rays=512",
                      "free_space.steps=60", f"free_space.w_front={w}", "mesh_resolution=32", "eval_points=1000",
                      "before_after=false", "w_mask=0")
        run_task(cfg, out_dir=tmp_path / f"w{w}")
        ends[w] = torch.load(tmp_path / f"w{w}" / "free_space.pt")["distance"]
        if w == 0:
            assert not calls
    assert len(calls) == 60
    data = with_masks(cfg.data)
    cov = (data.masks[data.train] >= 0.5).reshape(-1)
    fin = torch.isfinite(ends[0.0]) & torch.isfinite(ends[2.0])
    assert float(ends[2.0][cov & fin].median()) < float(ends[0.0][cov & fin].median()) - 0.05


def test_density_loss_needs_the_volsdf_density(compose):
    import l3d_app.tasks  # noqa: F401
    cfg = compose("task=volsdf", "density=neus", "free_space.steps=10", "free_space.loss=density",
                  "data=blender", "data.root=/no/such/folder")
    with pytest.raises(UserError, match="free_space.loss=density needs density=volsdf"):
        TASKS.get("volsdf")(cfg, None)


@pytest.mark.parametrize("loss", ["occupancy", "outside"])
def test_neus_with_the_stage_and_its_margin_reaches_the_data(compose, loss):
    """NeuS has an occupancy (sigmoid(-s f)) and a transition width (1 / s): the stage's occupancy loss and
    margin_beta pass the checks with it; the run stops at the missing data."""
    import l3d_app.tasks  # noqa: F401
    cfg = compose("task=volsdf", "density=neus", "free_space.steps=10", f"free_space.loss={loss}",
                  "free_space.margin_beta=2", "data=blender", "data.root=/no/such/folder")
    with pytest.raises(UserError) as err:
        TASKS.get("volsdf")(cfg, None)
    assert "free_space" not in str(err.value) and "/no/such/folder" in str(err.value)


def test_neus_occupancy_loss_against_the_logistic_cdf_by_hand():
    """NeuS: occupancy = mean(sigmoid(-s f) x length), 1 / (1 + exp(s f)) written out here."""
    import math

    from l3d_app.losses.free_space import free_stretch_loss
    from l3d_app.render.sdf.neus import NeuSDensity

    dens = NeuSDensity(20.0)
    f = torch.tensor([0.1, -0.05, 0.0, 3.0], dtype=torch.float64)
    length = torch.tensor([1.0, 2.0, 0.5, 1.0], dtype=torch.float64)
    phi = [1 / (1 + math.exp(20 * v)) for v in (0.1, -0.05, 0.0, 3.0)]
    expected = (phi[0] * 1 + phi[1] * 2 + phi[2] * 0.5 + phi[3] * 1) / 4
    assert float(free_stretch_loss("occupancy", f, length, dens)) == pytest.approx(expected, rel=1e-12)
    f.requires_grad_(True)      # d/df sigmoid(-s f) = -s phi (1 - phi): pushes f up inside the stretch
    free_stretch_loss("occupancy", f, length, dens).backward()
    grad = [-20 * p * (1 - p) * ln / 4 for p, ln in zip(phi, (1.0, 2.0, 0.5, 1.0))]
    torch.testing.assert_close(f.grad, torch.tensor(grad, dtype=torch.float64), rtol=1e-10, atol=1e-30)


def test_free_space_losses_against_the_laplace_cdf_by_hand():
    """Psi_beta(-f) = 0.5 exp(-f / beta) outside, 1 - 0.5 exp(f / beta) inside (VolSDF), written out
    here; occupancy = mean(Psi x length), density = alpha x that (alpha = 1 / beta), outside = mean(relu(-f))."""
    import math

    from l3d_app.render.sdf.densities import LaplaceDensity
    from l3d_app.losses.free_space import free_stretch_loss as free_space_loss

    dens = LaplaceDensity(0.1, None, learnable=False, beta_min=0.0)
    f = torch.tensor([0.1, -0.1, 0.0], dtype=torch.float64)
    length = torch.tensor([1.0, 2.0, 1.0], dtype=torch.float64)
    psi = [0.5 * math.exp(-1.0), 1 - 0.5 * math.exp(-1.0), 0.5]
    occupancy = (psi[0] * 1 + psi[1] * 2 + psi[2] * 1) / 3
    assert float(free_space_loss("occupancy", f, length, dens)) == pytest.approx(occupancy, rel=1e-6)
    assert float(free_space_loss("density", f, length, dens)) == pytest.approx(10 * occupancy, rel=1e-6)
    assert float(free_space_loss("outside", f, length, dens)) == pytest.approx(0.1 / 3, rel=1e-12)
    w = torch.tensor([2.0, 0.5, 1.0], dtype=torch.float64)     # importance weights multiply each point's term
    weighted = (psi[0] * 1 * 2.0 + psi[1] * 2 * 0.5 + psi[2] * 1 * 1.0) / 3
    assert float(free_space_loss("occupancy", f, length, dens, w)) == pytest.approx(weighted, rel=1e-6)
    assert float(free_space_loss("outside", f, length, dens, w)) == pytest.approx(0.1 * 0.5 / 3, rel=1e-12)


def test_free_space_weight_fades_linearly_to_zero_at_until():
    from l3d_app.losses.free_space import fade_to_zero as free_space_fade

    assert [free_space_fade(p, None) for p in (0.0, 0.7, 1.0)] == [1.0, 1.0, 1.0]
    assert [free_space_fade(p, 0.5) for p in (0.0, 0.25, 0.5, 0.9)] == [1.0, 0.5, 0.0, 0.0]


def test_auto_steps_turn_the_stage_on_for_either_density(compose):
    from l3d_app.tasks.free_space_common import check_free_space_config, resolve_free_space
    cfg = compose("task=volsdf")
    assert cfg.free_space.steps == "auto"
    check_free_space_config(cfg.free_space)
    assert resolve_free_space(cfg.free_space).steps == cfg.free_space.auto_steps == 600
    assert cfg.free_space.steps == "auto"                  # the task's config is not changed
    fixed = compose("task=volsdf", "free_space.steps=7")
    assert resolve_free_space(fixed.free_space).steps == 7


@pytest.mark.parametrize("value", ["often", -1, True])
def test_steps_must_be_auto_or_a_count(compose, value):
    from l3d_app.tasks.free_space_common import check_free_space_config
    cfg = compose("task=volsdf")
    cfg.free_space.steps = value
    with pytest.raises(UserError, match="free_space.steps must be auto or a number >= 0"):
        check_free_space_config(cfg.free_space)


def test_neus_with_the_default_free_space_reaches_the_data(compose):
    """density=neus with the defaults (steps=auto, margin_beta=1) passes the checks: the run stops at the data."""
    import l3d_app.tasks  # noqa: F401
    cfg = compose("task=volsdf", "density=neus", "data=blender", "data.root=/no/such/folder")
    with pytest.raises(UserError) as err:
        TASKS.get("volsdf")(cfg, None)
    assert "free_space" not in str(err.value) and "/no/such/folder" in str(err.value)


def test_a_budget_the_evaluation_needs_skips_the_stage(compose, tmp_path):
    """The timed "before" validation predicts the final work; with 100 s of budget and 45 s of reserve
    the stage's half of what is left is under 30 s, so it is skipped; without a budget it runs."""
    common = ["task=volsdf", *TINY, f"data.cache_dir={tmp_path / 'cache'}", "iters=10", "eval_every=10",
              "pretrain_steps=10", "free_space.steps=20", "gif_frames=0", "mesh_resolution=16", "eval_points=500"]
    import json
    run_task(compose(*common, "time_budget=100", "reserve=45"), out_dir=tmp_path / "tight")
    tight = json.loads((tmp_path / "tight" / "metrics.json").read_text())
    assert tight["free_space_skipped"] is True and tight["free_space_rays"] == 0
    assert not (tmp_path / "tight" / "free_space.pt").exists()
    run_task(compose(*common, "time_budget=0"), out_dir=tmp_path / "free")
    free = json.loads((tmp_path / "free" / "metrics.json").read_text())
    assert free["free_space_skipped"] is False and free["free_space_rays"] > 0
    assert (tmp_path / "free" / "free_space.pt").exists()


@pytest.mark.parametrize("override,message", [("free_space.proposal=near", "free_space.proposal must be uniform or surface"),
                                              ("free_space.candidates=0", "free_space.candidates must be an integer >= 1"),
                                              ("free_space.mix=1", r"free_space.mix must lie in \[0, 1\)")])
def test_proposal_knobs_are_checked(compose, override, message):
    from l3d_app.tasks.free_space_common import check_free_space_config
    with pytest.raises(UserError, match=message):
        check_free_space_config(compose("task=volsdf", override).free_space)


@pytest.mark.parametrize("cut, margins", [("none", ("free_space.margin_beta=0", "free_space.ray_margin_beta=null")),
                                          ("multi_view", ("free_space.margin_beta=0", "free_space.ray_margin_beta=null")),
                                          ("none", ("free_space.margin_beta=3", "free_space.ray_margin_beta=0")),
                                          ("none", ("free_space.margin_beta=0", "free_space.ray_margin_beta=null",
                                                    "free_space.ray_margin=0.02")),
                                          ("none", ("free_space.margin_beta=0", "free_space.ray_margin_beta=null",
                                                    "free_space.ray_loss=log_depth"))])
def test_the_ray_loss_reads_each_batch_rays_own_stretch_end(compose, tmp_path, monkeypatch, cut, margins):
    """free_space.ray_weight > 0 (the point loss off; no shortening: margin_beta 0 with ray_margin_beta
    null, which falls back to it, or ray_margin_beta 0 replacing a margin_beta of 3; ray_margin 0.02: the ends 0.03
    further than the stage's margin of 0.05 puts them; ray_loss=log_depth: each step's opacities then go
    through log_depth, and only there): every training step hands
    opacity_before the stretch ends of exactly the rays it drew, rebuilt here from the saved
    free_space.pt and the training rays (-inf where no stretch is known; with ray_cut=multi_view
    cut back by FreeRays.multi_view_cut, which moves some of them), and its term lowers
    the render's opacity before those ends (the run logs it falling)."""
    import l3d_app.tasks.volsdf as volsdf_task
    from l3d_app.render.volume.free_space import FreeRays

    drawn, calls = [], []

    def record_randint(*args, **kwargs):
        out = randint_before(*args, **kwargs)
        drawn.append(out)
        return out

    def record_opacity(weights, t, ray_indices, ends, n_rays):
        out = opacity_before(weights, t, ray_indices, ends, n_rays)
        calls.append((drawn[-1].clone(), ends.detach().clone(), float(out.detach().mean())))
        return out
    logged = []

    def record_log_depth(opacity):
        logged.append(opacity.detach().clone())
        return log_depth(opacity)
    randint_before, opacity_before = volsdf_task.randint, volsdf_task.opacity_before
    log_depth = volsdf_task.log_depth
    monkeypatch.setattr(volsdf_task, "randint", record_randint)
    monkeypatch.setattr(volsdf_task, "opacity_before", record_opacity)
    monkeypatch.setattr(volsdf_task, "log_depth", record_log_depth)
    cfg = compose("task=volsdf", *TINY, f"data.cache_dir={tmp_path / 'cache'}", "iters=30", "eval_every=30",
                  "pretrain_steps=20", "free_space.steps=60", "free_space.weight=0", "free_space.ray_weight=1",
                  *margins, "gif_frames=0", "mesh_resolution=32", "eval_points=1000",
                  "before_after=false", "batch_rays=256", f"free_space.ray_cut={cut}")
    run_task(cfg, out_dir=tmp_path / "run")
    assert len(calls) == 30
    assert len(logged) == (30 if cfg.free_space.ray_loss == "log_depth" else 0)
    for (_, _, mean), opacity in zip(calls, logged):
        assert float(opacity.mean()) == pytest.approx(mean)
    data = DATASETS.build(cfg.data)
    o, d = camera_rays(data.cameras[data.train], normalize=False)
    o, d = o.reshape(-1, 3), torch.nn.functional.normalize(d.reshape(-1, 3), dim=-1)
    saved = torch.load(tmp_path / "run" / "free_space.pt")
    keep = saved["index"]
    free = FreeRays.from_distances(o[keep], d[keep], saved["distance"], data.scene_box.tolist(),
                                   float(cfg.free_space.margin), keep)
    covered = data.masks[data.train].reshape(-1) >= 0.5 if data.masks is not None else None
    ray_margin = cfg.free_space.get("ray_margin")      # null: the stage's margin
    extend = 0.0 if ray_margin is None else float(cfg.free_space.margin) - float(ray_margin)
    want = free.ends_per_ray(o.shape[0], covered, extend)
    if cut == "multi_view":
        uncut = want
        want = free.multi_view_cut(want, data.cameras[data.train], o, d, float(cfg.free_space.margin))
        assert bool((want < uncut).any())
    for idx, ends, _ in calls:
        torch.testing.assert_close(ends, want[idx])
    assert torch.isfinite(want).float().mean() > 0.5          # most training rays carry a claim
    first, last = sum(c[2] for c in calls[:5]) / 5, sum(c[2] for c in calls[-5:]) / 5
    assert last < 0.5 * first
