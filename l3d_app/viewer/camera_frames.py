"""Between viser's camera (a world-from-camera quaternion ``wxyz``, a position, the vertical
field of view, the aspect) and the library's :class:`~l3d_app.geometry.cameras.Cameras`.

Viser's camera frame is OpenCV's (+X right, +Y down, +Z forward), the library's as well, so the
rotation is only transposed: ``R_world_to_cam = R(wxyz)^T``, ``t = -R_world_to_cam @ position``.
"""

from __future__ import annotations

import math
from typing import Tuple

import numpy as np
import torch

from l3d_app.geometry.cameras import Cameras


def quat_to_matrix(wxyz: np.ndarray) -> np.ndarray:
    """(3, 3) rotation of the unit quaternion ``wxyz`` (normalised here)."""
    w, x, y, z = np.asarray(wxyz, dtype=np.float64) / np.linalg.norm(wxyz)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def matrix_to_quat(R: np.ndarray) -> np.ndarray:
    """(4,) unit quaternion ``wxyz`` of the rotation ``R`` (3, 3) (Shepperd's method, w >= 0)."""
    R = np.asarray(R, dtype=np.float64)
    tr = np.trace(R)
    cands = np.array([tr, R[0, 0], R[1, 1], R[2, 2]])
    k = int(np.argmax(cands))
    if k == 0:
        s = 2.0 * math.sqrt(1.0 + tr)
        q = [0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s]
    elif k == 1:
        s = 2.0 * math.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2])
        q = [(R[2, 1] - R[1, 2]) / s, 0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s]
    elif k == 2:
        s = 2.0 * math.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2])
        q = [(R[0, 2] - R[2, 0]) / s, (R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s]
    else:
        s = 2.0 * math.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1])
        q = [(R[1, 0] - R[0, 1]) / s, (R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s]
    q = np.array(q)
    return q * (1.0 if q[0] >= 0 else -1.0) / np.linalg.norm(q)


def viser_to_cameras(wxyz, position, fov_y: float, aspect: float, width: int) -> Cameras:
    """One :class:`Cameras` of ``width`` x ``round(width / aspect)`` px for a viser camera
    (``fov_y`` radians, the vertical field of view; ``aspect`` = width / height)."""
    W = int(width)
    H = max(8, int(round(W / max(float(aspect), 1e-3))))
    R = quat_to_matrix(wxyz).T
    t = -R @ np.asarray(position, dtype=np.float64)
    f = 0.5 * H / math.tan(0.5 * float(fov_y))
    return Cameras(torch.from_numpy(R).float()[None], torch.from_numpy(t).float()[None],
                   f, f, W / 2.0, H / 2.0, W, H)


def cameras_to_viser(cams: Cameras) -> Tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """(N, 4) ``wxyz``, (N, 3) positions, (N,) vertical fields of view (radians) and the aspect of ``cams``."""
    R = cams.R.detach().double().cpu().numpy()
    wxyz = np.stack([matrix_to_quat(r.T) for r in R])
    fy = cams.fy.detach().double().cpu().numpy().reshape(-1) * np.ones(len(R))
    fov = 2.0 * np.arctan(0.5 * cams.height / fy)
    return wxyz, cams.centers().detach().double().cpu().numpy(), fov, cams.width / float(cams.height)
