"""Camera convention, look-at, converters and rays, against analytic values and
independent float64 re-derivations (PyTorch3D is not required: its formulas are
re-derived here in numpy).

Reference formulas (PyTorch3D, ``pytorch3d/renderer/cameras.py``):

* ``camera_position_from_spherical_angles``: ``dist * (cos e sin a, sin e, cos e cos a)``;
* ``look_at_rotation``: ``z = normalize(at - C)``, ``x = normalize(cross(up, z))``,
  ``y = normalize(cross(z, x))``, ``R = cat([x, y, z] as rows).transpose(1, 2)`` (so the
  axes are the COLUMNS of R);
* ``look_at_view_transform``: ``C = spherical + at``, ``T = -R^T C``;
* row vectors ``X_view = X_world @ R + T``; pixels ``u = px - fx X/Z``, ``v = py - fy Y/Z``
  with NDC -> pixels ``f_pix = F * s``, ``p_pix = (W/2 - C0 s, H/2 - C1 s)``, ``s = min(H, W)/2``.
"""

from __future__ import annotations

import itertools
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from l3d_app.errors import UserError
from l3d_app.geometry.cameras import (
    Cameras,
    from_opencv,
    from_opengl_c2w,
    from_pytorch3d,
    look_at,
    look_at_cameras,
    look_at_rotation,
    stack_cameras,
    to_opencv,
    to_opengl_c2w,
    to_pytorch3d,
)
from l3d_app.geometry.rays import camera_rays, pixel_axes, pixel_centers, pixels_to_directions, supersampled_rays

F64 = torch.float64
DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
TRUCK = DATA / "truck"
BOX = DATA / "box"
TRUCK_TEST_FRAMES = [33, 67, 101, 134, 168]


# --------------------------------------------------------------- references
def _normalize(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def p3d_look_at_view_transform(dist, elev, azim, at=(0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0)):
    """Independent float64 re-derivation of PyTorch3D's ``look_at_view_transform``."""
    dist, elev, azim = np.broadcast_arrays(*(np.asarray(v, dtype=np.float64).reshape(-1)
                                             for v in (dist, elev, azim)))
    at = np.asarray(at, dtype=np.float64).reshape(-1, 3)
    up = np.asarray(up, dtype=np.float64).reshape(-1, 3)
    e, a = np.deg2rad(elev), np.deg2rad(azim)
    pos = np.stack([dist * np.cos(e) * np.sin(a), dist * np.sin(e), dist * np.cos(e) * np.cos(a)], -1)
    C = pos + at
    n = max(len(C), len(at), len(up))
    C, at, up = (np.broadcast_to(v, (n, 3)) for v in (C, at, up))
    return p3d_look_at_eye(C, at, up)


def p3d_look_at_eye(C, at, up):
    """PyTorch3D ``look_at_rotation`` + ``T = -R^T C`` for explicit eyes (float64)."""
    C, at, up = (np.asarray(v, dtype=np.float64).reshape(-1, 3) for v in (C, at, up))
    z = _normalize(at - C)
    x = _normalize(np.cross(up, z))
    y = _normalize(np.cross(z, x))
    R = np.stack([x, y, z], axis=1).transpose(0, 2, 1)
    T = -np.einsum("bji,bj->bi", R, C)  # -R^T C
    return R, T


def p3d_pixels(R, T, fx, fy, px, py, X):
    """PyTorch3D projection to pixels: ``X_view = X @ R + T``; ``u = px - fx X/Z``.

    R (B,3,3), T (B,3), fx.. (B,), X (N,3) -> uv (B,N,2), Z (B,N); numpy float64.
    """
    Xv = np.einsum("nj,bjk->bnk", X, R) + T[:, None, :]
    Z = Xv[..., 2]
    u = px[:, None] - fx[:, None] * Xv[..., 0] / Z
    v = py[:, None] - fy[:, None] * Xv[..., 1] / Z
    return np.stack([u, v], -1), Z


def ndc_to_pixels(F, C, H, W):
    """README: f_pix = F * min(H, W)/2; p_pix = (W/2 - C0 s, H/2 - C1 s)."""
    F, C = np.asarray(F, np.float64).reshape(-1, 2), np.asarray(C, np.float64).reshape(-1, 2)
    s = min(H, W) / 2.0
    return F[:, 0] * s, F[:, 1] * s, W / 2.0 - C[:, 0] * s, H / 2.0 - C[:, 1] * s


def random_rotations(n: int, gen: torch.Generator) -> torch.Tensor:
    """(n, 3, 3) float64 random proper rotations from QR of Gaussian matrices."""
    A = torch.randn(n, 3, 3, generator=gen, dtype=F64)
    Q, Rr = torch.linalg.qr(A)
    Q = Q * torch.sign(torch.diagonal(Rr, dim1=-2, dim2=-1))[:, None, :]
    det = torch.linalg.det(Q)
    Q[:, :, 0] *= det.sign()[:, None]
    return Q


def random_cameras(gen, n=4, width=7, height=5) -> Cameras:
    """Random float64 cameras: QR rotations, random centres, fx != fy, off-centre pp."""
    R = random_rotations(n, gen)
    centre = torch.randn(n, 3, generator=gen, dtype=F64) * 3
    t = -(R @ centre[..., None])[..., 0]
    fx = 5 + 10 * torch.rand(n, generator=gen, dtype=F64)
    fy = fx * (0.6 + 0.8 * torch.rand(n, generator=gen, dtype=F64))
    cx = width / 2 + torch.randn(n, generator=gen, dtype=F64)
    cy = height / 2 + torch.randn(n, generator=gen, dtype=F64)
    return Cameras(R, t, fx, fy, cx, cy, width, height)


def assert_proper_rotation(R: torch.Tensor, atol: float):
    assert torch.isfinite(R).all()
    eye = torch.eye(3, dtype=R.dtype).expand_as(R)
    torch.testing.assert_close(R @ R.transpose(-1, -2), eye, atol=atol, rtol=0)
    torch.testing.assert_close(torch.linalg.det(R), torch.ones(R.shape[0], dtype=R.dtype), atol=atol, rtol=0)


def close(a, b, atol=1e-10, rtol=0.0):
    torch.testing.assert_close(torch.as_tensor(a, dtype=F64), torch.as_tensor(b, dtype=F64),
                               atol=atol, rtol=rtol)


@pytest.fixture
def gen():
    return torch.Generator().manual_seed(1234)


# ------------------------------------------------------------ look_at
def test_look_at_known_values_dist_2_7():
    # PyTorch3D: look_at_view_transform(2.7, 0, 0) -> R = diag(-1, 1, -1), T = (0, 0, 2.7).
    R_ref, T_ref = p3d_look_at_view_transform(2.7, 0.0, 0.0)
    close(R_ref[0], np.diag([-1.0, 1.0, -1.0]), atol=1e-15)
    close(T_ref[0], [0.0, 0.0, 2.7], atol=1e-15)

    R, t = look_at(2.7, 0.0, 0.0, dtype=F64)
    assert R.shape == (1, 3, 3) and t.shape == (1, 3)
    # Internal OpenCV: right = +X world, down = -Y world, forward = -Z world.
    close(R[0], np.diag([1.0, -1.0, -1.0]), atol=1e-15)
    cams = Cameras.from_fov(R, t, 60.0, 64, 48)
    close(cams.centers()[0], [0.0, 0.0, 2.7], atol=1e-14)
    Rp, Tp, _, _ = to_pytorch3d(cams)
    close(Rp[0], np.diag([-1.0, 1.0, -1.0]), atol=1e-15)
    close(Tp[0], [0.0, 0.0, 2.7], atol=1e-14)

    pts = torch.tensor([[0.0, 0, 0], [1.0, 0, 0], [0.0, 1, 0]], dtype=F64)
    uv, z = cams.project(pts)
    cx, cy = cams.cx[0].item(), cams.cy[0].item()
    close(uv[0, 0], [cx, cy], atol=1e-12)                 # origin -> principal point
    close(z[0], [2.7, 2.7, 2.7], atol=1e-14)
    assert uv[0, 1, 0] > cx + 1 and abs(uv[0, 1, 1] - cy) < 1e-12  # +X -> right
    assert uv[0, 2, 1] < cy - 1 and abs(uv[0, 2, 0] - cx) < 1e-12  # +Y -> up
    f = cams.fx[0].item()
    close(uv[0, 1], [cx + f / 2.7, cy], atol=1e-12)
    close(uv[0, 2], [cx, cy - f / 2.7], atol=1e-12)


LOOK_AT_CASES = [
    dict(dist=2.7, elev=0.0, azim=0.0),
    dict(dist=3.0, elev=30.0, azim=45.0),
    dict(dist=1.5, elev=-60.0, azim=-135.0),
    dict(dist=[1.0, 2.0, 3.0, 4.0], elev=[10.0, -20.0, 45.0, 89.0], azim=[0.0, 90.0, 180.0, 270.0]),
    dict(dist=[1.0, 2.5, 4.0], elev=15.0, azim=-30.0),            # scalar broadcast
    dict(dist=2.0, elev=20.0, azim=np.linspace(0, 360, 7)[:-1]),  # turntable
    dict(dist=2.0, elev=35.0, azim=60.0, at=(0.3, -1.2, 2.0)),    # non-origin at
    dict(dist=[2.0, 3.0], elev=[5.0, -40.0], azim=[120.0, 10.0], at=[(1.0, 2.0, 3.0), (-1.0, 0.5, 0.0)]),
    dict(dist=2.0, elev=10.0, azim=30.0, up=(0.0, 0.0, 1.0)),
    dict(dist=2.0, elev=10.0, azim=30.0, up=[(0.0, 1.0, 0.0), (0.2, 1.0, 0.1)]),  # batch via up rows
]


@pytest.mark.parametrize("case", LOOK_AT_CASES)
def test_look_at_matches_pytorch3d_reference(case):
    R_ref, T_ref = p3d_look_at_view_transform(**case)
    R, t = look_at(**case, dtype=F64)
    assert R.shape == (len(R_ref), 3, 3) and t.shape == (len(R_ref), 3)
    assert_proper_rotation(R, atol=1e-12)
    cams = Cameras.from_fov(R, t, 60.0, 32, 32)
    Rp, Tp, _, _ = to_pytorch3d(cams)
    close(Rp, R_ref, atol=1e-12)
    close(Tp, T_ref, atol=1e-12)
    # The camera centre is the documented eye.
    eye = -np.einsum("bij,bj->bi", R_ref, T_ref)  # C = -R T (R orthogonal) in row-vector form
    close(cams.centers(), eye, atol=1e-12)
    # Default float32 agrees too.
    R32, t32 = look_at(**case)
    assert R32.dtype == torch.float32
    close(R32, R, atol=2e-6)
    close(t32, t, atol=1e-5)


def test_look_at_radians_and_eye_formula():
    R_deg, t_deg = look_at(2.0, 30.0, 60.0, dtype=F64)
    R_rad, t_rad = look_at(2.0, math.radians(30.0), math.radians(60.0), degrees=False, dtype=F64)
    close(R_rad, R_deg, atol=1e-14)
    close(t_rad, t_deg, atol=1e-14)
    c = Cameras(R_deg, t_deg, 1.0, 1.0, 0.0, 0.0, 1, 1).centers()[0]
    e, a = math.radians(30.0), math.radians(60.0)
    close(c, [2 * math.cos(e) * math.sin(a), 2 * math.sin(e), 2 * math.cos(e) * math.cos(a)], atol=1e-14)


# ---------------------------------------------------- degenerate up vectors
def _documented_fallback_up(forward: np.ndarray) -> np.ndarray:
    """World axis most perpendicular to ``forward`` (ties -> first of X, Y, Z), projected."""
    a = np.abs(forward)
    idx = int(np.flatnonzero(a <= a.min() + 1e-9)[0])
    axis = np.eye(3)[idx]
    p = axis - forward * (forward @ axis)
    return p / np.linalg.norm(p)


@pytest.mark.parametrize("dtype", [torch.float32, F64])
@pytest.mark.parametrize("elev", [90.0, -90.0])
@pytest.mark.parametrize("azim", [0.0, 30.0, 90.0, 180.0, -90.0, 237.0])
def test_look_at_pole_is_finite_rotation_with_documented_fallback(dtype, elev, azim):
    at = (0.5, -0.25, 1.0)
    R, t = look_at(3.0, elev, azim, at=at, dtype=dtype)
    atol = 1e-5 if dtype == torch.float32 else 1e-12
    assert torch.isfinite(R).all() and torch.isfinite(t).all()
    assert_proper_rotation(R, atol=atol)
    # Forward axis points from the eye (above/below at) straight down/up to ``at``.
    forward = np.array([0.0, -math.copysign(1.0, elev), 0.0])
    close(R[0, 2], forward, atol=atol)
    cams = Cameras.from_fov(R, t, 50.0, 33, 33)
    close(cams.centers()[0], np.array(at) + 3.0 * np.array([0, math.copysign(1.0, elev), 0]),
          atol=10 * atol)
    uv, z = cams.project(torch.tensor([at], dtype=dtype))
    close(uv[0, 0], [16.5, 16.5], atol=1e-3 if dtype == torch.float32 else 1e-9)
    close(z[0, 0], 3.0, atol=10 * atol)
    # Documented fallback: X and Z tie as most perpendicular -> X; image up (= -camera down)
    # is world +X, whatever the azimuth (rounding noise must not change the choice).
    close(-R[0, 1], [1.0, 0.0, 0.0], atol=atol)
    close(-R[0, 1], _documented_fallback_up(forward), atol=atol)


@pytest.mark.parametrize("direction", [(0.0, 0.0, 1.0), (3.0, 1.0, -2.0), (-0.2, 5.0, 0.4), (1.0, 1.0, 1.0)])
@pytest.mark.parametrize("sign", [1.0, -1.0])
@pytest.mark.parametrize("dtype", [torch.float32, F64])
def test_look_at_rotation_up_parallel_to_view(direction, sign, dtype):
    d = np.asarray(direction) / np.linalg.norm(direction)
    eye = np.array([0.3, -1.0, 2.0])
    at = eye + 2.5 * d
    R = look_at_rotation(torch.tensor(eye[None], dtype=dtype), torch.tensor(at[None], dtype=dtype),
                         torch.tensor(sign * 4.0 * d[None], dtype=dtype))  # up (anti)parallel, not unit
    atol = 1e-5 if dtype == torch.float32 else 1e-12
    assert_proper_rotation(R, atol=atol)
    close(R[0, 2], d, atol=atol)                               # still looks at ``at``
    close(-R[0, 1], _documented_fallback_up(d), atol=atol)     # documented fallback up


def test_look_at_rotation_zero_up_uses_fallback():
    R = look_at_rotation(torch.tensor([[0.0, 0, 5]], dtype=F64), torch.zeros(1, 3, dtype=F64),
                         torch.zeros(1, 3, dtype=F64))
    assert_proper_rotation(R, atol=1e-12)
    close(R[0, 2], [0, 0, -1], atol=1e-15)
    close(-R[0, 1], [1, 0, 0], atol=1e-15)  # X and Y tie -> X


def test_look_at_rotation_nearly_parallel_up_stays_orthonormal(gen):
    # Up within 1e-8 .. 1e-2 rad of the view direction, generic (non-axis) directions.
    n = 400
    d = torch.nn.functional.normalize(torch.randn(n, 3, generator=gen, dtype=F64), dim=-1)
    angle = 10 ** (-8 + 6 * torch.rand(n, 1, generator=gen, dtype=F64))
    perp = torch.nn.functional.normalize(torch.cross(d, torch.randn(n, 3, generator=gen, dtype=F64), dim=-1), dim=-1)
    up = torch.cos(angle) * d + torch.sin(angle) * perp
    eye = torch.randn(n, 3, generator=gen, dtype=F64)
    at = eye + 2.0 * d
    for dtype, atol in ((torch.float32, 2e-6), (F64, 1e-12)):
        R = look_at_rotation(eye.to(dtype), at.to(dtype), up.to(dtype))
        assert_proper_rotation(R, atol=atol)
        close(R[:, 2], d, atol=atol * 10)
    # Where it is clearly not degenerate (angle >= 1e-3, float64) the image up is ``up``
    # projected orthogonally to the view direction, exactly as for a generic up.
    R = look_at_rotation(eye, at, up)
    keep = angle[:, 0] > 1e-3
    close(-R[keep, 1], perp[keep], atol=1e-9)


def test_look_at_rows_broadcast():
    R, t = look_at(2.0, 10.0, 30.0, at=[(0.0, 0, 0), (1.0, 2, 3)], up=[(0.0, 1, 0), (0.0, 0, 1)], dtype=F64)
    assert R.shape == (2, 3, 3)
    R_ref, T_ref = p3d_look_at_view_transform(2.0, 10.0, 30.0, at=[(0.0, 0, 0), (1.0, 2, 3)],
                                              up=[(0.0, 1, 0), (0.0, 0, 1)])
    Rp, Tp, _, _ = to_pytorch3d(Cameras(R, t, 1.0, 1.0, 0.0, 0.0, 1, 1))
    close(Rp, R_ref, atol=1e-12)
    close(Tp, T_ref, atol=1e-12)


# ------------------------------------------------------------ converters
@pytest.mark.parametrize("image_size", [(90, 160), (160, 90), (64, 64), (33, 20)])
@pytest.mark.parametrize("in_ndc", [True, False])
def test_pytorch3d_round_trip_and_projection(gen, image_size, in_ndc):
    H, W = image_size
    B = 5
    R = random_rotations(B, gen)
    T = torch.randn(B, 3, generator=gen, dtype=F64) + torch.tensor([0, 0, 6.0], dtype=F64)
    if in_ndc:
        focal = 0.8 + 2 * torch.rand(B, 2, generator=gen, dtype=F64)          # fx != fy
        pp = 0.3 * torch.randn(B, 2, generator=gen, dtype=F64)
        fx, fy, px, py = ndc_to_pixels(focal.numpy(), pp.numpy(), H, W)
    else:
        focal = 40 + 100 * torch.rand(B, 2, generator=gen, dtype=F64)
        pp = torch.tensor([W / 2, H / 2], dtype=F64) + 5 * torch.randn(B, 2, generator=gen, dtype=F64)
        fx, fy, px, py = focal[:, 0].numpy(), focal[:, 1].numpy(), pp[:, 0].numpy(), pp[:, 1].numpy()

    cams = from_pytorch3d(R, T, focal, pp, image_size=image_size, in_ndc=in_ndc)
    assert (cams.height, cams.width) == (H, W) and cams.image_size == (H, W)
    assert cams.R.dtype == F64
    assert_proper_rotation(cams.R, atol=1e-12)
    close(cams.fx, fx, atol=1e-12)
    close(cams.fy, fy, atol=1e-12)
    close(cams.cx, px, atol=1e-12)
    close(cams.cy, py, atol=1e-12)

    # Same pixels as PyTorch3D's documented projection.
    X = torch.randn(50, 3, generator=gen, dtype=F64)
    uv, z = cams.project(X)
    uv_ref, z_ref = p3d_pixels(R.numpy(), T.numpy(), fx, fy, px, py, X.numpy())
    close(z, z_ref, atol=1e-12)
    close(uv, uv_ref, atol=1e-9, rtol=1e-12)

    # Round trip p3d -> ours -> p3d.
    R2, T2, f2, pp2 = to_pytorch3d(cams, in_ndc=in_ndc)
    close(R2, R, atol=1e-14)
    close(T2, T, atol=1e-14)
    close(f2, focal, atol=1e-12)
    close(pp2, pp, atol=1e-12)

    # Round trip ours -> p3d -> ours, through the other unit system as well.
    for ndc in (True, False):
        back = from_pytorch3d(*to_pytorch3d(cams, in_ndc=ndc), image_size=image_size, in_ndc=ndc)
        for name in ("R", "t", "fx", "fy", "cx", "cy"):
            close(getattr(back, name), getattr(cams, name), atol=1e-12)


def test_pytorch3d_focal_shapes(gen):
    R = random_rotations(3, gen)
    T = torch.randn(3, 3, generator=gen, dtype=F64)
    a = from_pytorch3d(R, T, 2.0, image_size=(40, 60))
    b = from_pytorch3d(R, T, torch.full((3,), 2.0, dtype=F64), image_size=(40, 60))
    c = from_pytorch3d(R, T, torch.full((3, 2), 2.0, dtype=F64), image_size=(40, 60))
    for cams in (a, b, c):
        close(cams.fx, [40.0] * 3)
        close(cams.fy, [40.0] * 3)
        close(cams.cx, [30.0] * 3)
        close(cams.cy, [20.0] * 3)
    one = from_pytorch3d(R[0], T[0], torch.tensor([1.0, 2.0], dtype=F64), (0.5, -0.25), image_size=(40, 60))
    assert one.batch_size == 1
    close(one.fx, [20.0])
    close(one.fy, [40.0])
    close(one.cx, [30.0 - 0.5 * 20])
    close(one.cy, [20.0 + 0.25 * 20])


def test_opengl_round_trip_and_semantics(gen):
    B, W, H = 6, 40, 30
    rot = random_rotations(B, gen)
    centre = torch.randn(B, 3, generator=gen, dtype=F64) * 4
    c2w = torch.zeros(B, 4, 4, dtype=F64)
    c2w[:, :3, :3], c2w[:, :3, 3], c2w[:, 3, 3] = rot, centre, 1.0
    fx = 30 + torch.rand(B, generator=gen, dtype=F64) * 10
    fy = fx * 1.3
    cx = W / 2 + torch.randn(B, generator=gen, dtype=F64)
    cy = H / 2 + torch.randn(B, generator=gen, dtype=F64)
    cams = from_opengl_c2w(c2w, fx, fy, cx, cy, W, H)
    assert_proper_rotation(cams.R, atol=1e-12)
    close(cams.centers(), centre, atol=1e-12)
    close(to_opengl_c2w(cams), c2w, atol=1e-13)
    close(to_opengl_c2w(from_opengl_c2w(c2w[:, :3], fx, fy, cx, cy, W, H)), c2w, atol=1e-13)  # (B,3,4)

    # OpenGL camera: +X right, +Y up, looks down -Z (columns of c2w are its axes).
    right, upv, back = rot[:, :, 0], rot[:, :, 1], rot[:, :, 2]
    depth, a, b = 3.0, 0.5, 0.2
    P = centre - depth * back + a * right + b * upv
    uv, z = cams.project(P[:, None, :])
    close(z[:, 0], [depth] * B, atol=1e-12)
    close(uv[:, 0, 0], cx + fx * a / depth, atol=1e-11)
    close(uv[:, 0, 1], cy - fy * b / depth, atol=1e-11)

    # ours -> OpenGL -> ours.
    other = random_cameras(gen, n=3, width=W, height=H)
    back_cams = from_opengl_c2w(to_opengl_c2w(other), other.fx, other.fy, other.cx, other.cy, W, H)
    close(back_cams.R, other.R, atol=1e-13)
    close(back_cams.t, other.t, atol=1e-12)


def test_opencv_round_trip_and_projection(gen):
    B, W, H = 4, 50, 20
    R = random_rotations(B, gen)
    t = torch.randn(B, 3, generator=gen, dtype=F64) + torch.tensor([0, 0, 5.0], dtype=F64)
    K = torch.zeros(B, 3, 3, dtype=F64)
    K[:, 0, 0] = 40 + torch.rand(B, generator=gen, dtype=F64)
    K[:, 1, 1] = 55 + torch.rand(B, generator=gen, dtype=F64)
    K[:, 0, 2] = 24 + torch.rand(B, generator=gen, dtype=F64)
    K[:, 1, 2] = 11 + torch.rand(B, generator=gen, dtype=F64)
    K[:, 2, 2] = 1
    cams = from_opencv(R, t, K, W, H)
    R2, t2, K2 = to_opencv(cams)
    close(R2, R, atol=0)
    close(t2, t, atol=0)
    close(K2, K, atol=0)
    # Shared (3,3) K.
    shared = from_opencv(R, t, K[0], W, H)
    close(shared.fx, K[0, 0, 0].expand(B), atol=0)
    # u ~ K (R X + t), independently.
    X = torch.randn(30, 3, generator=gen, dtype=F64)
    uvw = torch.einsum("bij,bnj->bni", K, torch.einsum("bij,nj->bni", R, X) + t[:, None])
    uv, z = cams.project(X)
    close(uv, uvw[..., :2] / uvw[..., 2:], atol=1e-10)
    close(z, uvw[..., 2], atol=1e-12)
    back = from_opencv(*to_opencv(random_cameras(gen, 2, W, H)), W, H)
    assert back.batch_size == 2


# ------------------------------------------------------------ truck data
def _truck_pose_files():
    files = sorted((TRUCK / "poses").glob("frame*.npy")) if TRUCK.is_dir() else []
    if not files:
        pytest.skip(f"course truck data not found at {TRUCK}")
    return files


def _truck_cameras(files, indices):
    P = np.stack([np.load(files[i]) for i in indices])
    assert P.shape == (len(indices), 16) and P.dtype == np.float64
    R = torch.from_numpy(P[:, :9].reshape(-1, 3, 3).copy())
    T = torch.from_numpy(P[:, 9:12].copy())
    F = torch.from_numpy(P[:, 12:14].copy())
    C = torch.from_numpy(P[:, 14:16].copy())
    return P, from_pytorch3d(R, T, F, C, image_size=(90, 160))


def test_truck_intrinsics_match_readme():
    files = _truck_pose_files()
    assert len(files) == 202
    P, cams = _truck_cameras(files, range(len(files)))
    assert (cams.height, cams.width) == (90, 160)
    fx_ref, fy_ref, px_ref, py_ref = ndc_to_pixels(P[:, 12:14], P[:, 14:16], 90, 160)
    close(cams.fx, fx_ref, atol=1e-12)
    close(cams.fy, fy_ref, atol=1e-12)
    close(cams.cx, px_ref, atol=1e-12)
    close(cams.cy, py_ref, atol=1e-12)
    # README: pixel focal about 74.6 px (fx = fy), principal point about (80, 45).
    assert torch.all((cams.fx - 74.6).abs() < 1.0) and abs(cams.fx.mean().item() - 74.6) < 0.3
    close(cams.fx, cams.fy, atol=1e-12)
    close(cams.cx, torch.full_like(cams.cx, 80.0), atol=0.1)
    close(cams.cy, torch.full_like(cams.cy, 45.0), atol=0.1)
    # Round trip back to the stored numbers.
    R, T, F, C = to_pytorch3d(cams)
    close(R.reshape(-1, 9), P[:, :9], atol=1e-14)
    close(T, P[:, 9:12], atol=1e-14)
    close(F, P[:, 12:14], atol=1e-13)
    close(C, P[:, 14:16], atol=1e-13)


def test_truck_projection_matches_pytorch3d_formula(gen):
    files = _truck_pose_files()
    idx = [0, 33, 100, 201]
    P, cams = _truck_cameras(files, idx)
    X = (torch.rand(200, 3, generator=gen, dtype=F64) - 0.5) * 6
    uv, z = cams.project(X)
    R = P[:, :9].reshape(-1, 3, 3)
    fx, fy, px, py = ndc_to_pixels(P[:, 12:14], P[:, 14:16], 90, 160)
    uv_ref, z_ref = p3d_pixels(R, P[:, 9:12], fx, fy, px, py, X.numpy())
    close(z, z_ref, atol=1e-12)
    ok = torch.from_numpy(np.abs(z_ref) > 0.1)
    close(uv[ok], uv_ref[ok.numpy()], atol=1e-8, rtol=1e-12)
    # One camera at a time gives the same as the batch.
    for k in range(len(idx)):
        uv_k, _ = cams[k].project(X)
        close(uv_k[0], uv[k], atol=1e-12)


def test_truck_initial_points_project_into_training_frames():
    files = _truck_pose_files()
    pts_file = TRUCK / "points" / "points_10000.npy"
    if not pts_file.is_file():
        pytest.skip(f"{pts_file} not found")
    pts = torch.from_numpy(np.load(pts_file))
    assert pts.shape == (10000, 3)
    train = [i for i in range(len(files)) if i not in TRUCK_TEST_FRAMES]
    idx = train[:: len(train) // 6]
    _, cams = _truck_cameras(files, idx)
    uv, z = cams.project(pts)
    inside = (z > 0) & (uv[..., 0] >= 0) & (uv[..., 0] <= 160) & (uv[..., 1] >= 0) & (uv[..., 1] <= 90)
    frac = inside.to(F64).mean(dim=1)
    assert torch.all(frac > 0.5), frac
    assert frac.mean() > 0.9, frac


# ------------------------------------------------------------ box data
BOX_EYES = [(-2.5, 0.0, 0.0), (-1.0, 0.0, -2.2), (0.0, 0.0, -2.5), (1.0, 0.0, -2.2)]


def _box_cameras_two_ways(eye):
    eye_t = torch.tensor([eye], dtype=F64)
    R = look_at_rotation(eye_t, torch.zeros(1, 3, dtype=F64), torch.tensor([[0.0, 1, 0]], dtype=F64))
    t = -(R @ eye_t[..., None])[..., 0]
    fov_cams = Cameras.from_fov(R, t, 90.0, 256, 256)  # NDC focal 1 <=> fov 90 on a square
    R_p3d, T_p3d = p3d_look_at_eye([eye], [(0.0, 0, 0)], [(0.0, 1, 0)])
    p3d_cams = from_pytorch3d(torch.from_numpy(R_p3d), torch.from_numpy(T_p3d), 1.0, (0.0, 0.0),
                              image_size=(256, 256))
    return fov_cams, p3d_cams


@pytest.mark.parametrize("eye", BOX_EYES)
def test_box_cameras_two_constructions_agree(eye):
    fov_cams, p3d_cams = _box_cameras_two_ways(eye)
    for name in ("R", "t", "fx", "fy", "cx", "cy"):
        close(getattr(fov_cams, name), getattr(p3d_cams, name), atol=1e-12)
    close(fov_cams.fx, [128.0])
    close(fov_cams.cx, [128.0])
    close(fov_cams.centers()[0], eye, atol=1e-12)
    close(fov_cams.fov(), [90.0], atol=1e-12)
    # The same camera from look_at(dist, elev=0, azim): azim = atan2(x, z).
    dist = math.hypot(eye[0], eye[2])
    azim = math.degrees(math.atan2(eye[0], eye[2]))
    R, t = look_at(dist, 0.0, azim, dtype=F64)
    close(R, fov_cams.R, atol=1e-12)
    close(t, fov_cams.t, atol=1e-12)


def test_box_eye_minus_x_is_azim_minus_90():
    R, t = look_at(2.5, 0.0, -90.0, dtype=F64)
    close(Cameras(R, t, 1.0, 1.0, 0.0, 0.0, 1, 1).centers()[0], [-2.5, 0.0, 0.0], atol=1e-14)
    cams = look_at_cameras(2.5, 0.0, -90.0, fov=90.0, image_size=256)
    fov_cams, _ = _box_cameras_two_ways((-2.5, 0.0, 0.0))
    close(cams.R, fov_cams.R, atol=1e-6)
    close(cams.t, fov_cams.t, atol=1e-6)
    close(cams.fx, fov_cams.fx, atol=1e-4)


@pytest.mark.parametrize("view", range(4))
def test_box_images_match_projected_box(view):
    path = BOX / f"box_{view}.npy"
    if not path.is_file():
        pytest.skip(f"course box data not found at {BOX}")
    img = np.load(path)
    assert img.shape == (256, 256, 3)
    fg = img.max(-1) > 0.3
    rows, cols = np.flatnonzero(fg.any(1)), np.flatnonzero(fg.any(0))
    img_box = np.array([cols.min(), cols.max() + 1, rows.min(), rows.max() + 1], dtype=np.float64)
    # Ground-truth box (README) projected with our cameras: the (soft, bloated) silhouette
    # contains the projected corners, and the two are centred on each other (a mirrored
    # u or v convention would be off by tens of pixels on views 1-3).
    centre, size = np.array([0.25, 0.25, 0.0]), np.array([2.0, 1.5, 1.5])
    corners = torch.tensor(np.array([centre + size / 2 * np.array(s) for s in itertools.product([-1, 1], repeat=3)]))
    cams, _ = _box_cameras_two_ways(BOX_EYES[view])
    uv, z = cams.project(corners)
    assert torch.all(z > 0)
    u, v = uv[0, :, 0].numpy(), uv[0, :, 1].numpy()
    proj_box = np.array([u.min(), u.max(), v.min(), v.max()])
    assert img_box[0] <= proj_box[0] and proj_box[1] <= img_box[1], (img_box, proj_box)
    assert img_box[2] <= proj_box[2] and proj_box[3] <= img_box[3], (img_box, proj_box)
    assert np.all(np.abs(img_box - proj_box) < 16), (img_box, proj_box)
    img_c = np.array([img_box[:2].mean(), img_box[2:].mean()])
    proj_c = np.array([proj_box[:2].mean(), proj_box[2:].mean()])
    assert np.all(np.abs(img_c - proj_c) < 5), (img_c, proj_c)


# ------------------------------------------------------------------ rays
def test_pixel_centers():
    uv = pixel_centers(3, 4, dtype=F64)
    assert uv.shape == (3, 4, 2)
    close(uv[0, 0], [0.5, 0.5])
    close(uv[2, 3], [3.5, 2.5])
    close(uv[1, 2], [2.5, 1.5])  # (row i, col j) -> (u, v) = (j + .5, i + .5)


def test_camera_rays_reproject_to_pixel_centres(gen):
    H, W = 5, 7
    cams = random_cameras(gen, n=3, width=W, height=H)
    origins, dirs = camera_rays(cams)
    assert origins.shape == dirs.shape == (3, H, W, 3)
    close(origins, cams.centers()[:, None, None, :].expand(-1, H, W, -1), atol=1e-14)
    close(dirs.norm(dim=-1), torch.ones(3, H, W, dtype=F64), atol=1e-14)
    i, j = torch.meshgrid(torch.arange(H, dtype=F64), torch.arange(W, dtype=F64), indexing="ij")
    expected = torch.stack([j + 0.5, i + 0.5], -1).expand(3, -1, -1, -1)
    for s in (0.01, 1.0, 7.5):
        pts = origins + s * dirs
        uv, z = cams.project(pts.reshape(3, -1, 3))
        assert torch.all(z > 0)
        close(uv.reshape(3, H, W, 2), expected, atol=1e-10)

    # normalize=False: camera-frame Z of every direction is 1 (a point at s has depth s).
    _, raw = camera_rays(cams, normalize=False)
    d_cam = torch.einsum("bij,bhwj->bhwi", cams.R, raw)
    close(d_cam[..., 2], torch.ones(3, H, W, dtype=F64), atol=1e-13)
    close(torch.nn.functional.normalize(raw, dim=-1), dirs, atol=1e-13)
    _, z = cams.project((origins + 2.5 * raw).reshape(3, -1, 3))
    close(z, torch.full((3, H * W), 2.5, dtype=F64), atol=1e-12)


def test_centre_ray_of_odd_image_is_forward_axis(gen):
    H, W = 7, 9
    R = random_rotations(2, gen)
    t = torch.randn(2, 3, generator=gen, dtype=F64)
    cams = Cameras(R, t, [6.0, 11.0], [8.0, 3.0], W / 2, H / 2, W, H)
    _, dirs = camera_rays(cams)
    close(dirs[:, H // 2, W // 2], R[:, 2], atol=1e-14)  # forward axis in world coordinates
    cams_lk = look_at_cameras(3.0, 25.0, 40.0, fov=60.0, image_size=9, at=(0.1, 0.2, -0.3))
    origins, dirs = camera_rays(cams_lk)
    to_at = torch.tensor([0.1, 0.2, -0.3]) - origins[0, 4, 4]
    close(dirs[0, 4, 4], to_at / to_at.norm(), atol=1e-6)


def test_rays_match_pytorch3d_formula(gen):
    # Points along a ray through (u, v) project back to (u, v) under PyTorch3D's formula.
    H, W = 6, 10
    R = random_rotations(2, gen)
    T = torch.randn(2, 3, generator=gen, dtype=F64)
    focal = torch.tensor([[1.2, 1.7], [2.0, 0.9]], dtype=F64)
    pp = torch.tensor([[0.1, -0.2], [-0.3, 0.05]], dtype=F64)
    cams = from_pytorch3d(R, T, focal, pp, image_size=(H, W))
    origins, dirs = camera_rays(cams)
    pts = (origins + 4.0 * dirs).reshape(2, -1, 3).numpy()
    fx, fy, px, py = ndc_to_pixels(focal.numpy(), pp.numpy(), H, W)
    Xv = np.einsum("bnj,bjk->bnk", pts, R.numpy()) + T.numpy()[:, None]
    u = px[:, None] - fx[:, None] * Xv[..., 0] / Xv[..., 2]
    v = py[:, None] - fy[:, None] * Xv[..., 1] / Xv[..., 2]
    uv = pixel_centers(H, W, dtype=F64).reshape(-1, 2)
    close(np.stack([u, v], -1), uv.expand(2, -1, -1), atol=1e-10)


def test_pixels_to_directions_any_leading_shape(gen):
    cams = random_cameras(gen, n=2)
    uv = torch.rand(2, 3, 4, 2, generator=gen, dtype=F64) * 5
    d = pixels_to_directions(cams, uv)
    assert d.shape == (2, 3, 4, 3)
    uv_back, _ = cams.project((cams.centers()[:, None] + 2 * d.reshape(2, -1, 3)))
    close(uv_back, uv.reshape(2, -1, 2), atol=1e-10)


# ------------------------------------------------------- Cameras utilities
def test_cameras_getitem_len_and_stack(gen):
    cams = random_cameras(gen, n=4)
    assert len(cams) == 4 and cams.batch_size == 4
    for k in (0, 2, -1, -2):
        sub = cams[k]
        assert isinstance(sub, Cameras) and sub.batch_size == 1
        for name in ("R", "t", "fx", "fy", "cx", "cy"):
            close(getattr(sub, name)[0], getattr(cams, name)[k], atol=0)
        assert (sub.width, sub.height) == (cams.width, cams.height)
    sl = cams[1:3]
    assert sl.batch_size == 2
    close(sl.R, cams.R[1:3], atol=0)
    picked = cams[torch.tensor([3, 0])]
    close(picked.cx, cams.cx[[3, 0]], atol=0)
    both = stack_cameras([cams[0], cams[1:]])
    for name in ("R", "t", "fx", "fy", "cx", "cy"):
        close(getattr(both, name), getattr(cams, name), atol=0)
    with pytest.raises(ValueError):
        stack_cameras([cams, random_cameras(gen, n=1, width=8, height=5)])


def test_cameras_to_dtype_and_device(gen):
    cams = random_cameras(gen, n=2)
    c32 = cams.to(dtype=torch.float32)
    for name in ("R", "t", "fx", "fy", "cx", "cy"):
        assert getattr(c32, name).dtype == torch.float32
        close(getattr(c32, name), getattr(cams, name), atol=1e-5, rtol=1e-6)
    assert (c32.width, c32.height) == (cams.width, cams.height)
    same = cams.to("cpu")
    assert same.device == torch.device("cpu") and same.R.dtype == F64
    close(same.t, cams.t, atol=0)
    assert c32.to(dtype=F64).R.dtype == F64


def test_cameras_K_centers_and_broadcast():
    R = torch.eye(3, dtype=F64)
    t = torch.tensor([1.0, -2.0, 3.0], dtype=F64)
    cams = Cameras(R, t, 10.0, 20.0, 3.0, 4.0, 8, 6)  # unbatched inputs
    assert cams.batch_size == 1 and cams.R.shape == (1, 3, 3) and cams.t.shape == (1, 3)
    close(cams.K()[0], [[10.0, 0, 3.0], [0, 20.0, 4.0], [0, 0, 1.0]], atol=0)
    close(cams.centers()[0], [-1.0, 2.0, -3.0], atol=0)
    Rb = torch.stack([torch.eye(3, dtype=F64), torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=F64))])
    cb = Cameras(Rb, t, [10.0, 11.0], 20.0, 3.0, 4.0, 8, 6)  # t and fy broadcast over B
    assert cb.t.shape == (2, 3) and cb.fy.shape == (2,)
    close(cb.centers(), [[-1.0, 2.0, -3.0], [-1.0, -2.0, 3.0]], atol=0)  # C = -R^T t
    close(cb.K()[:, 0, 0], [10.0, 11.0], atol=0)
    # A point at the centre plane stays finite.
    uv, z = cb.project(cb.centers()[:1])
    assert torch.isfinite(uv).all()


@pytest.mark.parametrize("width,height", [(64, 64), (160, 90), (90, 160)])
@pytest.mark.parametrize("fov", [10.0, 60.0, 120.0, 179.0])
def test_from_fov_round_trip(width, height, fov):
    R, t = look_at([2.0, 3.0], 0.0, [0.0, 45.0], dtype=F64)
    cams = Cameras.from_fov(R, t, fov, width, height)
    close(cams.fov(), [fov, fov], atol=1e-10)
    close(cams.fov(degrees=False), [math.radians(fov)] * 2, atol=1e-12)
    s = min(width, height)
    close(cams.fx, [s / 2 / math.tan(math.radians(fov) / 2)] * 2, atol=1e-10)
    close(cams.cx, [width / 2] * 2, atol=0)
    close(cams.cy, [height / 2] * 2, atol=0)
    rad = Cameras.from_fov(R, t, math.radians(fov), width, height, degrees=False)
    close(rad.fx, cams.fx, atol=1e-10)
    per_cam = Cameras.from_fov(R, t, [fov, fov / 2], width, height)
    close(per_cam.fov(), [fov, fov / 2], atol=1e-10)
    # The smaller side really spans the field of view: a point on the image edge.
    edge = Cameras.from_fov(torch.eye(3, dtype=F64), torch.zeros(3, dtype=F64), fov, width, height)
    half = math.tan(math.radians(fov) / 2)
    uv, _ = edge.project(torch.tensor([[half, half, 1.0]], dtype=F64))
    if width <= height:
        close(uv[0, 0, 0], width, atol=1e-9)
    else:
        close(uv[0, 0, 1], height, atol=1e-9)


def test_fov_uses_smaller_side_focal():
    I = torch.eye(3, dtype=F64)
    z = torch.zeros(3, dtype=F64)
    landscape = Cameras(I, z, 10.0, 25.0, 50.0, 25.0, 100, 50)  # smaller side = height -> fy
    close(landscape.fov(), [90.0], atol=1e-12)
    portrait = Cameras(I, z, 25.0, 10.0, 25.0, 50.0, 50, 100)   # smaller side = width -> fx
    close(portrait.fov(), [90.0], atol=1e-12)


@pytest.mark.parametrize("width,height", [(0, 10), (10, 0), (-5, 10), (10, -1)])
def test_invalid_image_size_raises_user_error(width, height):
    I = torch.eye(3)
    with pytest.raises(UserError):
        Cameras(I, torch.zeros(3), 1.0, 1.0, 0.0, 0.0, width, height)
    with pytest.raises(UserError):
        Cameras.from_fov(I, torch.zeros(3), 60.0, width, height)


@pytest.mark.parametrize("fov", [0.0, -10.0, 180.0, 200.0, float("nan")])
def test_invalid_fov_raises_user_error(fov):
    I = torch.eye(3)
    with pytest.raises(UserError):
        Cameras.from_fov(I, torch.zeros(3), fov, 32, 32)
    with pytest.raises(UserError):
        look_at_cameras(2.0, 0.0, 0.0, fov=fov, image_size=32)
    with pytest.raises(UserError):
        Cameras.from_fov(I, torch.zeros(3), math.radians(fov), 32, 32, degrees=False)
    assert issubclass(UserError, ValueError)


def test_invalid_image_size_in_look_at_cameras():
    with pytest.raises(UserError):
        look_at_cameras(2.0, 0.0, 0.0, fov=60.0, image_size=0)


def test_pixel_axes_move_a_ray_exactly_by_sub_pixel_steps():
    cams = look_at_cameras(3.0, torch.tensor([10.0, 40.0]), torch.tensor([20.0, 200.0]), 45.0, 16).to(dtype=torch.float64)
    du, dv = pixel_axes(cams)
    uv = pixel_centers(16, 16, dtype=torch.float64)[None].expand(2, -1, -1, -1)
    d0 = pixels_to_directions(cams, uv, normalize=False)
    d1 = pixels_to_directions(cams, uv + torch.tensor([0.3, -0.45], dtype=torch.float64), normalize=False)
    assert torch.allclose(d0 + 0.3 * du[:, None, None] - 0.45 * dv[:, None, None], d1, atol=1e-14)


def test_supersampled_rays_hit_the_sub_pixel_centres_of_a_finer_camera():
    from l3d_app.render.mesh.renderer import scale_cameras

    cams = look_at_cameras(3.0, torch.tensor([25.0]), torch.tensor([60.0]), 50.0, 8).to(dtype=torch.float64)
    o, d = supersampled_rays(cams, 2)
    assert d.shape == (1, 8, 8, 4, 3) and torch.allclose(d.norm(dim=-1), torch.ones(1, 8, 8, 4, dtype=torch.float64))
    _, fine = camera_rays(scale_cameras(cams, 2))                        # (1, 16, 16, 3)
    fine = fine.reshape(1, 8, 2, 8, 2, 3).permute(0, 1, 3, 2, 4, 5).reshape(1, 8, 8, 4, 3)
    assert torch.allclose(d, fine, atol=1e-12)
    assert torch.allclose(o, cams.centers()[:, None, None, None].expand_as(o))
