"""density=neus_logistic: phi_s of the SDF as the density, against its closed forms (the logistic PDF, the
total optical depth 1 through a plane, the weight's peak 0.481 / s in front of it), finite at s = 1e4."""

from __future__ import annotations

import math

import mpmath
import pytest
import torch

from l3d_app.registry import DENSITIES
from l3d_app.render.sdf.neus_logistic import NeuSLogisticDensity
from l3d_app.render.volume.renderer import composite


def _density(s):
    import l3d_app.render  # noqa: F401  (registers the densities)
    return DENSITIES.build({"name": "neus_logistic", "s": s})


@pytest.mark.parametrize("s", [1.0, 64.0, 1e4])
def test_values_and_gradients_against_the_logistic_pdf(s):
    x = torch.tensor([-1e3, -0.3, -1e-3, 0.0, 2e-4, 0.05, 7.0, 1e3], dtype=torch.float64, requires_grad=True)
    d = _density(s).double()
    sigma = d(x)
    (grad,) = torch.autograd.grad(sigma.sum(), x)
    assert torch.isfinite(sigma).all() and torch.isfinite(grad).all()
    for xi, si, gi in zip(x.tolist(), sigma.tolist(), grad.tolist()):
        e = mpmath.exp(-mpmath.mpf(s) * xi)
        ref = s * e / (1 + e) ** 2                                            # s e^{-sx} / (1 + e^{-sx})^2
        dref = mpmath.diff(lambda y: s * mpmath.exp(-s * y) / (1 + mpmath.exp(-s * y)) ** 2, xi)
        assert si == pytest.approx(float(ref), rel=1e-9, abs=1e-300)
        assert gi == pytest.approx(float(dref), rel=1e-6, abs=1e-200)


def test_a_plane_gets_optical_depth_one_and_its_weight_peaks_in_front():
    s, t0 = 40.0, 1.0
    t = torch.linspace(0.0, 2.0, 20001, dtype=torch.float64)[None]
    ends = torch.cat([t[:, 1:], t[:, -1:]], dim=-1)
    d = NeuSLogisticDensity(s=s).double()
    tau = d.optical_depth(t0 - t[0], t[0], ends[0], torch.zeros(t.shape[1], dtype=torch.long))
    assert float(tau.sum()) == pytest.approx(1.0, abs=1e-3)                  # int phi_s = 1: never opaque
    w = composite(torch.zeros(1, t.shape[1], 1, dtype=torch.float64), t, sigmas=tau[None],
                  deltas=torch.ones_like(t))
    assert float(w["opacity"]) == pytest.approx(1 - math.exp(-1), abs=1e-3)
    peak = float(t[0, w["weights"][0].argmax()])
    assert t0 - peak == pytest.approx(math.log((1 + math.sqrt(5)) / 2) / s, abs=2e-4)   # 0.481 / s in front


def test_widen_lets_coarse_samples_see_a_sharp_peak():
    d = NeuSLogisticDensity(s=1000.0).double()
    t = torch.arange(0.0, 4.0, 0.5, dtype=torch.float64) + 0.13                 # spacing 0.5, surface at 2.0
    ends = t + 0.5
    rays = torch.zeros(len(t), dtype=torch.long)
    sharp = d.optical_depth(2.0 - t, t, ends, rays)
    wide = d.optical_depth(2.0 - t, t, ends, rays, widen=torch.full_like(t, 0.5))
    assert float(sharp.sum()) < 1e-6 and 0.5 < float(wide.sum()) < 1.5
