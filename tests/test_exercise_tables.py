"""The worked exercises' exact tables: stereo depth error (f 1000 px, B 0.12 m, +-1 px), evenly spaced
against stratified ray samples, and the |n_y| > 0.8 / < 0.3 surface classes, against hand-computed values."""

import json
import math

import pytest
import torch

from l3d_app.app import run_task
from l3d_app.geometry.surface_orientation import HORIZONTAL, OTHER, VERTICAL, classify_by_cosine
from l3d_app.metrics.stereo_table import disparity_error_rows
from l3d_app.render.volume.sampling_variance import Slab, estimates_at, position_spread, sample_positions


def test_stereo_rows_by_hand():
    rows = disparity_error_rows(1000.0, 0.12, [10.0, 100.0, 120.0], 1.0)
    # Z = 10: d = 120 / 10 = 12 px; 120 / 11 - 10 and 120 / 13 - 10; first order 10^2 / 120
    assert rows[0]["disparity"] == pytest.approx(12.0)
    assert rows[0]["error_far"] == pytest.approx(120 / 11 - 10) and rows[0]["error_near"] == pytest.approx(120 / 13 - 10)
    assert rows[0]["first_order"] == pytest.approx(100 / 120)
    # Z = 100: d = 1.2 px; d - 1 = 0.2 px puts the point at 600 m
    assert rows[1]["error_far"] == pytest.approx(500.0) and rows[1]["error_near"] == pytest.approx(120 / 2.2 - 100)
    assert rows[1]["first_order"] == pytest.approx(1e4 / 120)
    assert math.isinf(rows[2]["error_far"])                  # d = 1 px: d - 1 = 0, at infinity


def test_stereo_exercise_preset_prints_the_table(compose, tmp_path, capsys):
    run_task(compose("task=stereo_depth", "preset=exercise"), out_dir=tmp_path)
    m = json.loads((tmp_path / "metrics.json").read_text())
    assert [r["depth"] for r in m["rows"]] == [1, 2, 5, 10, 20, 50, 100]
    for r in m["rows"]:                                          # the closed form Z^2 / (f B) * 1 px
        assert r["first_order"] == pytest.approx(r["depth"] ** 2 / 120.0, abs=1e-6)     # rounded to 6 places
        assert r["disparity"] == pytest.approx(120.0 / r["depth"], abs=1e-6)
    out = capsys.readouterr().out
    assert "| 20 | 6 | +4 | -2.857 |" in out and (tmp_path / "table.md").read_text().count("\n| ") == 8


def test_evenly_spaced_samples_have_no_spread_and_a_fixed_error():
    g = torch.Generator().manual_seed(0)
    slab = Slab(2.3, 3.1, 2.0)
    t = sample_positions(1.0, 5.0, 4, 500, "evenly", g)
    est = estimates_at(slab, t, 1.0, 5.0, "evenly")
    assert position_spread(t) == 0.0 and float(est.max() - est.min()) == 0.0
    # samples 1, 7/3, 11/3, 5 with strata widths 2/3, 4/3, 4/3, 2/3: only 7/3 lies in the slab -> 2 * 4/3
    assert float(est[0]) == pytest.approx(8 / 3)
    s = sample_positions(1.0, 5.0, 8, 40000, "stratified", g)
    assert position_spread(s) == pytest.approx(4.0 / (8 * math.sqrt(12)), rel=0.02)


def test_sampling_variance_task_shows_the_zero_spread(compose, tmp_path):
    run_task(compose("task=sampling_variance", "rays=200", "samples=[4,16]"), out_dir=tmp_path)
    m = json.loads((tmp_path / "metrics.json").read_text())
    assert m["evenly_max_spread"] == 0.0
    slab4 = [r for r in m["rows"] if r["density"] == "slab" and r["n_samples"] == 4][0]
    assert slab4["evenly_error"] == pytest.approx(8 / 3 - 1.6, abs=1e-6) and slab4["stratified_range"] > 0.5
    assert "range across rays" in (tmp_path / "table.md").read_text()


def test_classify_by_cosine_strict_thresholds():
    n = torch.tensor([[0, 1, 0], [0, 0.8, 0.6], [0, 0.81, math.sqrt(1 - 0.81 ** 2)], [1, 0, 0],
                      [0, 0.3, math.sqrt(0.91)], [0, -0.29, math.sqrt(1 - 0.29 ** 2)], [0, 0.5, math.sqrt(0.75)]],
                     dtype=torch.float64)
    assert classify_by_cosine(n).tolist() == [HORIZONTAL, OTHER, HORIZONTAL, VERTICAL, OTHER, VERTICAL, OTHER]


def test_pca_normals_exercise_counts_on_the_clean_room(compose, tmp_path, capsys):
    from l3d_app.data.room_scene import room_points

    run_task(compose("task=pca_normals", "preset=exercise", "data.num_samples=6000", "data.noise=0",
                     "image_size=32"), out_dir=tmp_path)
    m = json.loads((tmp_path / "metrics.json").read_text())
    assert m["count_horizontal"] + m["count_vertical"] + m["count_other"] == 6000
    truth = room_points(200000, noise=0.0, seed=5).normals[:, 1].abs()    # the room's own normals, |n_y|
    # PCA normals blur at the room's edges (a few % of the points at k = 16): the classes of the true normals
    assert m["fraction_horizontal"] == pytest.approx(float((truth > 0.8).double().mean()), abs=0.05)
    assert m["fraction_vertical"] == pytest.approx(float((truth < 0.3).double().mean()), abs=0.05)
    assert m["class_accuracy"] > 0.9
    assert f"horizontal {m['count_horizontal']}, vertical {m['count_vertical']}" in capsys.readouterr().out
