"""The stereo exercise's table: for one rectified rig, the depth error a disparity error of +-dd pixels
makes at each depth, exact and to first order.

With focal length ``f`` (pixels), baseline ``B`` (metres) and true depth ``Z`` the disparity is
``d = f B / Z``; a measured disparity ``d - dd`` gives the depth ``f B / (d - dd)`` and ``d + dd`` gives
``f B / (d + dd)`` (:func:`l3d_app.geometry.stereo.depth_error_from_disparity_error`, ``exact=True``).
To first order both errors are ``+- Z^2 / (f B) * dd``. Where ``d <= dd`` the under-estimated disparity
puts the point at or beyond infinity: its error is ``+inf``.
"""

from __future__ import annotations

import math
from typing import Dict, List, Sequence

import torch

from l3d_app.geometry.stereo import depth_error_from_disparity_error, depth_to_disparity


def disparity_error_rows(focal_px: float, baseline: float, depths: Sequence[float], disparity_error: float
                         ) -> List[Dict[str, float]]:
    """One row per depth (float64): ``depth``, ``disparity`` (px), ``error_far`` (the depth error of a
    disparity ``dd`` too small: >= 0, ``inf`` past infinity), ``error_near`` (``dd`` too large: <= 0),
    ``first_order`` (``Z^2 dd / (f B)``) and ``relative`` (``first_order / Z``)."""
    z = torch.as_tensor([float(v) for v in depths], dtype=torch.float64)
    d = depth_to_disparity(z, focal_px, baseline)
    far = depth_error_from_disparity_error(z, focal_px, baseline, disparity_error, exact=True)
    near = depth_error_from_disparity_error(z, focal_px, baseline, -float(disparity_error), exact=True)
    first = depth_error_from_disparity_error(z, focal_px, baseline, disparity_error)
    return [{"depth": float(z[i]), "disparity": float(d[i]), "error_far": float(far[i]),
             "error_near": float(near[i]), "first_order": float(first[i]), "relative": float(first[i] / z[i])}
            for i in range(len(z))]


def _number(v: float) -> str:
    return "inf" if math.isinf(v) else f"{v:.4g}"


def disparity_error_markdown(rows: List[Dict[str, float]], disparity_error: float) -> str:
    """The rows of :func:`disparity_error_rows` as a markdown table (metres and pixels)."""
    dd = f"{disparity_error:g}"
    head = (f"| depth Z (m) | disparity d (px) | error at d - {dd} px (m) | error at d + {dd} px (m) | "
            f"first order Z^2 dd / (f B) (m) | relative |\n|---|---|---|---|---|---|\n")
    return head + "".join(f"| {r['depth']:g} | {r['disparity']:.4g} | +{_number(r['error_far'])} | "
                          f"{_number(r['error_near'])} | +-{r['first_order']:.4g} | {100 * r['relative']:.3g}% |\n"
                          for r in rows)
