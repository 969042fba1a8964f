"""The course's four Gaussian-rasteriser checks (../shared/data/course_tests/gaussians_unit_vectors.json)
run against our projection code through a thin adapter for the PyTorch3D camera convention.

Adapter (test-only; the library is not changed):

* camera: ``look_at(6, 45, 75)`` places the camera exactly as PyTorch3D's
  ``look_at_view_transform`` (tested in test_cameras.py); focal 320 px, principal point
  (64, 64) px, 128 x 128. Our ``u = fx X/Z + cx`` in the OpenCV view frame equals the
  course's ``px - fx X/Z`` in the PyTorch3D view frame (+X left, +Y up), so means2D and
  the Jacobian's clamp (``+-1.3 tan(fov/2) = +-0.26`` = our ``[-0.15 W, 1.15 W]`` frustum)
  need no change.
* scales: the course's scales are raw standard deviations (``scale^2 I``), ours are logs:
  ``log_scales = log|scale|`` (the covariance depends on the sign only through ``s^2``).
* rotation in cov2D (test_2, test_4): the course uses ``W`` = the PyTorch3D ``R`` *as is*
  in ``J W Sigma W^T J^T``. With PyTorch3D's row vectors (``X_view = X_world R + T``) the
  world->view rotation of column vectors is ``R^T``, which is what our projection uses
  (and what the means in test_3 use). The course's figure is therefore the covariance of
  the Gaussian turned by ``R R`` first: ``R Sigma R^T = R^T (R R Sigma R^T R^T) R``. The
  adapter pre-rotates the quaternion by ``R R`` (scipy's Rotation, independent of our
  quaternion code) so that our code reproduces the course's numbers, and a second test
  checks our correct-convention covariance against an independent float64 ``J R^T Sigma R J^T``.
* power (test_4): at integer pixel coordinates (no +0.5), ``-0.5 d^T cov2D^-1 d``; our
  rasteriser's pixel centres are at +0.5, so the render cross-check shifts ``cx, cy`` by
  +0.5 to put pixel (0, j)'s centre at the course's coordinate (j, 0).
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from conftest import course_data
from l3d_app.geometry.cameras import Cameras, look_at, to_pytorch3d
from l3d_app.render.gaussians.rasterize import project_gaussians, rasterize_gaussians
from l3d_app.render.gaussians.project import quat_rotation

D = torch.float64
W_PX = H_PX = 128
F_PX, PX, PY = 320.0, 64.0, 64.0


@pytest.fixture(scope="module")
def course():
    data = json.loads(course_data("course_tests", "gaussians_unit_vectors.json").read_text())
    cam = data["camera"]
    assert cam["convention"] == "PyTorch3D"
    assert cam["look_at_view_transform"] == {"dist": 6.0, "elev": 45.0, "azim": 75.0}
    assert cam["PerspectiveCameras"]["focal_length"] == F_PX and cam["PerspectiveCameras"]["in_ndc"] is False
    assert cam["PerspectiveCameras"]["principal_point"] == [PX, PY]
    assert cam["PerspectiveCameras"]["image_size"] == [H_PX, W_PX]
    return data["tests"]


def _cams(shift: float = 0.0) -> Cameras:
    R, t = look_at(6.0, 45.0, 75.0, dtype=D)
    return Cameras(R, t, F_PX, F_PX, PX + shift, PY + shift, W_PX, H_PX)


def _t(x) -> torch.Tensor:
    return torch.tensor(x, dtype=D)


def _course_frame_quats(quats: torch.Tensor) -> torch.Tensor:
    """(N, 4) wxyz quaternions pre-rotated by R_p3d R_p3d (see the module docstring)."""
    R_p3d = to_pytorch3d(_cams(), in_ndc=False)[0][0].numpy()
    q = quats.numpy()
    rot = Rotation.from_matrix(R_p3d @ R_p3d) * Rotation.from_quat(q[:, [1, 2, 3, 0]])   # scipy: xyzw
    return torch.from_numpy(rot.as_quat()[:, [3, 0, 1, 2]].copy())


def _cov2d(conic: torch.Tensor) -> torch.Tensor:
    """(N, 2, 2) covariance from our conic (A, B, C) = inverse covariance entries."""
    inv = torch.stack([conic[:, 0], conic[:, 1], conic[:, 1], conic[:, 2]], -1).reshape(-1, 2, 2)
    return torch.linalg.inv(inv)


def _project(means, scales, quats):
    return project_gaussians(means, scales.abs().log(), quats, torch.full((means.shape[0],), 0.5, dtype=D), _cams())


def test_1_isotropic_cov3d(course):
    c = course["test_1"]
    scales, quats = _t(c["scales"]).expand(-1, 3), _t(c["quats"])
    _, _, _, Rq = quat_rotation(quats)                              # ours: Sigma = R S S R^T
    M = Rq * scales.abs()[:, None, :]
    cov3 = M @ M.transpose(1, 2)
    np.testing.assert_allclose(cov3.numpy(), np.array(c["gt_answer"]), atol=1e-3, rtol=0)


def test_2_anisotropic_cov2d(course):
    c = course["test_2"]
    out = _project(_t(c["means_3D"]), _t(c["scales"]), _course_frame_quats(_t(c["quats"])))
    assert out["visible"].all()
    np.testing.assert_allclose(_cov2d(out["conic"][0]).numpy(), np.array(c["gt_answer"]), rtol=1e-4, atol=0)


def test_2_cov2d_in_our_convention_against_an_independent_construction(course):
    """Unadapted quaternions: ours = J R_wc Sigma R_wc^T J^T + 0.3 I with the correct world->view
    rotation R_wc = R_p3d^T, built here from scipy's rotation and the PyTorch3D camera."""
    c = course["test_2"]
    means, scales, quats = _t(c["means_3D"]), _t(c["scales"]), _t(c["quats"])
    out = _project(means, scales, quats)
    R_p3d, T_p3d, _, _ = to_pytorch3d(_cams(), in_ndc=False)
    R_p3d, T_p3d = R_p3d[0].numpy(), T_p3d[0].numpy()
    rot = Rotation.from_quat(quats.numpy()[:, [1, 2, 3, 0]]).as_matrix()
    S = np.stack([np.diag(s) for s in scales.numpy()])
    sigma = rot @ S @ S @ rot.transpose(0, 2, 1)
    pv = means.numpy() @ R_p3d + T_p3d                                 # PyTorch3D view frame
    x, y, z = pv.T
    lim = 1.3 * (W_PX / 2) / F_PX
    xz, yz = np.clip(x / z, -lim, lim), np.clip(y / z, -lim, lim)
    J = np.zeros((len(z), 2, 3))
    J[:, 0, 0], J[:, 0, 2] = F_PX / z, -F_PX * xz / z
    J[:, 1, 1], J[:, 1, 2] = F_PX / z, -F_PX * yz / z
    ref = J @ R_p3d.T @ sigma @ R_p3d @ J.transpose(0, 2, 1) + 0.3 * np.eye(2)
    np.testing.assert_allclose(_cov2d(out["conic"][0]).numpy(), ref, rtol=1e-9, atol=0)
    # and it is NOT the course's figure (the course's W = R as is): the adapter matters
    assert not np.allclose(ref, np.array(c["gt_answer"]), rtol=1e-2)


def test_3_means2d(course):
    c = course["test_3"]
    n = len(c["means_3D"])
    out = _project(_t(c["means_3D"]), torch.ones(n, 3, dtype=D), torch.tensor([[1.0, 0, 0, 0]] * n, dtype=D))
    np.testing.assert_allclose(out["means2d"][0].numpy(), np.array(c["gt_answer"]), rtol=1e-4, atol=0)


def test_4_power_at_integer_pixels(course):
    c = course["test_4"]
    means, scales = _t(c["means_3D"]), _t(c["scales"])
    quats = _course_frame_quats(_t(c["quats"]))
    out = _project(means, scales, quats)
    A, B, C = out["conic"][0].unbind(-1)
    mu = out["means2d"][0]
    px = torch.tensor([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0]], dtype=D)          # (x, y), no +0.5
    d = px[None] - mu[:, None]                                                 # (N, 3, 2)
    power = -0.5 * (A[:, None] * d[..., 0] ** 2 + 2 * B[:, None] * d[..., 0] * d[..., 1]
                    + C[:, None] * d[..., 1] ** 2)
    gt = np.array(c["gt_answer"])
    np.testing.assert_allclose(power.numpy(), gt, rtol=1e-4, atol=0)
    # the rasteriser's own power: one splat at a time, opacity sigmoid(4), pixel centres shifted onto
    # the course's integer coordinates; only splats whose alpha clears 1/255 can be seen
    cams = _cams(shift=0.5)
    sh = torch.zeros(1, 1, 3, dtype=D)
    opacity = 1.0 / (1.0 + math.exp(-4.0))
    checked = 0
    for i in range(means.shape[0]):
        if opacity * math.exp(float(gt[i].min())) < 1.5 / 255.0:
            continue
        r = rasterize_gaussians(means[i:i + 1], scales[i:i + 1].abs().log(), quats[i:i + 1],
                                torch.full((1,), 4.0, dtype=D), sh, 0, cams)
        np.testing.assert_allclose(r["alpha"][0, 0, :3].numpy(), opacity * np.exp(gt[i]), rtol=1e-3, atol=0)
        checked += 1
    assert checked >= 2
