"""bench/surface_by_part.py's per-object surface figures against values known in closed form: two unit
squares as the true parts, a prediction that lifts one by 0.03 and adds a phantom square above it."""

import math

import pytest
import torch

from bench_scripts import load_bench_script
from l3d_app.geometry.mesh import Mesh
from l3d_app.geometry.primitives import join


def _square(x0: float, z: float) -> Mesh:
    """The unit square [x0, x0 + 1] x [0, 1] at height z (two triangles)."""
    v = torch.tensor([[x0, 0, z], [x0 + 1, 0, z], [x0 + 1, 1, z], [x0, 1, z]], dtype=torch.float64)
    return Mesh(v, torch.tensor([[0, 1, 2], [0, 2, 3]]))


def _rows():
    mod = load_bench_script("surface_by_part")
    a, b = _square(0.0, 0.0), _square(3.0, 0.0)
    pred = join([_square(0.0, 0.03), b, _square(0.0, 0.5)])    # part a lifted by 0.03, b exact, a phantom over a
    return mod.scores_by_part(pred, join([a, b]), [a, b], samples=20000, seed=0)


def test_each_part_gets_its_own_completeness_and_accuracy():
    a, b, whole = _rows()
    assert a["truth_to_mesh"] == pytest.approx(0.03, abs=1e-9)     # every true sample of a: 0.03 below the lift
    assert a["truth_far"] == 1.0 and b["truth_far"] == 0.0
    assert b["truth_to_mesh"] == pytest.approx(0.0, abs=1e-9)
    # the prediction's area: a's lift and the phantom go to part a (2/3 of the area), b's copy to b
    assert a["mesh_share"] == pytest.approx(2 / 3, abs=0.015) and b["mesh_share"] == pytest.approx(1 / 3, abs=0.015)
    assert a["mesh_share"] + b["mesh_share"] == pytest.approx(1.0)
    # a's samples: half at 0.03 (the lift), half at 0.5 (the phantom): accuracy mean 0.265, phantom share 1/2
    assert a["phantom"] == pytest.approx(0.5, abs=0.02)
    assert a["mesh_to_truth"] == pytest.approx(0.03 + 0.47 * a["phantom"], abs=1e-9)
    assert b["phantom"] == 0.0 and b["mesh_to_truth"] == pytest.approx(0.0, abs=1e-9)
    assert whole["part"] == "all" and whole["true_samples"] == a["true_samples"] + b["true_samples"] == 20000
    assert whole["phantom"] == pytest.approx(1 / 3, abs=0.015)
    assert whole["truth_to_mesh"] == pytest.approx(0.03 * a["true_samples"] / 20000, abs=1e-9)


def test_a_part_the_prediction_never_comes_near_has_nan_accuracy():
    mod = load_bench_script("surface_by_part")
    a, b = _square(0.0, 0.0), _square(3.0, 0.0)
    ra, rb, _ = mod.scores_by_part(_square(0.0, 0.0), join([a, b]), [a, b], samples=2000, seed=1)
    assert rb["mesh_samples"] == 0 and math.isnan(rb["mesh_to_truth"]) and math.isnan(rb["phantom"])
    # b's samples (x uniform in [3, 4]) lie x - 1 from a's edge at x = 1: mean 2.5, all farther than 0.02
    assert rb["truth_to_mesh"] == pytest.approx(2.5, abs=0.03) and rb["truth_far"] == 1.0
    assert ra["truth_to_mesh"] == pytest.approx(0.0, abs=1e-9) and ra["mesh_share"] == 1.0 and ra["phantom"] == 0.0


def test_the_command_line_says_what_is_missing(tmp_path):
    mod = load_bench_script("surface_by_part")
    (tmp_path / "mesh.ply").write_text("")
    with pytest.raises(SystemExit, match="no file"):
        mod.main([str(tmp_path / "absent.ply"), "--scene", str(tmp_path)])
    with pytest.raises(SystemExit, match="no parts"):
        mod.main([str(tmp_path / "mesh.ply"), "--scene", str(tmp_path)])
