import math

import pytest
import torch

from l3d_app.metrics.image import psnr, ssim


def test_psnr_known_value():
    a = torch.zeros(4, 4, 3)
    b = torch.full((4, 4, 3), 0.1)
    assert float(psnr(a, b)) == pytest.approx(20.0, abs=1e-5)  # mse 0.01 -> 20 dB
    assert math.isinf(float(psnr(a, a)))


def test_ssim_identical_and_constant_images():
    img = torch.rand(2, 20, 24, 3, generator=torch.Generator().manual_seed(0))
    assert float(ssim(img, img)) == pytest.approx(1.0, abs=1e-6)
    a, b = 0.3, 0.7  # constant images: variances and covariance vanish
    expected = (2 * a * b + 0.01 ** 2) / (a * a + b * b + 0.01 ** 2)
    assert float(ssim(torch.full((16, 16, 3), a, dtype=torch.float64), torch.full((16, 16, 3), b, dtype=torch.float64))) == pytest.approx(expected, rel=1e-5)


def test_ssim_matches_naive_float64_window_loop():
    gen = torch.Generator().manual_seed(1)
    x = torch.rand(13, 12, 1, generator=gen, dtype=torch.float64)
    y = (x + 0.1 * torch.randn(13, 12, 1, generator=gen, dtype=torch.float64)).clamp(0, 1)
    w = 11
    g = torch.exp(-(torch.arange(w, dtype=torch.float64) - 5) ** 2 / (2 * 1.5 ** 2))
    k = (g[:, None] * g[None, :]) / (g.sum() ** 2)
    vals = []
    for i in range(13 - w + 1):  # naive reference: a loop over windows, in the test only
        for j in range(12 - w + 1):
            px, py = x[i:i + w, j:j + w, 0], y[i:i + w, j:j + w, 0]
            mx, my = (k * px).sum(), (k * py).sum()
            vx, vy = (k * px * px).sum() - mx ** 2, (k * py * py).sum() - my ** 2
            cxy = (k * px * py).sum() - mx * my
            vals.append((2 * mx * my + 1e-4) * (2 * cxy + 9e-4) / ((mx ** 2 + my ** 2 + 1e-4) * (vx + vy + 9e-4)))
    assert float(ssim(x, y)) == pytest.approx(float(torch.stack(vals).mean()), rel=1e-5)
