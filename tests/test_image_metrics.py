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


@pytest.mark.parametrize("shape", [(40, 37, 3), (2, 24, 30, 3), (11, 11, 1)])
def test_ssim_and_psnr_match_scikit_image(shape):
    """Against scikit-image (independent code): Gaussian window sigma 1.5 (11 px), population
    covariances, data range 1 (Wang et al. 2004), mean over channels and images; PSNR too."""
    from skimage.metrics import peak_signal_noise_ratio, structural_similarity

    gen = torch.Generator().manual_seed(2)
    x = torch.rand(*shape, generator=gen, dtype=torch.float64)
    y = (x + 0.2 * torch.randn(*shape, generator=gen, dtype=torch.float64)).clamp(0, 1)
    xs, ys = x.reshape(-1, *shape[-3:]).numpy(), y.reshape(-1, *shape[-3:]).numpy()
    ref = sum(structural_similarity(a, b, channel_axis=-1, gaussian_weights=True, sigma=1.5,
                                    use_sample_covariance=False, data_range=1.0) for a, b in zip(xs, ys)) / len(xs)
    assert float(ssim(x, y)) == pytest.approx(ref, rel=1e-10)
    assert float(psnr(x, y)) == pytest.approx(peak_signal_noise_ratio(ys, xs, data_range=1.0), rel=1e-10)
