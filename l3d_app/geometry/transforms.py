"""Rotations: Euler angles and axis rotations as (3, 3) matrices (column-vector convention)."""

from __future__ import annotations

import math
from typing import Sequence

import torch

from l3d_app.errors import UserError


def axis_rotation(axis: str, degrees: float, dtype=torch.float32) -> torch.Tensor:
    """(3, 3) right-handed rotation by ``degrees`` about the world axis 'x', 'y' or 'z'."""
    a = math.radians(float(degrees))
    c, s = math.cos(a), math.sin(a)
    mats = {
        "x": [[1, 0, 0], [0, c, -s], [0, s, c]],
        "y": [[c, 0, s], [0, 1, 0], [-s, 0, c]],
        "z": [[c, -s, 0], [s, c, 0], [0, 0, 1]],
    }
    if axis not in mats:
        raise UserError(f"axis must be x, y or z, got {axis!r}")
    return torch.tensor(mats[axis], dtype=dtype)


def euler_xyz(degrees: Sequence[float], dtype=torch.float32) -> torch.Tensor:
    """(3, 3) rotation ``Rz(c) @ Ry(b) @ Rx(a)`` for angles (a, b, c) in degrees
    (rotate about x first, then y, then z; fixed world axes)."""
    a, b, c = (float(v) for v in degrees)
    return axis_rotation("z", c, dtype) @ axis_rotation("y", b, dtype) @ axis_rotation("x", a, dtype)
