"""Uniform vs stratified ray sampling: measured variances against the exact ones, and their rates."""

import json
import math

import pytest
import torch

from l3d_app.app import run_task
from l3d_app.render.volume.sampling_variance import (GaussianBump, Slab, optical_depth_estimates,
                                              stratified_variance_slab, uniform_variance)


def test_closed_forms_by_direct_quadrature():
    t = torch.linspace(1.0, 5.0, 400001, dtype=torch.float64)
    for d in (Slab(2.3, 3.1, 2.0), GaussianBump(3.0, 0.3, 2.0)):
        for p in (1, 2):
            assert d.integral(1.0, 5.0, p) == pytest.approx(float(torch.trapezoid(d(t) ** p, t)), rel=1e-4)
    # stratified slab variance by hand: N = 2 -> bins [1, 3] and [3, 5]; the slab [2.3, 3.1] covers
    # p = 0.35 of the first and 0.05 of the second: 4 * 4 * (0.35 * 0.65 + 0.05 * 0.95)
    assert stratified_variance_slab(Slab(2.3, 3.1, 2.0), 1.0, 5.0, 2) == pytest.approx(16 * (0.2275 + 0.0475))


@pytest.mark.parametrize("n", [4, 16, 64])
def test_measured_variance_matches_the_exact_one(n):
    g = torch.Generator().manual_seed(n)
    slab = Slab(2.3, 3.1, 2.0)
    m = 20000
    u = optical_depth_estimates(slab, 1.0, 5.0, n, m, "uniform", g)
    s = optical_depth_estimates(slab, 1.0, 5.0, n, m, "stratified", g)
    assert float(u.var()) == pytest.approx(uniform_variance(slab, 1.0, 5.0, n), rel=0.08)
    assert float(s.var()) == pytest.approx(stratified_variance_slab(slab, 1.0, 5.0, n), rel=0.12)
    for est in (u, s):                                               # both unbiased
        assert abs(float(est.mean()) - 1.6) < 5 * math.sqrt(float(est.var()) / m)


def test_sampling_variance_task_rates(compose, tmp_path):
    run_task(compose("task=sampling_variance", "rays=3000", "samples=[4,8,16,32,64]"), out_dir=tmp_path)
    m = json.loads((tmp_path / "metrics.json").read_text())
    assert m["slab_uniform_slope"] == pytest.approx(-1.0, abs=0.1)
    assert m["bump_uniform_slope"] == pytest.approx(-1.0, abs=0.1)
    assert m["slab_stratified_slope"] == pytest.approx(-2.0, abs=0.3)
    assert m["bump_stratified_slope"] < -2.6
    assert len(m["rows"]) == 10 and (tmp_path / "variance.png").stat().st_size > 0


def test_bad_sample_counts_are_user_errors(compose, tmp_path):
    from l3d_app.errors import UserError

    with pytest.raises(UserError, match="samples"):
        run_task(compose("task=sampling_variance", "samples=[1,2]"), out_dir=tmp_path)
    assert not (tmp_path / "metrics.json").exists()
