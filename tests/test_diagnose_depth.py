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
