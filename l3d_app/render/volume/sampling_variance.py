"""Uniform vs stratified sampling along a ray: the variance of a quadrature estimate, measured and exact.

The estimated quantity is the optical depth ``tau = int_near^far sigma(t) dt`` of a 1D density
along a ray (world units along a unit ray). Two unbiased estimators with ``N`` samples:

- uniform: ``t_i ~ U(near, far)`` i.i.d., ``tau_hat = L / N * sum_i sigma(t_i)`` (``L = far - near``);
  ``Var = (L * int sigma^2 dt - tau^2) / N``, the 1/N Monte-Carlo rate;
- evenly spaced (the course's ``linspace``: stratified without the jitter): the same samples on every
  ray of the same length, so the estimate has zero spread across rays, and a fixed error (bias)
  instead of a variance;
- stratified (NeRF's, :func:`l3d_app.render.volume.samplers.stratified_samples` with ``perturb``): one
  ``t_i`` uniform in each bin ``[e_i, e_{i+1}]`` (:func:`~l3d_app.render.volume.samplers.bin_edges` of the unperturbed samples: the end bins are
  half as wide as the others),
  ``tau_hat = sum_i sigma(t_i) (e_{i+1} - e_i)``; only bins where ``sigma`` varies add variance:
  for a slab of constant density ``s`` the bins cut by an edge of the slab, each adding
  ``(w s)^2 p (1 - p)`` (width ``w``, share ``p`` of the bin inside the slab): a 1/N^2 rate;
  for a smooth density the rate is 1/N^3.

Densities (callables ``t (...) -> sigma (...)``) with closed forms: :class:`Slab`, :class:`GaussianBump`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from l3d_app.errors import UserError
from l3d_app.render.volume.samplers import bin_edges, stratified_samples
from l3d_app.runtime.random import rand

METHODS = ("uniform", "evenly", "stratified")


@dataclass
class Slab:
    """Density ``s`` on ``[start, end]``, 0 elsewhere."""
    start: float
    end: float
    s: float

    def __call__(self, t: torch.Tensor) -> torch.Tensor:
        return torch.where((t >= self.start) & (t <= self.end), torch.full_like(t, self.s), torch.zeros_like(t))

    def integral(self, near: float, far: float, power: int = 1) -> float:
        """``int_near^far sigma(t)^power dt``."""
        return self.s ** power * max(0.0, min(far, self.end) - max(near, self.start))


@dataclass
class GaussianBump:
    """Density ``s exp(-(t - centre)^2 / (2 width^2))``."""
    centre: float
    width: float
    s: float

    def __call__(self, t: torch.Tensor) -> torch.Tensor:
        return self.s * torch.exp(-0.5 * ((t - self.centre) / self.width) ** 2)

    def integral(self, near: float, far: float, power: int = 1) -> float:
        """``int_near^far sigma(t)^power dt`` (power 1 or 2), by the error function."""
        w = self.width / math.sqrt(power)
        a, b = (near - self.centre) / (w * math.sqrt(2)), (far - self.centre) / (w * math.sqrt(2))
        return self.s ** power * w * math.sqrt(math.pi / 2) * (math.erf(b) - math.erf(a))


def sample_positions(near: float, far: float, n_samples: int, n_rays: int, method: str,
                     generator: torch.Generator) -> torch.Tensor:
    """(n_rays, n_samples) float64 sample distances of ``method`` on rays of length ``far - near``."""
    if method not in METHODS:
        raise UserError(f"unknown sampling method '{method}'; known: {', '.join(METHODS)}")
    if not far > near or int(n_samples) < 1 or int(n_rays) < 1:
        raise UserError(f"need far > near, n_samples >= 1, n_rays >= 1; got {near}, {far}, {n_samples}, {n_rays}")
    if method != "uniform" and int(n_samples) < 2:
        raise UserError(f"{method} sampling needs n_samples >= 2 (one sample has no bins)")
    if method == "uniform":
        return near + (far - near) * rand((int(n_rays), int(n_samples)), generator).to(torch.float64)
    return stratified_samples(near, far, int(n_samples), n_rays=int(n_rays), perturb=method == "stratified",
                              generator=generator, dtype=torch.float64)


def optical_depth_estimates(density, near: float, far: float, n_samples: int, n_rays: int, method: str,
                            generator: torch.Generator) -> torch.Tensor:
    """(n_rays,) float64 estimates of ``int_near^far density`` with ``n_samples`` samples per ray."""
    return estimates_at(density, sample_positions(near, far, n_samples, n_rays, method, generator), near, far,
                        method)


def estimates_at(density, t: torch.Tensor, near: float, far: float, method: str) -> torch.Tensor:
    """(R,) float64 optical-depth estimates of ``method`` from its sample distances ``t`` (R, S): the mean
    density times the length for uniform draws, each sample times its stratum's width otherwise."""
    n_samples = t.shape[-1]
    if method == "uniform":
        return (far - near) / n_samples * density(t).sum(dim=-1)
    strata = stratified_samples(near, far, int(n_samples), n_rays=1, dtype=torch.float64)  # unperturbed
    widths = bin_edges(strata, near, far).diff(dim=-1)              # (1, S): the strata, not the draws
    return (density(t) * widths).sum(dim=-1)


def position_spread(t: torch.Tensor) -> float:
    """Mean over the sample index of the standard deviation across rays of the sample distance (t (R, S)):
    0 for evenly spaced samples; ``(far - near) / (S sqrt(12))`` for stratified ones (one uniform draw per bin,
    the two end bins half wide)."""
    return float(t.std(dim=0, unbiased=False).mean())


def uniform_variance(density, near: float, far: float, n_samples: int) -> float:
    """Exact variance of the uniform estimator: ``(L int sigma^2 - tau^2) / N``."""
    length = far - near
    return (length * density.integral(near, far, 2) - density.integral(near, far) ** 2) / int(n_samples)


def stratified_variance_slab(slab: Slab, near: float, far: float, n_samples: int) -> float:
    """Exact variance of the stratified estimator on a :class:`Slab`: ``sum_bins (w s)^2 p (1 - p)``."""
    t = torch.linspace(near, far, int(n_samples), dtype=torch.float64)[None]
    e = bin_edges(t, near, far)[0] if int(n_samples) > 1 else torch.tensor([near, far], dtype=torch.float64)
    lo, hi = e[:-1], e[1:]
    w = hi - lo
    inside = (torch.minimum(hi, torch.tensor(slab.end)) - torch.maximum(lo, torch.tensor(slab.start))).clamp_min(0)
    p = inside / w
    return float(((w * slab.s) ** 2 * p * (1 - p)).sum())


def loglog_slope(ns, values) -> float:
    """Least-squares slope of log(values) against log(ns)."""
    x = torch.log(torch.as_tensor(ns, dtype=torch.float64))
    y = torch.log(torch.as_tensor(values, dtype=torch.float64))
    x = x - x.mean()
    return float((x * (y - y.mean())).sum() / x.square().sum())
