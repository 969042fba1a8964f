"""task=stereo_depth: recovered depth and its error against the first-order law Z^2 sigma / (f B)."""

import json

import pytest
import torch

from l3d_app.app import run_task
from l3d_app.metrics.stereo_error import binned_rmse, noisy_depth, simulate_depth_error


def test_noisy_depth_matches_a_direct_formula():
    z = torch.linspace(1.0, 5.0, 50, dtype=torch.float64)
    out = noisy_depth(z, 500.0, 0.2, 0.3, torch.Generator().manual_seed(3))
    n = torch.randn(z.shape, generator=torch.Generator().manual_seed(3)).to(torch.float64)
    torch.testing.assert_close(out["depth"], 100.0 / (100.0 / z + 0.3 * n))


def test_first_order_law_holds_for_small_noise_and_scales_with_baseline():
    z = torch.full((20000,), 4.0, dtype=torch.float64)
    g = torch.Generator().manual_seed(0)
    a = simulate_depth_error(z, 800.0, 0.1, 0.1, g)          # d = 20 px, sigma 0.1 px
    assert a["rmse_first_order"] == pytest.approx(16 / 80 * 0.1)
    assert a["ratio"] == pytest.approx(1.0, abs=0.02)
    b = simulate_depth_error(z, 800.0, 0.2, 0.1, g)
    assert b["rmse"] / a["rmse"] == pytest.approx(0.5, abs=0.02)
    # large noise: the exact error grows faster than first order (1/d is convex)
    c = simulate_depth_error(z, 800.0, 0.1, 4.0, g)
    assert c["ratio"] > 1.05 and c["bias"] > 0


def test_binned_rmse():
    depth = torch.tensor([1.0, 1.1, 2.9, 3.0])
    err = torch.tensor([1.0, -1.0, 2.0, 2.0])
    out = binned_rmse(depth, err, bins=2)
    assert out["rmse"] == pytest.approx([1.0, 2.0]) and out["depth"] == pytest.approx([1.5, 2.5])


def test_stereo_depth_task_table(compose, tmp_path):
    run_task(compose("task=stereo_depth", "image_size=48", "trials=2", "focal_px=140"), out_dir=tmp_path)
    m = json.loads((tmp_path / "metrics.json").read_text())
    assert len(m["rows"]) == 1 + 4 + 4 + 5 and m["n_pixels"] > 100
    small = [r for r in m["rows"] if r["sigma_px"] == 0.1][0]
    assert small["ratio"] == pytest.approx(1.0, abs=0.03)
    base = {r["baseline"]: r["rmse_first_order"] for r in m["rows"] if r["varied"] == "baseline"}
    assert base[0.05] == pytest.approx(2 * base[0.1], rel=1e-4) and base[0.4] == pytest.approx(base[0.1] / 4, rel=1e-4)
    for name in ("stereo.png", "error_vs_depth.png", "table.md"):
        assert (tmp_path / name).stat().st_size > 0
