"""Shared test fixtures: paths to the repo, its configs and the optional course data; the
random-order setup.

Random order: pytest-randomly (the test extra; ``addopts = -p randomly``) shuffles the tests
on every run and reseeds ``random`` and numpy before each test; the seed is printed at the
end of the run (repeat an order with ``--randomly-seed=N``, or ``-p no:randomly`` for file
order). It does not touch torch, so this conftest seeds torch's global generator before
each test (``pytest_runtest_setup``, ahead of its fixtures) from the test's id alone: a
test's torch draws are the same in any order and under any --randomly-seed, and the shuffle
can only expose real leaks between tests (registries, global flags, working directory,
environment).
"""

from __future__ import annotations

import os
import zlib
from pathlib import Path

import pytest
import torch

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"

os.environ.setdefault("L3D_NO_PROGRESS", "1")
if os.environ.get("PYTEST_XDIST_WORKER"):   # one worker per core: one torch thread each
    torch.set_num_threads(1)


def course_data(*parts: str) -> Path:
    """Path inside ../shared/data; skips the test cleanly when it is absent."""
    path = SHARED_DATA.joinpath(*parts)
    if not path.exists():
        pytest.skip(f"course data not present: {path}")
    return path


def compose_config(*overrides: str):
    """The app's Hydra config composed with ``overrides`` (no run directory, no chdir), their shorthands
    expanded as on the command line (l3d_app/aliases.py)."""
    from hydra import compose as hydra_compose, initialize_config_dir

    from l3d_app.aliases import expand_aliases

    with initialize_config_dir(version_base="1.3", config_dir=str(REPO / "conf")):
        return hydra_compose(config_name="config", overrides=expand_aliases(list(overrides)))


@pytest.fixture
def compose():
    """:func:`compose_config` as a fixture."""
    return compose_config


@pytest.fixture(scope="session")
def data_cache(tmp_path_factory):
    """One cache folder for the test run's built-in datasets (each file keyed by the dataset's
    parameters, written atomically): a scene is rendered once for every test that asks for the
    same one, and under pytest-xdist the workers share the folder (it sits beside their own)."""
    if os.environ.get("PYTEST_XDIST_WORKER"):
        shared = tmp_path_factory.getbasetemp().parent / "data_cache"
        shared.mkdir(exist_ok=True)
        return shared
    return tmp_path_factory.mktemp("data_cache")


@pytest.hookimpl(tryfirst=True)
def pytest_runtest_setup(item):
    """Seed torch's global generator from the test's node id (order-independent), before any
    fixture of the test is set up (module-scoped ones included)."""
    torch.manual_seed(zlib.crc32(item.nodeid.encode()))


LONGEST_FILES = ("test_volsdf_free_space.py", "test_app.py", "test_volsdf.py", "test_render_path.py",
                 "test_viewer_browser.py", "test_course_surfaces.py", "test_learned_background.py", "test_nerf.py",
                 "test_faults.py", "test_pointnet.py")
"""The files with the longest end-to-end runs (about 10-45 s each on one core in a ``--durations`` reading)."""


@pytest.hookimpl(trylast=True)
def pytest_collection_modifyitems(session, config, items):
    """Longest first: after the random shuffle, the tests of :data:`LONGEST_FILES` move ahead of the rest (each
    group keeps its shuffled order), so that the xdist workers, which take a file at a time, do not end with one
    of them running alone."""
    items[:] = sorted(items, key=lambda item: item.path.name not in LONGEST_FILES)


def pytest_terminal_summary(terminalreporter, config):
    """Print the random-order seed even under -q (pytest-randomly prints it only in the header)."""
    if config.pluginmanager.hasplugin("randomly"):
        seed = config.getoption("randomly_seed", None)
        terminalreporter.write_line(f"random order: --randomly-seed={seed} (pytest-randomly; "
                                    f"-p no:randomly for file order)")


VOLSDF_TINY = ("data.image_size=32", "data.n_train=48", "data.n_val=2", "data.n_test=2", "data.antialias=1",
               "threads=1", "time_budget=0")
"""volsdf on the built-in scene at 32 px (48 training views): the end-to-end tests' size."""


@pytest.fixture(scope="session")
def volsdf_run(tmp_path_factory, data_cache):
    """One short volsdf run shared by the end-to-end tests (tests/test_volsdf.py): the defaults' parts (density=auto,
    the sphere init, coarse-to-fine levels, colour, eikonal and patch terms) without the free-space stage
    (:func:`free_space_run`), 80 steps of 256 rays from beta 0.1 (the shipped 0.3 has barely begun its anneal
    by then), every output on. Its run directory, config and metrics."""
    import json
    from types import SimpleNamespace

    from l3d_app.app import run_task

    cfg = compose_config("task=volsdf", *VOLSDF_TINY, f"data.cache_dir={data_cache}", "iters=80",
                         "eval_every=40", "batch_rays=256", "optim.lr=0.005", "beta=0.1", "stages.sphere_init.steps=50",
                         "stages.free_space.steps=0", "gif_frames=2", "mesh_resolution=32", "eval_points=2000",
                         "mesh_formats=[obj,glb]")
    out = tmp_path_factory.mktemp("volsdf_run")
    run_task(cfg, out_dir=out)
    return SimpleNamespace(dir=out, cfg=cfg, metrics=json.loads((out / "metrics.json").read_text()))


@pytest.fixture(scope="session")
def free_space_run(tmp_path_factory, data_cache):
    """One volsdf run with the free-space stage (tests/test_volsdf_free_space.py): the built-in scene at 64 px
    (48 training views), the stage's 300 steps of 1024 rays with a small radiance field (4 grid levels up to 64,
    48 samples a ray; 50000 of the 196608 training rays read off), then 30 steps of 256 rays whose only free-space
    term is the ray term (weight 1, its ends as the stage left them) and no patch term. What each step handed
    the ray term is recorded: the batch's ray indices, their ends and the batch's mean opacity before them."""
    import json
    from types import SimpleNamespace

    import l3d_app.losses.free_space as free_space_losses
    from l3d_app.app import run_task
    from l3d_app.losses.terms import LossTerms

    cfg = compose_config("task=volsdf", *VOLSDF_TINY, "data.image_size=64",
                         f"data.cache_dir={data_cache}", "tensorboard=false",
                         "iters=30", "eval_every=30", "batch_rays=256", "stages.sphere_init.steps=20",
                         "stages.free_space.steps=300", "+stages.free_space.batch_rays=1024",
                         "+stages.free_space.max_rays=50000", "losses.free_points.weight=0",
                         "losses.free_rays.weight=1",
                         "losses.free_rays.margin_beta=0", "losses.ncc.weight=0", "gif_frames=0", "mesh_resolution=16",
                         "eval_points=500",
                         "+stages.free_space.model={name:grid_field,n_levels:4,max_resolution:64,log2_hashmap_size:15}",
                         "+stages.free_space.sampler={name:occupancy,n_samples:48,resolution:32}")
    drawn, calls = [], []
    real_call, real_opacity = LossTerms.__call__, free_space_losses.opacity_before

    def record_batch(self, batch, iters):
        drawn.append(batch.rays.clone())
        return real_call(self, batch, iters)

    def record_opacity(weights, t, ray_indices, ends, n_rays):
        out = real_opacity(weights, t, ray_indices, ends, n_rays)
        calls.append((drawn[-1], ends.detach().clone(), float(out.detach().mean())))
        return out
    out = tmp_path_factory.mktemp("free_space_run")
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(LossTerms, "__call__", record_batch)
        patch.setattr(free_space_losses, "opacity_before", record_opacity)
        run_task(cfg, out_dir=out)
    return SimpleNamespace(dir=out, cfg=cfg, metrics=json.loads((out / "metrics.json").read_text()), calls=calls)
