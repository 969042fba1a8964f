"""volsdf's free-space stage (stages/free_space.py) on the built-in scene: the free stretches it reads off its
radiance field stop at the TRUE surface (the scene's mesh, rendered independently by true_depth_maps), not
before it by much and not beyond it; the front prior pulls the covered rays' ends forward; inside a volsdf
run the ray term reads each batch ray's own stretch end; a budget the evaluation needs skips the stage."""

import json
from types import SimpleNamespace

import pytest
import torch

from conftest import VOLSDF_TINY, compose_config
from l3d_app.app import run_task
from l3d_app.errors import UserError
from l3d_app.geometry.rays import camera_rays
from l3d_app.geometry.training_rays import TrainingRays
from l3d_app.models.background import background_parameter
from l3d_app.registry import DATASETS
from l3d_app.render.mesh.rgbd import true_depth_maps
from l3d_app.render.volume.free_space import FreeRays
from l3d_app.runtime.context import RunContext
from l3d_app.runtime.logger import RunLogger
from l3d_app.runtime.budget import TimeBudget
from l3d_app.stages.base import MethodState
from l3d_app.stages.free_space import FILE, FreeSpaceStage


SMALL_FIELD = {"name": "grid_field", "n_levels": 4, "max_resolution": 64, "log2_hashmap_size": 15}
SMALL_SAMPLER = {"name": "occupancy", "n_samples": 48, "resolution": 32}
"""A radiance field and sampler for the stage that a few seconds fit (the tests that read the stage's own logic)."""


def _scene(cache, n_train: int = 48, masks: bool = False):
    """The built-in scene at 32 px; ``masks``: its mesh's coverage as the images' alpha (the built-in data has none)."""
    cfg = compose_config("task=volsdf", *VOLSDF_TINY, f"data.cache_dir={cache}", f"data.n_train={n_train}")
    data = DATASETS.build(cfg.data)
    if masks:
        data.masks = torch.isfinite(true_depth_maps(data.mesh, data.cameras, scale=1)).float()
    rays = TrainingRays.of_views(data.cameras, data.images, data.masks, data.train)
    state = MethodState(data, rays, None, None, data.scene_box.tolist(), 1, needed={"free_rays"},
                        background=lambda: background_parameter("auto", data))
    return data, state


def _fit(stage: FreeSpaceStage, state: MethodState, out) -> FreeRays:
    """``stage`` run alone (no budget) on ``state``, writing into ``out``; its free rays."""
    ctx = RunContext(out_dir=out, device=torch.device("cpu"), generator=torch.Generator().manual_seed(0),
                     logger=RunLogger(out, enabled=False))
    assert stage.before_training(state, ctx, TimeBudget())
    return state.products["free_rays"]


def test_free_stretches_end_at_the_true_surface(free_space_run):
    """The stage of free_space_run (64 px, 48 views, 300 steps of a small field), scored on the rays it read off.
    Measured when written: 1.3% of the covered pixels' stretches end more than 0.02 inside the true solid (a bright
    object over the white background, which the radiance field leaves partly transparent), the median stretch ends
    0.045 in front of the surface (0.05 of it the margin), 98.7% of the empty pixels are free through the box."""
    from l3d_app.geometry.point_mesh_distance import point_mesh_distance

    cfg, m = free_space_run.cfg, free_space_run.metrics
    saved = torch.load(free_space_run.dir / FILE)                    # a random 50000 of the training pixels
    keep, dist = saved["index"], saved["distance"]                   # (R,) which, and their distances along unit rays
    assert keep.shape == (50000,) and bool((keep[1:] > keep[:-1]).all())
    data = DATASETS.build(cfg.data)
    cams = data.cameras[data.train]
    truth = true_depth_maps(data.mesh, cams, scale=1).reshape(-1)[keep]   # camera-Z depth, +inf where no surface
    o, d = camera_rays(cams, normalize=False)                      # camera Z = 1: |d| converts t to Z
    o, d = o.reshape(-1, 3)[keep], d.reshape(-1, 3)[keep]
    norm = d.norm(dim=-1)
    end_t = dist - float(cfg.stages.free_space.margin)
    hit = torch.isfinite(truth)
    past = hit & (end_t / norm > truth) & torch.isfinite(end_t)     # the stretch ends behind the first surface ...
    ends = o[past] + end_t[past, None] * d[past] / norm[past, None]
    through = (hit & torch.isinf(end_t)).sum()                       # (or never ends: free through the solid)
    inside = ((point_mesh_distance(ends, data.mesh).distance > 0.02).sum() + through) / hit.sum()   # ... deep in it
    short = (truth[hit] - end_t[hit] / norm[hit]).median()
    empty = torch.isinf(dist[~hit]).float().mean()
    assert inside < 0.08           # free stretches that cut into the true solid
    assert 0.0 < short < 0.12      # where the surface is, the stretch reaches close to it (margin 0.05)
    assert empty > 0.95            # rays that meet no surface are free through the box
    assert m["free_space_skipped"] is False and m["free_space_rays"] > 0.3 * dist.shape[0]


def test_the_ray_term_reads_each_batch_rays_own_stretch_end(free_space_run):
    """losses.free_rays alone (the point term off; margin_beta 0: the ends as the stage left them): every
    training step handed opacity_before the stretch ends of exactly the rays it drew, rebuilt here from the
    saved free_space.pt and the training rays (-inf where no stretch is known), and its term lowered the
    render's opacity before those ends (the run logged it falling)."""
    cfg, calls = free_space_run.cfg, free_space_run.calls
    assert len(calls) == 30
    data = DATASETS.build(cfg.data)
    o, d = camera_rays(data.cameras[data.train], normalize=False)
    o, d = o.reshape(-1, 3), torch.nn.functional.normalize(d.reshape(-1, 3), dim=-1)
    saved = torch.load(free_space_run.dir / FILE)
    keep = saved["index"]
    free = FreeRays.from_distances(o[keep], d[keep], saved["distance"], data.scene_box.tolist(),
                                   float(cfg.stages.free_space.margin), keep)
    want = free.ends_per_ray(o.shape[0], None)
    for idx, ends, _ in calls:
        torch.testing.assert_close(ends, want[idx])
    assert torch.isfinite(want[keep]).float().mean() > 0.5    # most of the rays read off carry a claim
    first, last = sum(c[2] for c in calls[:5]) / 5, sum(c[2] for c in calls[-5:]) / 5
    assert last < 0.5 * first


def test_resume_reads_the_saved_stretches_instead_of_fitting_again(tmp_path):
    torch.save({"index": torch.tensor([0, 2]), "distance": torch.tensor([3.2, float("inf")])}, tmp_path / FILE)
    o = torch.tensor([[-3.0, 0.0, 0.0], [-3.0, 9.0, 0.0], [-3.0, 0.5, 0.0]])
    d = torch.tensor([[1.0, 0.0, 0.0]] * 3)
    rays = SimpleNamespace(origins=o, unit_dirs=lambda: d, rgb=None, covered=None)
    state = SimpleNamespace(rays=rays, box=((-1.0, -1.0, -1.0), (1.0, 1.0, 1.0)), resuming=True)
    ctx = SimpleNamespace(path=lambda name: tmp_path / name, device=torch.device("cpu"))
    free = FreeSpaceStage().fit(state, ctx, 0.0)
    torch.testing.assert_close(free.origins, o[[0, 2]])
    torch.testing.assert_close(free.near, torch.tensor([2.0, 2.0]))
    torch.testing.assert_close(free.far, torch.tensor([3.15, 4.0]))


def test_the_front_prior_pulls_the_covered_rays_stretch_ends_forward(tmp_path, data_cache, monkeypatch):
    """The built-in scene given masks (its mesh's coverage), 40 stage steps of a small field with and without a
    large w_front, 8000 of its rays read off: the prior is evaluated once per step and not at all at 0, and the
    covered rays' stretches end clearly earlier with it (the density moved to the front; measured when written:
    median 3.20 -> 2.45 along the ray)."""
    import l3d_app.stages.free_space as module

    calls = []
    real = module.termination_distance

    def spy(depth, opacity, near, far):
        calls.append(depth.shape[0])
        return real(depth, opacity, near, far)

    monkeypatch.setattr(module, "termination_distance", spy)
    data, state = _scene(data_cache, masks=True)
    ends, index = {}, {}
    for w in (0.0, 2.0):
        state.products.clear()
        _fit(FreeSpaceStage(steps=40, batch_rays=256, w_front=w, max_rays=8000, model=SMALL_FIELD,
                            sampler=SMALL_SAMPLER), state, tmp_path / f"w{w}")
        saved = torch.load(tmp_path / f"w{w}" / FILE)
        index[w], ends[w] = saved["index"], saved["distance"]
        if w == 0:
            assert not calls
    assert len(calls) == 40 and torch.equal(index[0.0], index[2.0])     # the same random rays in both fits
    cov = state.rays.covered[index[0.0]]
    fin = torch.isfinite(ends[0.0]) & torch.isfinite(ends[2.0])
    assert float(ends[2.0][cov & fin].median()) < float(ends[0.0][cov & fin].median()) - 0.05


def test_a_stage_whose_product_no_term_reads_does_not_run():
    stage = FreeSpaceStage(steps=10)
    ctx = SimpleNamespace(stopwatch=None)
    assert stage.before_training(SimpleNamespace(needed=set()), ctx, TimeBudget()) and stage.free is None
    assert stage.metrics() == {"free_space_seconds": 0.0, "free_space_rays": 0, "free_space_skipped": False}


def test_the_free_space_terms_work_with_neus(compose):
    """NeuS has an occupancy (sigmoid(-s f)) and a transition width (1 / s): the stage and both free-space
    terms pass the checks with it; the run stops at the missing data."""
    import l3d_app.tasks  # noqa: F401
    from l3d_app.registry import TASKS
    cfg = compose("task=volsdf", "density=neus", "losses.free_points.margin_beta=2", "data=blender",
                  "data.root=/no/such/folder")
    with pytest.raises(UserError) as err:
        TASKS.get("volsdf")(cfg, None)
    assert "/no/such/folder" in str(err.value)


def test_neus_occupancy_loss_against_the_logistic_cdf_by_hand():
    """NeuS: occupancy = mean(sigmoid(-s f) x length), 1 / (1 + exp(s f)) written out here."""
    import math

    from l3d_app.losses.free_space import free_stretch_occupancy
    from l3d_app.render.sdf.neus import NeuSDensity

    dens = NeuSDensity(20.0)
    f = torch.tensor([0.1, -0.05, 0.0, 3.0], dtype=torch.float64)
    length = torch.tensor([1.0, 2.0, 0.5, 1.0], dtype=torch.float64)
    phi = [1 / (1 + math.exp(20 * v)) for v in (0.1, -0.05, 0.0, 3.0)]
    expected = (phi[0] * 1 + phi[1] * 2 + phi[2] * 0.5 + phi[3] * 1) / 4
    assert float(free_stretch_occupancy(f, length, dens)) == pytest.approx(expected, rel=1e-12)
    f.requires_grad_(True)      # d/df sigmoid(-s f) = -s phi (1 - phi): pushes f up inside the stretch
    free_stretch_occupancy(f, length, dens).backward()
    grad = [-20 * p * (1 - p) * ln / 4 for p, ln in zip(phi, (1.0, 2.0, 0.5, 1.0))]
    torch.testing.assert_close(f.grad, torch.tensor(grad, dtype=torch.float64), rtol=1e-10, atol=1e-30)


def test_volsdf_occupancy_loss_against_the_laplace_cdf_by_hand():
    """Psi_beta(-f) = 0.5 exp(-f / beta) outside, 1 - 0.5 exp(f / beta) inside (VolSDF), written out here."""
    import math

    from l3d_app.losses.free_space import free_stretch_occupancy
    from l3d_app.render.sdf.densities import LaplaceDensity

    dens = LaplaceDensity(0.1, None, learnable=False, beta_min=0.0)
    f = torch.tensor([0.1, -0.1, 0.0], dtype=torch.float64)
    length = torch.tensor([1.0, 2.0, 1.0], dtype=torch.float64)
    psi = [0.5 * math.exp(-1.0), 1 - 0.5 * math.exp(-1.0), 0.5]
    occupancy = (psi[0] * 1 + psi[1] * 2 + psi[2] * 1) / 3
    assert float(free_stretch_occupancy(f, length, dens)) == pytest.approx(occupancy, rel=1e-6)


@pytest.mark.parametrize("override,message", [("stages.free_space.steps=-1", "steps must be an integer >= 0"),
                                              ("stages.free_space.opacity=1.5", r"opacity must lie in \(0, 1\]"),
                                              ("stages.free_space.margin=-0.1", "margin must be a number >= 0"),
                                              ("losses.free_points.points=0", "points must be a positive integer"),
                                              ("losses.free_rays.margin_beta=-1", "margin_beta must be a number >= 0")])
def test_bad_free_space_knobs_fail_before_the_data_is_read(compose, override, message):
    import l3d_app.tasks  # noqa: F401
    from l3d_app.registry import TASKS
    with pytest.raises(UserError, match=message):
        TASKS.get("volsdf")(compose("task=volsdf", override, "data=blender", "data.root=/no/such/folder"), None)


def test_a_budget_the_evaluation_needs_skips_the_stage(compose, tmp_path):
    """The timed "before" validation predicts the final work; with 100 s of budget and 45 s of reserve
    the stage's half of what is left is under 90 s, so it is skipped (no file, logged in the metrics)."""
    cfg = compose("task=volsdf", *VOLSDF_TINY, "data.n_train=8", "data.image_size=16", "tensorboard=false",
                  f"data.cache_dir={tmp_path / 'cache'}", "iters=2", "eval_every=2", "stages.sphere_init.steps=0",
                  "stages.free_space.steps=20", "gif_frames=0", "mesh_resolution=8", "eval_points=100",
                  "time_budget=100", "reserve=45")
    run_task(cfg, out_dir=tmp_path / "tight")
    tight = json.loads((tmp_path / "tight" / "metrics.json").read_text())
    assert tight["free_space_skipped"] is True and tight["free_space_rays"] == 0
    assert not (tmp_path / "tight" / FILE).exists()
