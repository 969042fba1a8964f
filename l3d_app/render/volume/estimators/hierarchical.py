"""NeRF's hierarchical sampling with two networks: a coarse network, trained with its own colour loss,
places the fine network's samples."""

from __future__ import annotations

from typing import Callable, Optional

import torch

from l3d_app.errors import UserError
from l3d_app.registry import SAMPLERS
from l3d_app.render.volume.estimators.base import Box, Samples, segment_ends
from l3d_app.render.volume.estimators.stratified import StratifiedEstimator
from l3d_app.render.volume.renderer import composite
from l3d_app.render.volume.rendering import pack_samples
from l3d_app.render.volume.samplers import importance_samples


@SAMPLERS.register("hierarchical")
class HierarchicalEstimator(StratifiedEstimator):
    """Coarse and fine networks (Mildenhall et al., NeRF, section 5.2; the course's NeRF).

    Each call renders ``n_samples`` stratified samples per ray with the COARSE network (its own
    parameters, built by :meth:`attach_fields` with the fine network's architecture); the coarse
    compositing weights, detached, are a piecewise-constant pdf over the bins around those samples
    from which ``n_fine`` more distances are drawn by inverse CDF
    (:func:`~l3d_app.render.volume.samplers.importance_samples`). The returned samples, for the FINE
    network (the task's field), are the union: ``n_samples + n_fine`` sorted distances per ray.
    While gradients are enabled (a training step) the coarse pass keeps its colour, and
    :meth:`training_loss` returns ``coarse_weight * mean((coarse colour - target)^2)``, the coarse
    term of the paper's loss; in evaluation renders (no grad) only the coarse density is computed.

    Args:
        scene_box / near, far: the rays' interval (see :class:`StratifiedEstimator`).
        n_samples: coarse samples per ray (N_c; the paper: 64).
        n_fine: fine samples per ray drawn from the coarse weights (N_f; the paper: 128).
        padding: added to every coarse weight before the draw (no bin has zero mass).
        coarse_weight: weight of the coarse colour loss (the paper: 1).
    """

    def __init__(self, scene_box: Optional[Box] = None, n_samples: int = 64, n_fine: int = 128,
                 padding: float = 1e-5, coarse_weight: float = 1.0, near: Optional[float] = None,
                 far: Optional[float] = None, min_t: float = 0.0):
        super().__init__(n_samples, scene_box=scene_box, near=near, far=far, min_t=min_t)
        if int(n_fine) < 1 or float(coarse_weight) < 0:
            raise UserError(f"n_fine must be >= 1 and coarse_weight >= 0, got {n_fine}, {coarse_weight}")
        self.n_fine, self.padding, self.coarse_weight = int(n_fine), float(padding), float(coarse_weight)
        self.coarse: Optional[torch.nn.Module] = None
        self._coarse_color: Optional[torch.Tensor] = None
        self._coarse_mse = float("nan")

    def attach_fields(self, build_field: Callable[[], torch.nn.Module]) -> None:
        """Build the coarse network (``build_field()``: a new, independently initialised field with the
        fine network's architecture); its parameters are this estimator's, trained with the task's."""
        self.coarse = build_field()

    def coarse_pass(self, origins: torch.Tensor, dirs: torch.Tensor, perturb: bool = False,
                    generator: Optional[torch.Generator] = None, background=None):
        """(t (R, N_c), far (R,), hit (R,), weights (R, N_c), colour (R, 3) or None without grad) of the
        coarse network along unit rays ``origins``, ``dirs`` (R, 3); rays that miss the box weigh nothing."""
        if self.coarse is None:
            raise ValueError("the hierarchical estimator has no coarse network: call attach_fields(build_field)")
        near, far, hit = self.bounds(origins, dirs)
        t_c, ends, _ = self.dense(origins, dirs, perturb, generator)
        pts = origins[:, None, :] + t_c[..., None] * dirs[:, None, :]
        if torch.is_grad_enabled():
            sigma, rgb = self.coarse(pts.reshape(-1, 3), dirs[:, None, :].expand_as(pts).reshape(-1, 3))
            out = composite(rgb.reshape(*t_c.shape, -1), t_c, sigmas=sigma.reshape(t_c.shape) * hit[:, None],
                            deltas=ends - t_c, background=background)
            return t_c, near, far, hit, out["weights"], out["color"]
        sigma = self.coarse.density(pts.reshape(-1, 3)).reshape(t_c.shape) * hit[:, None]
        w = composite(torch.zeros_like(t_c)[..., None], t_c, sigmas=sigma, deltas=ends - t_c)["weights"]
        return t_c, near, far, hit, w, None

    def sampling(self, origins: torch.Tensor, dirs: torch.Tensor, *, perturb: bool = False,
                 generator: Optional[torch.Generator] = None, background=None, **field_kw) -> Samples:
        t_c, near, far, hit, w, color = self.coarse_pass(origins, dirs, perturb, generator, background)
        self._coarse_color = color
        t = importance_samples(t_c, w.detach(), self.n_fine, perturb=perturb, generator=generator,
                               padding=self.padding, near=near, far=far)
        return pack_samples(t, segment_ends(t, far), hit[:, None].expand_as(t))

    def training_loss(self, target: torch.Tensor) -> Optional[torch.Tensor]:
        """The coarse colour loss of the last training render against ``target`` (R, 3) (None after an
        evaluation render); read once."""
        color, self._coarse_color = self._coarse_color, None
        if color is None:
            return None
        mse = (color - target).square().mean()
        self._coarse_mse = float(mse.detach())
        return self.coarse_weight * mse

    def stats(self) -> dict:
        """Coarse samples per ray and the coarse network's colour MSE on the last training batch."""
        return {"coarse_samples_per_ray": float(self.n_samples), "coarse_train_mse": self._coarse_mse}
