"""A single-view depth scanner of a procedural object, optionally in a cluttered spot: what the built-in
scans (:mod:`l3d_app.data.shape_scans`) are made of.

The object's parts and any clutter (a neighbouring object, the floor) are sampled by area at one density
(``oversample`` x ``num_points`` samples on the object), normalised so that the object's samples fill
the unit ball, and scanned: an orthographic z-buffer along the viewing direction keeps what the scanner
sees (:func:`l3d_app.geometry.partial_scan.visible_points`), so clutter in front hides the object;
optionally a disc occluder hides a further part of the view (:func:`occluded`). What the scanner keeps
is cropped to the object's bounding box widened by ``crop_margin`` on every side (clutter inside it stays,
labelled ``background``), ``num_points`` of it are drawn, centred, scaled to the unit ball and made noisy.
"""

from __future__ import annotations

from typing import List, Sequence, Tuple

import torch

from l3d_app.geometry import primitives as prim
from l3d_app.geometry.mesh import Mesh
from l3d_app.geometry.partial_scan import image_plane_basis, view_direction, visible_points
from l3d_app.geometry.sampling import sample_surface

Part = Tuple[Mesh, int]


def occluded(points: torch.Tensor, seen: torch.Tensor, direction: torch.Tensor, generator: torch.Generator,
             radius: Tuple[float, float], keep: float = 0.4) -> torch.Tensor:
    """(N,) bool: the ``seen`` (N,) samples of ``points`` (N, 3) that a disc in the image plane of a scanner
    looking along ``direction`` (3,) hides: centred on a random seen sample, radius uniform in ``radius``
    (world units), capped at the distance within which ``1 - keep`` of the seen samples lie."""
    u, v = image_plane_basis(direction.to(points))
    flat = torch.stack([points @ u, points @ v], -1)
    index = seen.nonzero()[:, 0]
    centre = flat[index[torch.randint(0, len(index), (1,), generator=generator)]]
    dist = (flat - centre).norm(dim=-1)
    r = radius[0] + (radius[1] - radius[0]) * float(torch.rand((), generator=generator, dtype=torch.float64))
    r = min(r, float(dist[index].quantile(1.0 - keep)))
    return seen & (dist < r)


def _samples(parts: Sequence[Part], count: int, generator: torch.Generator) -> Tuple[torch.Tensor, torch.Tensor]:
    """``count`` area-uniform samples (count, 3) float64 of the joined ``parts`` and their labels (count,)."""
    mesh = prim.join([m for m, _ in parts])
    face_part = torch.cat([torch.full((m.num_faces,), label, dtype=torch.int64) for m, label in parts])
    samples = sample_surface(mesh, int(count), generator)
    return samples.points.double(), face_part[samples.face_index]


def _area(parts: Sequence[Part]) -> float:
    return float(sum(float(m.face_areas().sum()) for m, _ in parts))


def scan_object(parts: List[Part], num_points: int, generator: torch.Generator, azimuth: float, elevation: float,
                oversample: int = 8, grid: int = 24, tolerance: float = 0.08, noise: float = 0.01,
                occlusion: float = 0.0, occluder_radius: Tuple[float, float] = (0.25, 0.6),
                clutter: Sequence[Part] = (), crop_margin: float = 0.15, max_clutter: float = 4.0
                ) -> Tuple[torch.Tensor, torch.Tensor, float]:
    """A noisy single-view scan of the object made of ``parts`` (see the module docstring).

    ``occlusion`` is the probability of a disc occluder, ``clutter`` meshes in the object's frame with
    their labels (at most ``max_clutter`` times the object's samples); with neither, the generator draws
    nothing for them. ``grid`` cells span the unit ball (the raster widens with the crop).

    Returns points (P, 3) float32 (centred, farthest point at distance 1, then noise), their part labels
    (P,) int64 and the share of the object's dense samples in the scan (seen, not occluded, cropped)."""
    count = int(oversample) * int(num_points)
    pts, labels = _samples(parts, count, generator)
    n_object = len(pts)
    if clutter:
        extra = min(int(round(count * _area(clutter) / max(_area(parts), 1e-12))), int(max_clutter * count))
        if extra > 0:
            more, more_labels = _samples(clutter, extra, generator)
            pts, labels = torch.cat([pts, more]), torch.cat([labels, more_labels])
    obj = pts[:n_object]
    lo, hi = obj.min(0).values, obj.max(0).values
    centre = (lo + hi) / 2
    scale = (obj - centre).norm(dim=-1).max().clamp_min(1e-12)
    pts = (pts - centre) / scale                                        # the object: unit ball
    lo, hi = (lo - centre) / scale, (hi - centre) / scale
    margin = float(crop_margin) * float((hi - lo).max())
    inside = ((pts >= lo - margin) & (pts <= hi + margin)).all(-1)
    extent = 1.0 + (margin if clutter else 0.0) * 3 ** 0.5
    direction = view_direction(azimuth, elevation).double()
    seen = visible_points(pts, direction, int(round(grid * extent)), extent, float(tolerance))
    if float(occlusion) > 0 and float(torch.rand((), generator=generator, dtype=torch.float64)) < float(occlusion):
        seen = seen & ~occluded(pts, seen & inside, direction, generator, occluder_radius)
    index = (seen & inside).nonzero()[:, 0]
    pick = torch.randperm(len(index), generator=generator)[:int(num_points)] if len(index) >= int(num_points) else \
        torch.randint(0, len(index), (int(num_points),), generator=generator)
    p, lab = pts[index[pick]], labels[index[pick]]
    lo, hi = p.min(0).values, p.max(0).values
    p = p - (lo + hi) / 2
    p = p / p.norm(dim=-1).max().clamp_min(1e-12)
    p = p + float(noise) * torch.randn(p.shape, generator=generator, dtype=p.dtype)
    return p.float(), lab, float((seen & inside)[:n_object].double().mean())
