"""Occupancy-grid estimator: stratified samples, those in empty cells dropped (Instant-NGP / nerfacc)."""

from __future__ import annotations

from typing import Optional, Sequence, Tuple

import torch

from l3d_app.registry import SAMPLERS
from l3d_app.render.volume.estimators.stratified import StratifiedEstimator
from l3d_app.render.volume.estimators.base import Samples
from l3d_app.render.volume.occupancy import OccupancyGrid
from l3d_app.render.volume.rendering import pack_samples


@SAMPLERS.register("occupancy")
class OccupancyEstimator(StratifiedEstimator):
    """Stratified samples inside ``scene_box`` kept only in occupied cells of an
    :class:`~l3d_app.render.volume.occupancy.OccupancyGrid` (its knobs below). Dropping a sample is
    exact for a field that is empty there: its optical depth would be 0.

    ``update(step, field)`` refreshes the grid from ``field.density`` every ``update_every``
    steps (before step ``step`` when ``step`` is a multiple of it), all cells occupied before
    ``warmup_steps``; ``init_from_field=True`` fills it from the field at construction time of
    the first update (e.g. a density blob to start from).
    """

    def __init__(self, scene_box: Tuple[Sequence[float], Sequence[float]], n_samples: int = 96,
                 resolution: int = 64, threshold: float = 1.0, decay: float = 0.95, warmup_steps: int = 48,
                 update_every: int = 16, init_from_field: bool = False, min_t: float = 0.0):
        super().__init__(n_samples, scene_box=scene_box, min_t=min_t)
        self.grid = OccupancyGrid(scene_box, resolution=resolution, threshold=threshold, decay=decay,
                                  warmup_steps=warmup_steps, update_every=update_every)
        self.init_from_field = bool(init_from_field)

    def _update(self, step: int, field, generator, force: bool) -> None:
        if force or (self.init_from_field and step == 0):
            self.grid.update(field.density, step, generator, force=True)
        elif step > 0:       # the grid's own counter: "after step - 1"
            self.grid.update(field.density, step - 1, generator)

    def sampling(self, origins: torch.Tensor, dirs: torch.Tensor, *, perturb: bool = False,
                 generator: Optional[torch.Generator] = None, **field_kw) -> Samples:
        t, t_end, hit = self.dense(origins, dirs, perturb, generator)
        points = origins[:, None, :] + t[..., None] * dirs[:, None, :]
        keep = hit[:, None].expand_as(t) & self.grid.occupied(points.reshape(-1, 3)).reshape(t.shape)
        return pack_samples(t, t_end, keep)

    def stats(self) -> dict:
        return {"occupied_fraction": self.grid.occupied_fraction}
