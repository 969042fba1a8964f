"""Volume rendering: emission-absorption compositing along rays, chunked ray rendering.

Along a ray with samples at distances ``t_i`` (world units along unit directions), each
sample stands for the segment ``[t_i, t_i + delta_i)`` of constant density ``sigma_i``
(1 / world units) and colour ``c_i``. Then, for every sample i (nothing is approximated
beyond the piecewise-constant model)::

    tau_i   = sigma_i * delta_i                      optical depth of segment i
    T_i     = exp(-sum_{j<i} tau_j)                  transmittance from the ray start to t_i
    alpha_i = 1 - exp(-tau_i) = -expm1(-tau_i)       opacity of segment i
    w_i     = T_i * alpha_i                          compositing weight
    colour  = sum_i w_i c_i  (+ (1 - opacity) * background)
    opacity = sum_i w_i = 1 - exp(-sum_i tau_i)      in [0, 1]
    depth   = sum_i w_i t_i                          (not divided by opacity)

The exclusive cumulative sum is taken in log space (never ``cumprod(1 - alpha + eps)``),
so huge ``sigma`` (1e10) and huge ``delta`` (1e10) give exact zeros, not NaN, in values and
gradients.

Alpha mode: when opacities ``alpha_i`` in [0, 1] are given directly (the course's box rule
uses the VolSDF Laplace-CDF value as each sample's opacity), ``T_i = prod_{j<i} (1 - alpha_j)``
is computed as ``exp(sum_{j<i} log1p(-alpha_j))`` with ``alpha`` clamped to
``1 - eps(dtype)`` inside the logarithm only, so a fully opaque sample lets through a
transmittance of ``eps`` (1.2e-7 in float32, 2.2e-16 in float64) instead of making
``log(0)`` and NaN gradients.

Last delta: by default the last sample's segment is ``last_delta = 1e10`` long (it extends
"to infinity", as in NeRF and the course), so any positive density there absorbs the rest of
the ray. Pass ``deltas`` explicitly (e.g. ``far - t_last`` for the last one) to end rays at
``far`` instead.
"""

from __future__ import annotations

from typing import Callable, Dict, Optional, Sequence, Union

import torch

from l3d_app.errors import UserError
from l3d_app.geometry.cameras import Cameras
from l3d_app.geometry.rays import camera_rays
from l3d_app.registry import RENDERERS
from l3d_app.render.volume.samplers import stratified_samples

Background = Union[None, float, Sequence[float], torch.Tensor]


def sample_deltas(t: torch.Tensor, last_delta: float = 1e10) -> torch.Tensor:
    """(R, S) segment lengths ``t_{i+1} - t_i`` with ``last_delta`` for the last sample."""
    last = torch.full_like(t[:, :1], float(last_delta))
    return torch.cat([t[:, 1:] - t[:, :-1], last], dim=-1)


def _exclusive_cumsum(x: torch.Tensor) -> torch.Tensor:
    """(R, S) ``sum_{j<i} x_j`` (0 for i = 0), without the lossy ``cumsum(x) - x``."""
    return torch.cat([torch.zeros_like(x[:, :1]), torch.cumsum(x[:, :-1], dim=-1)], dim=-1)


class _OpacityFromOpticalDepth(torch.autograd.Function):
    """alpha = 1 - exp(-tau) = -expm1(-tau), with d alpha / d tau = exp(-tau) computed directly.

    torch's own expm1 backward rebuilds exp(-tau) as ``result + 1``, which is 0 in float32
    once tau > ~16.6 (and loses relative accuracy well before), so a long, dense segment (the
    1e10-long last one) would get no gradient at all.
    """

    @staticmethod
    def forward(ctx, tau):
        ctx.save_for_backward(tau)
        return -torch.expm1(-tau)

    @staticmethod
    def backward(ctx, grad):
        (tau,) = ctx.saved_tensors
        return grad * torch.exp(-tau)


def opacity_from_optical_depth(tau: torch.Tensor) -> torch.Tensor:
    """``1 - exp(-tau)`` (any shape; tau >= 0), accurate for small tau and with an exact
    gradient ``exp(-tau)`` for large tau in float32."""
    return _OpacityFromOpticalDepth.apply(tau)


def composite(colors: torch.Tensor, t: torch.Tensor, sigmas: Optional[torch.Tensor] = None,
              alphas: Optional[torch.Tensor] = None, deltas: Optional[torch.Tensor] = None,
              background: Background = None, last_delta: float = 1e10) -> Dict[str, torch.Tensor]:
    """Composite samples along R rays front to back (see the module docstring).

    Args:
        colors: (R, S, C) per-sample colour/feature.
        t: (R, S) sorted sample distances (world units along unit rays).
        sigmas: (R, S) densities >= 0 (1 / world units); give exactly one of sigmas/alphas.
        alphas: (R, S) per-sample opacities in [0, 1] (alpha mode; ``deltas`` unused).
        deltas: (R, S) segment lengths; default :func:`sample_deltas` (``t`` differences,
            ``last_delta`` for the last sample).
        background: None (black, nothing added), a float, a (C,) colour or an (R, C)
            tensor: ``color += (1 - opacity) * background``.
    Returns:
        dict with ``color`` (R, C), ``depth`` (R,) = sum w t, ``opacity`` (R,) in [0, 1],
        ``weights`` (R, S), ``transmittance`` (R, S) = T_i (light reaching sample i),
        ``alphas`` (R, S) and ``optical_depth`` (R,) = sum tau (opacity = 1 - exp(-it); it keeps
        a gradient where the opacity has saturated to 1 in floating point).
    """
    if (sigmas is None) == (alphas is None):
        raise ValueError("composite needs exactly one of sigmas or alphas")
    if sigmas is not None:
        if deltas is None:
            deltas = sample_deltas(t, last_delta)
        tau = sigmas * deltas
        alpha = opacity_from_optical_depth(tau)
        log_t = -_exclusive_cumsum(tau)
        optical_depth = tau.sum(dim=-1)
        opacity = opacity_from_optical_depth(optical_depth)
    else:
        alpha = alphas
        eps = torch.finfo(alphas.dtype).eps
        log_pass = torch.log1p(-alphas.clamp(0.0, 1.0 - eps))
        log_t = _exclusive_cumsum(log_pass)
        optical_depth = -log_pass.sum(dim=-1)
        opacity = -torch.expm1(-optical_depth)
    trans = torch.exp(log_t)
    weights = trans * alpha
    color = (weights[..., None] * colors).sum(dim=-2)
    if background is not None:
        bg = torch.as_tensor(background, dtype=color.dtype, device=color.device)
        color = color + (1.0 - opacity)[..., None] * bg
    depth = (weights * t).sum(dim=-1)
    return {"color": color, "depth": depth, "opacity": opacity, "weights": weights,
            "transmittance": trans, "alphas": alpha, "optical_depth": optical_depth}


def render_rays_chunked(fn: Callable[[torch.Tensor, torch.Tensor], Dict[str, torch.Tensor]],
                        origins: torch.Tensor, dirs: torch.Tensor, chunk: int = 8192
                        ) -> Dict[str, torch.Tensor]:
    """Call ``fn(origins (n, 3), dirs (n, 3)) -> {key: (n, ...)}`` on chunks of ``chunk`` rays.

    ``origins``/``dirs`` may have any leading shape (..., 3); every output is concatenated
    and reshaped to (..., *rest). Memory is bounded by ``chunk`` whatever the image size
    (call under ``torch.no_grad()`` for inference).
    """
    if chunk < 1:
        raise UserError(f"chunk must be >= 1, got {chunk}")
    lead = origins.shape[:-1]
    o, d = origins.reshape(-1, 3), dirs.reshape(-1, 3)
    parts: Dict[str, list] = {}
    for start in range(0, o.shape[0], chunk):
        out = fn(o[start:start + chunk], d[start:start + chunk])
        for k, v in out.items():
            parts.setdefault(k, []).append(v)
    return {k: torch.cat(v, dim=0).reshape(*lead, *v[0].shape[1:]) for k, v in parts.items()}


Field = Callable[[torch.Tensor, torch.Tensor], tuple]


@RENDERERS.register("volume")
class VolumeRenderer:
    """Render a radiance field seen by :class:`Cameras` with stratified samples.

    ``field(points (N, 3), dirs (N, 3)) -> (sigma (N,), rgb (N, C))``; with
    ``mode="alpha"`` the first output is a per-sample opacity in [0, 1] instead of a density.

    Args:
        n_samples: samples per ray (S).
        near, far: sample range, world units along the unit ray directions.
        chunk: rays per field call (bounds memory).
        background: None (black) or an RGB triple in [0, 1].
        perturb: jitter samples in their bins (needs a generator at call time).
        mode: "density" or "alpha".
    """

    def __init__(self, n_samples: int = 64, near: float = 0.0, far: float = 5.0, chunk: int = 8192,
                 background: Background = None, perturb: bool = False, mode: str = "density"):
        if mode not in ("density", "alpha"):
            raise UserError(f"mode must be 'density' or 'alpha', got {mode!r}")
        self.n_samples, self.near, self.far = int(n_samples), float(near), float(far)
        self.chunk, self.background, self.perturb, self.mode = int(chunk), background, bool(perturb), mode

    def render_rays(self, field: Field, origins: torch.Tensor, dirs: torch.Tensor,
                    generator: Optional[torch.Generator] = None) -> Dict[str, torch.Tensor]:
        """origins, dirs (R, 3), unit dirs -> composite() outputs for those rays."""
        t = stratified_samples(self.near, self.far, self.n_samples, n_rays=origins.shape[0],
                               perturb=self.perturb, generator=generator,
                               dtype=origins.dtype, device=origins.device)
        points = origins[:, None, :] + t[..., None] * dirs[:, None, :]
        first, rgb = field(points.reshape(-1, 3), dirs[:, None, :].expand_as(points).reshape(-1, 3))
        first = first.reshape(t.shape)
        rgb = rgb.reshape(*t.shape, -1)
        key = "sigmas" if self.mode == "density" else "alphas"
        return composite(rgb, t, background=self.background, **{key: first})

    def __call__(self, field: Field, cams: Cameras, generator: Optional[torch.Generator] = None
                 ) -> Dict[str, torch.Tensor]:
        """image (B, H, W, C), depth (B, H, W), opacity (B, H, W) for every pixel centre."""
        origins, dirs = camera_rays(cams, normalize=True)
        out = render_rays_chunked(lambda o, d: {k: v for k, v in self.render_rays(field, o, d, generator).items()
                                                if k in ("color", "depth", "opacity")},
                                  origins, dirs, self.chunk)
        return {"image": out["color"], "depth": out["depth"], "opacity": out["opacity"]}
