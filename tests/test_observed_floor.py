"""bench/observed_floor.py: the true mesh cut to what the cameras see, scored against the whole truth,
costs exactly the unseen part's distance to the kept surface (an analytic cube seen from above)."""

import pytest
import torch

from bench_scripts import load_bench_script
from l3d_app.geometry import primitives as P
from l3d_app.geometry.cameras import look_at_cameras
from l3d_app.metrics.surface_scores import surface_scores


def test_a_cube_seen_from_above_scores_the_distance_of_its_bottom_to_its_sides():
    floor = load_bench_script("observed_floor")
    el = torch.tensor([30.0, 60.0]).repeat_interleave(12)
    az = (torch.arange(12) * 30.0).repeat(2)
    cams = look_at_cameras(4.0, el, az, 40.0, 48)             # +Y up: the -Y face is never seen
    truth = P.cube(1.0)
    seen, cut = floor.observed_truth(truth, cams)
    assert cut == pytest.approx(1.0 / 6.0, abs=1e-6) and seen.num_faces == 10
    s = surface_scores(seen, truth, n=40000, threshold=0.05)
    # the kept faces lie on the truth (accuracy 0); a bottom point's nearest kept surface is the nearest
    # side wall, at min(x, 1-x, z, 1-z) from it: mean 1/6 over the unit square, and the bottom is 1/6 of the area
    assert s["accuracy_distance"] == pytest.approx(0.0, abs=1e-9)
    assert s["completeness_distance"] == pytest.approx(1.0 / 36.0, rel=0.05)
    assert s["precision"] == 1.0
    # recall at 0.05: the bottom's points within 0.05 of a wall, 1 - 0.9^2 of it
    assert s["recall"] == pytest.approx(5.0 / 6.0 + (1 - 0.9 ** 2) / 6.0, abs=0.01)
