"""Scores of a reconstructed surface against the true one: chamfer and F-score, on the whole
true surface and on the part the input cameras observe.

Definitions (world units; ``P`` = ``n`` area-uniform samples of the prediction, ``G`` = ``n``
of the truth, distances EXACT point-to-mesh (:mod:`~l3d_app.geometry.point_mesh_distance`),
so there is no sampling floor):

- accuracy ``acc(p) = d(p, true mesh)``, completeness ``comp(g) = d(g, predicted mesh)``
  (``accuracy_distance`` / ``completeness_distance``: their means);
- ``chamfer = mean_P acc + mean_G comp``; ``precision`` / ``recall`` = fraction of ``P`` / ``G``
  within ``threshold``, ``f1`` their harmonic mean;
- ``*_observed``: the same restricted to what the cameras see (:mod:`~l3d_app.metrics.observed`):
  ``G`` to its observed samples (seen by at least one camera, facing it), ``P`` to the samples
  whose nearest true sample is observed (a guess about unseen surface, e.g. under a stand,
  is not scored; a floater in front of seen surface is). ``observed_fraction`` = the share
  of the true surface's area that is observed.

``chamfer_rel_diag`` (and ``chamfer_observed_rel_diag``) divide by the true mesh's
bounding-box diagonal.
"""

from __future__ import annotations

from typing import Dict, Optional

import torch

from l3d_app.geometry.cameras import Cameras
from l3d_app.geometry.mesh import Mesh
from l3d_app.geometry.sampling import sample_surface
from l3d_app.metrics.chamfer import nearest_neighbors
from l3d_app.geometry.point_mesh_distance import point_mesh_distance
from l3d_app.metrics.observed import observed_mask


def _prf(acc: torch.Tensor, comp: torch.Tensor, threshold: float) -> Dict[str, float]:
    p = float((acc <= threshold).double().mean()) if acc.numel() else 0.0
    r = float((comp <= threshold).double().mean()) if comp.numel() else 0.0
    return {"precision": p, "recall": r, "f1": 0.0 if p + r == 0 else 2 * p * r / (p + r)}


@torch.no_grad()
def surface_scores(pred: Mesh, truth: Mesh, cameras: Optional[Cameras] = None, n: int = 10000,
                   threshold: float = 0.05, seed: int = 0, depth_maps: Optional[torch.Tensor] = None,
                   tolerance: float = 0.01) -> Dict[str, float]:
    """Chamfer / F-score of mesh ``pred`` against mesh ``truth`` (see the module docstring);
    with ``cameras`` (the input views) and ``depth_maps`` (B, h, w), the true surface's depth
    seen by them (:func:`l3d_app.render.mesh.rgbd.true_depth_maps`, e.g. at 4x their resolution),
    also the observed-surface variants (``cameras`` without ``depth_maps`` is a ValueError:
    metrics do not render). CPU, float64.
    """
    if (cameras is None) != (depth_maps is None):
        raise ValueError("surface_scores: pass both cameras and depth_maps (render.rgbd.true_depth_maps) or neither")
    pred, truth = pred.to("cpu"), truth.to("cpu")
    gen = torch.Generator().manual_seed(int(seed))
    ps = sample_surface(pred, int(n), generator=gen).points
    gs = sample_surface(truth, int(n), generator=gen)
    acc = point_mesh_distance(ps, truth).distance
    comp = point_mesh_distance(gs.points, pred).distance
    diag = float((truth.verts.max(0).values - truth.verts.min(0).values).norm())
    out = {"chamfer": float(acc.mean() + comp.mean()), "accuracy_distance": float(acc.mean()),
           "completeness_distance": float(comp.mean()), **_prf(acc, comp, threshold)}
    out["chamfer_rel_diag"] = out["chamfer"] / diag
    if cameras is not None:
        cams = cameras.to("cpu")
        depth = depth_maps.to("cpu")
        normals = truth.face_normals()[gs.face_index]
        seen_g = observed_mask(gs.points, cams, depth, float(tolerance), normals=normals)
        seen_p = seen_g[nearest_neighbors(ps, gs.points)]
        a, c = acc[seen_p], comp[seen_g]
        obs = {"chamfer": float(a.mean() + c.mean()) if a.numel() and c.numel() else float("nan"),
               **_prf(a, c, threshold)}
        out.update({f"{k}_observed": v for k, v in obs.items()})
        out["chamfer_observed_rel_diag"] = out["chamfer_observed"] / diag
        out["observed_fraction"] = float(seen_g.double().mean())
    return out
