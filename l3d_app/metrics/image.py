"""Image error figures: PSNR and SSIM for float images in [0, 1], shapes (..., H, W, C)."""

from __future__ import annotations

import torch
import torch.nn.functional as F


def psnr(pred: torch.Tensor, target: torch.Tensor, max_val: float = 1.0) -> torch.Tensor:
    """Peak signal-to-noise ratio in dB over all elements; +inf for identical images."""
    dtype = torch.promote_types(pred.dtype, torch.float32)
    mse = torch.mean((pred.to(dtype) - target.to(dtype)) ** 2)
    return 10.0 * torch.log10(max_val ** 2 / mse)


def _gaussian_window(size: int, sigma: float, dtype, device) -> torch.Tensor:
    x = torch.arange(size, dtype=dtype, device=device) - (size - 1) / 2
    g = torch.exp(-x ** 2 / (2 * sigma ** 2))
    return g / g.sum()


def ssim(pred: torch.Tensor, target: torch.Tensor, window: int = 11, sigma: float = 1.5,
         max_val: float = 1.0, k1: float = 0.01, k2: float = 0.03) -> torch.Tensor:
    """Mean structural similarity (Wang et al. 2004) with a Gaussian window (11, 1.5).

    Images (H, W, C) or (B, H, W, C); statistics use 'valid' windows only (no padding),
    per channel, then the mean over windows, channels and batch. Differentiable.
    """
    dtype = torch.promote_types(pred.dtype, torch.float32)  # float64 stays float64
    x, y = (t.to(dtype).reshape(-1, *t.shape[-3:]).permute(0, 3, 1, 2) for t in (pred, target))
    c = x.shape[1]
    window = min(window, x.shape[-1], x.shape[-2])
    g = _gaussian_window(window, sigma, x.dtype, x.device)
    # the five local means in one grouped convolution, the Gaussian window applied as its two
    # 1D factors (rows, then columns: 2 x 11 taps per pixel instead of 121; the same window)
    stack = torch.cat([x, y, x * x, y * y, x * y], 1)                          # (B, 5C, H, W)
    n = stack.shape[1]
    rows = F.conv2d(stack, g.view(1, 1, 1, window).expand(n, 1, 1, window), groups=n)
    mu_x, mu_y, e_xx, e_yy, e_xy = F.conv2d(rows, g.view(1, 1, window, 1).expand(n, 1, window, 1),
                                            groups=n).split(c, 1)
    var_x = e_xx - mu_x ** 2
    var_y = e_yy - mu_y ** 2
    cov = e_xy - mu_x * mu_y
    c1, c2 = (k1 * max_val) ** 2, (k2 * max_val) ** 2
    num = (2 * mu_x * mu_y + c1) * (2 * cov + c2)
    den = (mu_x ** 2 + mu_y ** 2 + c1) * (var_x + var_y + c2)
    return (num / den).mean()
