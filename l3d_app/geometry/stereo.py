"""Rectified stereo: disparity <-> depth, and how disparity errors become depth errors.

For a rectified pair with focal length ``f`` (pixels) and baseline ``B`` (world units), a
point at depth ``Z`` (world units, along the optical axis) has disparity ``d = f B / Z``
(pixels), and conversely ``Z = f B / d``.

Invalid values are handled explicitly, never as NaN:

- a disparity that is not finite and positive (``d <= 0``, NaN or inf) has no finite
  depth: its depth is ``+inf`` (``d = 0`` is a point at infinity; negative or NaN
  disparities are matcher failures, reported the same way). Use ``torch.isfinite`` on the
  depth, or ``return_valid=True``, to mask them;
- a depth that is not finite and positive (``Z <= 0``, NaN, ``+inf``) maps to disparity
  ``0``: a point at infinity for ``+inf``, and the "no match" code for the others, so that
  ``disparity_to_depth`` gives ``+inf`` back.

Gradients are finite everywhere (zero at invalid entries).
"""

from __future__ import annotations

from typing import Tuple, Union

import torch

from l3d_app.errors import UserError

Scalar = Union[float, torch.Tensor]


def _check_positive(name: str, value: Scalar) -> None:
    t = torch.as_tensor(value)
    if not bool(torch.isfinite(t).all()) or not bool((t > 0).all()):
        raise UserError(f"{name} must be finite and > 0, got {value}")


def _as_float(x) -> torch.Tensor:
    """A float tensor view of ``x`` (python numbers and integer tensors become floats)."""
    x = torch.as_tensor(x)
    return x if x.is_floating_point() else x.to(torch.get_default_dtype())


def _reciprocal_scaled(x: torch.Tensor, fb: Scalar, fill: float) -> Tuple[torch.Tensor, torch.Tensor]:
    """``fb / x`` where ``x`` is finite and > 0, ``fill`` elsewhere; also the validity mask."""
    valid = torch.isfinite(x) & (x > 0)
    safe = torch.where(valid, x, torch.ones_like(x))  # keeps NaN out of values and gradients
    out = torch.where(valid, fb / safe, torch.full_like(x, fill))
    return out, valid


def disparity_to_depth(disparity: torch.Tensor, focal_px: Scalar, baseline: Scalar,
                       return_valid: bool = False):
    """Depth from disparity, ``Z = f B / d``.

    Args:
        disparity: (...) disparities in pixels.
        focal_px: focal length ``f`` in pixels (> 0; a float or a tensor broadcastable to
            ``disparity``).
        baseline: baseline ``B`` in world units (> 0; float or broadcastable tensor).
        return_valid: also return the (...) bool mask of finite, positive disparities.
    Returns:
        (...) depth in the units of ``baseline``; ``+inf`` where the disparity is not finite
        and positive. With ``return_valid``: ``(depth, valid)``.
    """
    _check_positive("focal_px", focal_px)
    _check_positive("baseline", baseline)
    depth, valid = _reciprocal_scaled(_as_float(disparity), focal_px * baseline, float("inf"))
    return (depth, valid) if return_valid else depth


def depth_to_disparity(depth: torch.Tensor, focal_px: Scalar, baseline: Scalar,
                       return_valid: bool = False):
    """Disparity from depth, ``d = f B / Z``.

    Args:
        depth: (...) depths in world units (the units of ``baseline``).
        focal_px: focal length in pixels (> 0).
        baseline: baseline in world units (> 0).
        return_valid: also return the (...) bool mask of finite, positive depths.
    Returns:
        (...) disparity in pixels; ``0`` where the depth is not finite and positive
        (``+inf`` depth is exactly disparity 0). With ``return_valid``: ``(disparity, valid)``.
    """
    _check_positive("focal_px", focal_px)
    _check_positive("baseline", baseline)
    disparity, valid = _reciprocal_scaled(_as_float(depth), focal_px * baseline, 0.0)
    return (disparity, valid) if return_valid else disparity


def depth_error_from_disparity_error(depth: torch.Tensor, focal_px: Scalar, baseline: Scalar,
                                     disparity_error: Scalar, exact: bool = False) -> torch.Tensor:
    """Depth error caused by an error ``dd`` in the measured disparity.

    Sign convention: the measured disparity is ``d - dd`` where ``d = f B / Z`` is the true
    one, so a positive ``dd`` (disparity under-estimated) gives a positive depth error.

    - first order (default): ``dZ = Z^2 / (f B) * dd`` -- quadratic in depth, linear in
      ``dd``, inverse in focal length and baseline;
    - ``exact=True``: ``dZ = f B / (d - dd) - Z``; ``+inf`` where ``d - dd <= 0`` (the
      measured disparity puts the point at or beyond infinity).

    Args:
        depth: (...) true depth ``Z`` in world units; entries that are not finite and
            > 0 give ``+inf`` (no NaN).
        focal_px: focal length in pixels (> 0).
        baseline: baseline in world units (> 0).
        disparity_error: ``dd`` in pixels, a float or a tensor broadcastable to ``depth``.
        exact: use the exact formula instead of the first-order one.
    Returns:
        (...) depth error in world units.
    """
    _check_positive("focal_px", focal_px)
    _check_positive("baseline", baseline)
    depth = _as_float(depth)
    dd = torch.as_tensor(disparity_error, dtype=depth.dtype, device=depth.device)
    valid = torch.isfinite(depth) & (depth > 0)
    z = torch.where(valid, depth, torch.ones_like(depth))  # safe stand-in at invalid entries
    if exact:
        error = disparity_to_depth(focal_px * baseline / z - dd, focal_px, baseline) - z
    else:
        error = z.square() / (focal_px * baseline) * dd
    return torch.where(valid, error, torch.full_like(error, float("inf")))
