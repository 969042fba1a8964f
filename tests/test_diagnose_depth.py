"""bench/diagnose_depth.py's shares of a learnt surface in front of / behind the truth, counted by
hand on depth maps built for the purpose (+inf where a mesh covers no pixel)."""

import math

import torch

from bench_scripts import load_bench_script


def _diag():
    return load_bench_script("diagnose_depth")


def test_shares_count_front_behind_and_uncovered_pixels():
    inf = math.inf
    truth = torch.tensor([[[2.0, 2.0, 2.0, 2.0, 2.0, inf]]])        # (1, 1, 6)
    mesh = torch.tensor([[[1.9, 1.94, 2.01, 2.2, inf, 3.0]]])
    s = _diag().depth_error_shares(mesh, truth, tol=0.05)
    # both cover pixels 0-3: errors -0.1 (front), -0.06 (front), 0.01 (inside tol), 0.2 (behind)
    assert s["pixels"] == 4
    assert s["front"] == 0.5 and s["behind"] == 0.25
    assert abs(s["median_abs"] - 0.06) < 1e-6          # torch's lower median of 0.01, 0.06, 0.1, 0.2
    assert s["mesh_only"] == 1 and s["truth_only"] == 1


def test_identical_maps_have_no_error():
    d = torch.full((2, 3, 3), 1.5)
    d[0, 0, 0] = math.inf
    s = _diag().depth_error_shares(d, d.clone(), tol=0.05)
    assert s["pixels"] == 17 and s["front"] == 0.0 and s["behind"] == 0.0 and s["median_abs"] == 0.0
    assert s["mesh_only"] == 0 and s["truth_only"] == 0


def test_field_split_counts_what_the_renderer_sees_and_pays_on_front_pixels():
    inf = math.inf
    truth = torch.tensor([[[2.0, 2.0, 2.0, 2.0, inf]]])               # (1, 1, 5)
    mesh = torch.tensor([[[1.8, 1.8, 2.0, 1.8, 2.0]]])                # pixels 0, 1, 3 in front by 0.2
    field = torch.tensor([[[1.81, 1.95, 2.0, 1.8, 2.0]]])             # sees the mesh at 0 (0.01) and 3, not at 1 (0.15)
    alpha = torch.tensor([[[1.0, 1.0, 1.0, 0.2, 1.0]]])               # pixel 3: field too faint, not counted
    target = torch.zeros(1, 1, 5, 3)
    color = torch.zeros(1, 1, 5, 3)
    color[0, 0, 0] = 0.3                                              # squared error 0.09
    color[0, 0, 1] = 0.1                                              # 0.01
    color[0, 0, 2] = 0.2                                              # 0.04 (a covered pixel not in front)
    f = _diag().field_split(field, alpha, color, target, mesh, truth, tol=0.05, agree=0.02)
    assert f["front_pixels"] == 2
    assert f["field_sees"] == 0.5
    assert abs(f["mse_front"] - 0.05) < 1e-7 and abs(f["mse_rest"] - 0.04) < 1e-7


def test_field_split_without_front_pixels_reports_nan():
    d = torch.full((1, 2, 2), 1.0)
    f = _diag().field_split(d, torch.ones_like(d), torch.zeros(1, 2, 2, 3), torch.zeros(1, 2, 2, 3), d, d.clone(), 0.05, 0.02)
    assert f["front_pixels"] == 0 and math.isnan(f["field_sees"]) and math.isnan(f["mse_front"]) and f["mse_rest"] == 0.0


def test_field_split_counts_only_the_region_asked():
    truth = torch.full((1, 1, 3), 2.0)
    mesh = torch.tensor([[[1.8, 1.8, 2.0]]])
    color = torch.tensor([[[[0.3] * 3, [0.1] * 3, [0.2] * 3]]])
    region = torch.tensor([[[True, False, True]]])
    f = _diag().field_split(mesh.clone(), torch.ones(1, 1, 3), color, torch.zeros(1, 1, 3, 3), mesh, truth, 0.05, 0.02,
                            region=region)
    assert f["front_pixels"] == 1 and f["field_sees"] == 1.0
    assert abs(f["mse_front"] - 0.09) < 1e-7 and abs(f["mse_rest"] - 0.04) < 1e-7


def test_nearest_part_names_the_part_that_is_the_first_surface():
    inf = math.inf
    truth = torch.tensor([[[1.0, 2.0, inf, 3.0]]])
    parts = torch.tensor([[[[1.0, inf, inf, 3.5]]],               # part 0: first at pixel 0; at pixel 3 the only part covering it
                          [[[1.6, 2.0, inf, inf]]]])              # part 1: first at pixel 1
    which = _diag().nearest_part(parts, truth)
    assert which.tolist() == [[[0, 1, -1, 0]]]
