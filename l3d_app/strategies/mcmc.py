"""``strategy=mcmc``: 3DGS as Markov-chain Monte Carlo (Kheradmand et al. 2024, "3D Gaussian
Splatting as Markov Chain Monte Carlo"), in the form gsplat's ``MCMCStrategy`` uses.

* **Relocation.** Every ``every`` steps in ``(start, until)``, splats with opacity
  ``<= min_opacity`` ("dead") are moved onto live ones drawn with probability proportional
  to opacity. A live splat drawn ``k - 1`` times is shared by ``k`` copies whose opacity
  ``1 - (1 - o)^(1/k)`` and scale (the paper's binomial correction, :func:`relocation`)
  keep the rendered distribution of the original; their Adam moments are zeroed.
* **Growth to a fixed budget.** At the same steps, ``grow_rate`` x N more splats (never past
  ``cap_max``) are added by the same opacity-proportional draw and split.
* **Noise.** After every step, each mean moves by ``Sigma n lr_means noise_lr`` with ``n``
  standard normal, ``Sigma`` the splat's covariance, gated by ``sigmoid(100 (1 - o - 0.995))``
  so that only nearly transparent splats wander (an SGLD step of the paper).
* **Regularisers.** ``opacity_reg * mean(opacity) + scale_reg * mean(scales)`` is added to
  the loss (:meth:`MCMCStrategy.regularization`), pushing unneeded splats to die.
"""

from __future__ import annotations

import math
from typing import Any, Dict, Optional

import torch

from l3d_app.errors import UserError
from l3d_app.models.gaussians import PARAM_NAMES
from l3d_app.registry import STRATEGIES
from l3d_app.render.gaussians.rasterize import quaternion_to_rotation
from l3d_app.runtime.horizon import scheduled_event
from l3d_app.runtime.random import rand, randn
from l3d_app.strategies.base import Strategy
from l3d_app.strategies.ops import append_rows, zero_moments

N_MAX = 51          # gsplat: the relocation correction is tabulated for up to 51 copies of one splat
OPACITY_EPS = 1e-4  # relocated opacities stay in [min_opacity, 1 - eps]


def _relocation_table(n_max: int = N_MAX) -> torch.Tensor:
    """(n_max + 1, n_max) float64: row k holds a_k[j] = sum_{i=j+1..k} C(i-1, j) (-1)^j / sqrt(j+1)
    so that the paper's denominator for k copies is sum_j a_k[j] o_new^(j+1)."""
    i = torch.arange(1, n_max + 1, dtype=torch.float64)[:, None]                  # (n, 1)
    j = torch.arange(n_max, dtype=torch.float64)[None, :]                          # (1, n)
    logc = torch.lgamma(i) - torch.lgamma(j + 1) - torch.lgamma((i - j).clamp_min(1))
    term = torch.where(j <= i - 1, torch.exp(logc), torch.zeros(())) * (-1.0) ** j / torch.sqrt(j + 1)
    return torch.cat([torch.zeros(1, n_max, dtype=torch.float64), torch.cumsum(term, 0)])


_TABLE = _relocation_table()


def relocation(opacity: torch.Tensor, scale: torch.Tensor, copies: torch.Tensor):
    """Opacity and scale of each of ``copies`` (M,) >= 1 splats sharing one original.

    opacity (M,) in (0, 1), scale (M, S) world units. Returns (new_opacity (M,), new_scale
    (M, S)): ``o' = 1 - (1 - o)^(1/k)``, ``s' = o / (sum_{i=1..k} sum_{j<i} C(i-1, j)
    (-1)^j o'^(j+1) / sqrt(j+1)) * s``; ``k = 1`` leaves both unchanged.
    """
    k = copies.clamp(1, N_MAX).long()
    o = opacity.to(torch.float64)
    new_o = 1.0 - (1.0 - o) ** (1.0 / k.to(torch.float64))
    powers = new_o[:, None] ** torch.arange(1, N_MAX + 1, dtype=torch.float64, device=o.device)
    denom = (_TABLE.to(o.device)[k] * powers).sum(-1)
    coeff = (o / denom).to(scale.dtype)
    return new_o.to(opacity.dtype), coeff[:, None] * scale


@STRATEGIES.register("mcmc")
class MCMCStrategy(Strategy):
    """3DGS-MCMC (see the module docstring). Steps are 1-based counts, as in ``default``."""

    def __init__(self, cap_max: int = 20_000, start: int = 500, until: int = 25_000, every: int = 100,
                 min_opacity: float = 0.005, grow_rate: float = 0.05, noise_lr: float = 5e5,
                 opacity_reg: float = 0.01, scale_reg: float = 0.01):
        super().__init__()
        if int(every) <= 0 or int(cap_max) <= 0:
            raise UserError(f"strategy.every and strategy.cap_max must be > 0, got {every}, {cap_max}")
        self.cap_max, self.start, self.until, self.every = int(cap_max), int(start), int(until), int(every)
        self.min_opacity, self.grow_rate, self.noise_lr = float(min_opacity), float(grow_rate), float(noise_lr)
        self.opacity_reg, self.scale_reg = float(opacity_reg), float(scale_reg)

    def regularization(self, model) -> Optional[torch.Tensor]:
        terms = []
        if self.opacity_reg > 0:
            terms.append(self.opacity_reg * torch.sigmoid(model.opacity_logits).mean())
        if self.scale_reg > 0:
            terms.append(self.scale_reg * torch.exp(model.log_scales).mean())
        return sum(terms) if terms else None

    def step_post_backward(self, model, optimizer, step: int, info: Dict[str, Any],
                           generator: Optional[torch.Generator] = None) -> Dict[str, float]:
        previous, done = self.schedule(step, info)     # (step, step + 1) unless the task's schedule says otherwise
        logs: Dict[str, float] = {}
        if scheduled_event(previous, done, self.every, first=self.start + 1, last=self.until - 1):
            logs["relocated"] = float(self.relocate(model, optimizer, generator))
            logs["added"] = float(self.grow(model, optimizer, generator))
            logs["n"] = float(model.num)
        self.add_noise(model, optimizer, generator)
        return logs

    # -- the operations ------------------------------------------------------------------------
    @staticmethod
    def _draw(weights: torch.Tensor, n: int, generator) -> torch.Tensor:
        """``n`` indices drawn with replacement, probability proportional to ``weights`` (M,) >= 0
        (inverse CDF of one uniform draw per sample from the run's generator)."""
        cdf = torch.cumsum(weights.to(torch.float64), 0)
        u = rand((n,), generator, weights.device, torch.float64) * cdf[-1]
        return torch.searchsorted(cdf, u, right=True).clamp_max(weights.shape[0] - 1)

    @torch.no_grad()
    def _share(self, model, optimizer, sampled: torch.Tensor) -> None:
        """Give each drawn original (indices, repeats allowed) the opacity/scale of one of its copies."""
        counts = torch.bincount(sampled, minlength=model.num)[sampled] + 1
        opac = torch.sigmoid(model.opacity_logits[sampled])
        new_o, new_s = relocation(opac, torch.exp(model.log_scales[sampled]), counts)
        new_o = new_o.clamp(self.min_opacity, 1.0 - OPACITY_EPS)
        model.opacity_logits.data[sampled] = torch.log(new_o / (1 - new_o))
        model.log_scales.data[sampled] = torch.log(new_s)
        for name in PARAM_NAMES:
            zero_moments(optimizer, getattr(model, name), sampled)

    @torch.no_grad()
    def relocate(self, model, optimizer, generator) -> int:
        """Move dead splats onto live ones; returns how many moved."""
        opac = torch.sigmoid(model.opacity_logits)
        dead = opac <= self.min_opacity
        n_dead, alive = int(dead.sum()), torch.nonzero(~dead).reshape(-1)
        if n_dead == 0 or alive.numel() == 0:
            return 0
        sampled = alive[self._draw(opac[alive], n_dead, generator)]
        self._share(model, optimizer, sampled)
        dead_idx = torch.nonzero(dead).reshape(-1)
        for name in PARAM_NAMES:
            p = getattr(model, name)
            p.data[dead_idx] = p.data[sampled]
            zero_moments(optimizer, p, dead_idx)
        return n_dead

    @torch.no_grad()
    def grow(self, model, optimizer, generator) -> int:
        """Add ``grow_rate`` x N splats (up to ``cap_max``) as copies of opacity-drawn ones."""
        n_new = max(0, min(self.cap_max, int(math.floor((1.0 + self.grow_rate) * model.num))) - model.num)
        if n_new == 0:
            return 0
        opac = torch.sigmoid(model.opacity_logits)
        sampled = self._draw(opac, n_new, generator)
        self._share(model, optimizer, sampled)
        append_rows(model, optimizer, {name: getattr(model, name).data[sampled] for name in PARAM_NAMES})
        return n_new

    @torch.no_grad()
    def add_noise(self, model, optimizer, generator) -> None:
        """Opacity-gated noise on the means, shaped by each splat's covariance and the means' LR."""
        lr = next((g["lr"] for g in optimizer.param_groups if g.get("name") == "means"),
                  optimizer.param_groups[0]["lr"])
        opac = torch.sigmoid(model.opacity_logits)
        gate = torch.sigmoid(100.0 * ((1.0 - opac) - 0.995))
        R = quaternion_to_rotation(model.quats)
        s2 = torch.exp(2.0 * model.log_scales).expand(-1, 3)
        cov = (R * s2[:, None, :]) @ R.transpose(-1, -2)                                    # R S^2 R^T
        n = randn((model.num, 3), generator, model.means.device) * (gate * lr * self.noise_lr)[:, None]
        model.means.data += (cov @ n[..., None])[..., 0]
