"""The seconds a time-budgeted task keeps for its marching-cubes mesh follow ``mesh_resolution``:
the configured price holds at 128, another resolution adds twice the grid's extra points at the
level function's measured cost. A fake clock advanced by the level function itself makes the
measurement exact, so every figure below is hand arithmetic, not this machine's speed."""

import pytest
import torch

from l3d_app.render import field_mesh
from l3d_app.render.field_mesh import PROBE_RESOLUTION, seconds_per_grid_point
from l3d_app.runtime.budget import MESH_PRICED_AT, TimeBudget, mesh_seconds_at

BOX = ([-1.0, -1.0, -1.0], [1.0, 1.0, 1.0])


class FakeClock:
    """perf_counter for field_mesh; a level function advances it by ``cost`` seconds per point."""

    def __init__(self, cost: float):
        self.now, self.cost, self.points = 0.0, cost, 0

    def __call__(self) -> float:
        return self.now

    def level_fn(self, p: torch.Tensor) -> torch.Tensor:
        assert p.ndim == 2 and p.shape[1] == 3       # (N, 3) rows, as extract_mesh calls it
        self.now += self.cost * p.shape[0]
        self.points += p.shape[0]
        return p.norm(dim=-1) - 0.5


@pytest.fixture
def clock(monkeypatch):
    fake = FakeClock(cost=2e-6)
    monkeypatch.setattr(field_mesh.time, "perf_counter", fake)
    return fake


def test_the_probe_measures_seconds_per_point_of_the_grid(clock):
    assert seconds_per_grid_point(clock.level_fn, BOX) == pytest.approx(2e-6, rel=1e-12)
    assert clock.points == PROBE_RESOLUTION ** 3         # each grid point once, no more


@pytest.mark.parametrize("resolution, at_128, expected", [
    (128, 35.0, 35.0),                                    # the configured price, as measured at 128
    (256, 35.0, 35.0 + 58.720256),                        # + twice 14,680,064 extra points at 2 us
    (64, 35.0, 35.0 - 7.340032),                          # fewer points, less time: twice 1,835,008 at 2 us
    (8, 1.0, 0.0),                                        # never below nothing
])
def test_the_price_follows_the_grid(resolution, at_128, expected):
    assert MESH_PRICED_AT == 128
    assert mesh_seconds_at(resolution, at_128, 2e-6) == pytest.approx(expected, rel=1e-12)


def test_nothing_is_measured_at_128_or_without_a_budget(clock):
    def measure():
        return seconds_per_grid_point(clock.level_fn, BOX)
    for seconds, resolution in ((590.0, 128), (0.0, 256)):
        timer = TimeBudget(seconds, reserve=5.0)
        assert timer.keep_mesh(resolution, 35.0, measure) == 35.0 and timer.reserve == 40.0
    assert clock.points == 0
    notes = []
    timer = TimeBudget(590.0, note=lambda tag, text: notes.append((tag, text)))
    assert timer.keep_mesh(256, 35.0, measure) == pytest.approx(35.0 + 58.720256, rel=1e-9)
    assert timer.reserve == pytest.approx(35.0 + 58.720256, rel=1e-9)
    assert notes[0][0] == "reserve" and "2.00 us per grid point" in notes[0][1]


class _Reserved(Exception):
    pass


SMALL = ("data.image_size=16", "data.n_train=4", "data.n_val=1", "data.n_test=1", "before_after=false",
         "tensorboard=false", "time_budget=590")
VOLSDF = ("task=volsdf", "stages.free_space.steps=0", "stages.sphere_init.steps=5", *SMALL)


@pytest.mark.parametrize("task, overrides, expected", [
    ("volsdf", (*VOLSDF,), 35.0),
    ("volsdf", (*VOLSDF, "mesh_resolution=256"), 35.0 + 2 * 1e-6 * (256 ** 3 - 128 ** 3)),
    ("volsdf", (*VOLSDF, "mesh_resolution=256", "reserve=50"), 50.0 + 2 * 1e-6 * (256 ** 3 - 128 ** 3)),
    ("train_nerf", ("task=train_nerf", "extract_mesh=true", "mesh_resolution=192", *SMALL),
     5.0 + 30.0 + 2 * 1e-6 * (192 ** 3 - 128 ** 3)),                    # its own reserve (5 s) and the mesh's
    ("train_nerf", ("task=train_nerf", "extract_mesh=true", "mesh_resolution=192", "reserve=0", *SMALL),
     30.0 + 2 * 1e-6 * (192 ** 3 - 128 ** 3)),
])
def test_a_task_keeps_the_priced_seconds_for_its_mesh(compose, tmp_path, monkeypatch, task, overrides, expected):
    # mesh_resolution=256 used to keep the 35 s measured at 128, where the mesh step takes ~twice that
    import importlib

    from l3d_app.app import run_task
    module = importlib.import_module(f"l3d_app.tasks.{task}")
    seen = {}

    def fake_train(ctx, trainable, step_fn, spec, eval_fn=None, budget=None, after_step=None):
        seen["reserve"] = budget.reserve
        raise _Reserved
    monkeypatch.setattr(module, "train", fake_train)
    monkeypatch.setattr(module, "seconds_per_grid_point", lambda *a, **k: 1e-6)
    with pytest.raises(_Reserved):
        run_task(compose(*overrides), out_dir=tmp_path)
    assert seen["reserve"] == pytest.approx(expected, rel=1e-12)
