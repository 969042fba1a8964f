"""The estimator interface and the ray-interval helper every estimator shares."""

from __future__ import annotations

from typing import Callable, Optional, Sequence, Tuple

import torch

from l3d_app.errors import UserError
from l3d_app.render.volume.samplers import ray_aabb

Box = Tuple[Sequence[float], Sequence[float]]
Samples = Tuple[torch.Tensor, torch.Tensor, torch.Tensor]


class Estimator(torch.nn.Module):
    """Base class: rays bounded by a scene box (``scene_box``) or by fixed ``near`` / ``far``.

    Subclasses implement :meth:`sampling`; :meth:`update` is a no-op here. State that must
    survive a checkpoint lives in buffers (``state_dict``).
    """

    def __init__(self, scene_box: Optional[Box] = None, near: Optional[float] = None,
                 far: Optional[float] = None, min_t: float = 0.0):
        super().__init__()
        if scene_box is None and (near is None or far is None):
            raise ValueError("an estimator needs a scene_box or both near and far")
        if scene_box is None and not float(far) > float(near):
            raise UserError(f"far must be > near, got near={near}, far={far}")
        self.scene_box = None if scene_box is None else ([float(v) for v in scene_box[0]],
                                                          [float(v) for v in scene_box[1]])
        self.near, self.far, self.min_t = near, far, float(min_t)
        self._updated_at: Optional[int] = None

    def bounds(self, origins: torch.Tensor, dirs: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """near (R,), far (R,), hit (R,) bool of each ray's interval (world units, unit dirs)."""
        if self.scene_box is not None:
            return ray_aabb(origins, dirs, self.scene_box[0], self.scene_box[1], min_t=self.min_t)
        n = origins.shape[0]
        near = torch.full((n,), float(self.near), dtype=origins.dtype, device=origins.device)
        return near, torch.full_like(near, float(self.far)), torch.ones(n, dtype=torch.bool, device=origins.device)

    def update(self, step: int, field: torch.nn.Module, generator: Optional[torch.Generator] = None,
               force: bool = False) -> None:
        """Refresh learned state before step ``step`` renders (once per step; ``force``: always)."""
        if not force and self._updated_at == step:
            return
        self._updated_at = step
        self._update(step, field, generator, force)

    def _update(self, step: int, field, generator, force: bool) -> None:
        return None

    def sampling(self, origins: torch.Tensor, dirs: torch.Tensor, *, perturb: bool = False,
                 generator: Optional[torch.Generator] = None, **field_kw) -> Samples:
        """(t_starts (N,), t_ends (N,), ray_indices (N,)) for rays ``origins``, unit ``dirs`` (R, 3)."""
        raise NotImplementedError

    def stats(self) -> dict:
        """Figures worth reporting next to the error (e.g. the occupied fraction)."""
        return {}

    def attach_fields(self, build_field: Callable[[], torch.nn.Module]) -> None:
        """Build the networks this estimator owns (a proposal network) with ``build_field()``, a new
        field of the task's architecture; none here. Their parameters are the estimator's own."""
        return None

    def training_loss(self, target: torch.Tensor) -> Optional[torch.Tensor]:
        """The loss of what this estimator trains itself (a proposal network's colour against ``target``
        (R, 3) of the last training render), added to the task's; None here."""
        return None


def segment_ends(t: torch.Tensor, far: torch.Tensor) -> torch.Tensor:
    """(R, S) end of each sample's segment: the next sample, the last one ending at ``far``
    (never before its start)."""
    return torch.cat([t[:, 1:], torch.maximum(far[:, None], t[:, -1:])], dim=-1)
