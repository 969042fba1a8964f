"""Camera paths as batched :class:`Cameras`: turntables and dolly zooms (about +Y, the
course's), and paths about a scene's own up axis for ``task=render_path``: :func:`orbit`,
:func:`spiral`, :func:`interpolate_cameras` (slerp rotations + Catmull-Rom centres through
key cameras) and nerfstudio's ``camera_path.json`` (:func:`read_camera_path`,
:func:`write_camera_path`)."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Optional, Sequence, Tuple

import torch

from l3d_app.errors import UserError
from l3d_app.geometry.cameras import Cameras, from_opengl_c2w, from_pytorch3d, look_at, look_at_rotation, \
    to_opengl_c2w
from l3d_app.geometry.pose_checks import check_rigid_poses
from l3d_app.geometry.transforms import euler_xyz
from l3d_app.registry import CAMERA_PATHS
from l3d_app.runtime.config_values import config_floats
from l3d_app.runtime.files import read_json


def cameras_up(cams: Cameras) -> torch.Tensor:
    """(3,) unit mean "up" of a camera batch: the average of each camera's image-up axis in
    world coordinates (minus the second row of ``R``, whose +Y points down the image).

    For hand-held or orbit captures this is the scene's vertical (COLMAP and nerfstudio
    worlds have no fixed up axis). Falls back to +Y if the cameras' ups cancel out.
    """
    mean = (-cams.R[:, 1, :].double()).mean(0)
    if float(mean.norm()) < 1e-6:
        return torch.tensor([0.0, 1.0, 0.0])
    return (mean / mean.norm()).float().cpu()


@CAMERA_PATHS.register("turntable")
def turntable(num_frames: int, distance: float, elevation: float, fov: float, image_size: int,
              at: Sequence[float] = (0.0, 0.0, 0.0), device=None, azimuth_offset: float = 0.0) -> Cameras:
    """``num_frames`` cameras evenly spaced in azimuth over 360 degrees (the last frame
    stops one step short of the first, so the gif loops without a repeated frame).

    distance in world units, elevation and fov in degrees, image_size in pixels (square);
    azimuth_offset (degrees) turns every frame (e.g. half a step: views between another
    turntable's frames).
    """
    if num_frames <= 0:
        raise UserError(f"num_frames must be positive, got {num_frames}")
    if distance <= 0:
        raise UserError(f"distance must be positive, got {distance}")
    azim = torch.arange(num_frames, dtype=torch.float32, device=device) * (360.0 / num_frames) + float(azimuth_offset)
    R, t = look_at(distance, elevation, azim, at=at, device=device)
    return Cameras.from_fov(R, t, fov, image_size, image_size)


def dolly_distance(fov_deg: torch.Tensor, radius: float, fraction: float) -> torch.Tensor:
    """Camera distance at which a sphere of ``radius`` spans ``fraction`` of the image width.

    The sphere's silhouette has angular half-width asin(r / d); it spans ``fraction`` of
    the image when tan(asin(r / d)) = fraction * tan(fov / 2), i.e.
    ``d = r * sqrt(1 + 1 / (fraction * tan(fov / 2))^2)``. Exact for a sphere at any
    field of view (a plain ``r / (fraction * tan(fov/2))`` drifts at wide angles).
    """
    k = fraction * torch.tan(torch.deg2rad(fov_deg) / 2)
    return radius * torch.sqrt(1 + 1 / k ** 2)


def dolly_zoom(num_frames: int, fov_range: Tuple[float, float], radius: float, fraction: float,
               image_size: int, elevation: float = 0.0, azimuth: float = 0.0,
               at: Sequence[float] = (0.0, 0.0, 0.0), device=None) -> Tuple[Cameras, torch.Tensor]:
    """Cameras whose field of view sweeps ``fov_range`` (degrees) while the distance
    follows :func:`dolly_distance`, so a subject of bounding radius ``radius`` keeps its
    on-screen size (``fraction`` of the width) and the background perspective changes.

    Returns the cameras and the (N,) distances.
    """
    if num_frames <= 0:
        raise UserError(f"num_frames must be positive, got {num_frames}")
    lo, hi = float(fov_range[0]), float(fov_range[1])
    if not (0 < lo < 180 and 0 < hi < 180):
        raise UserError(f"dolly fov range must lie in (0, 180) degrees, got {list(fov_range)}")
    if not 0 < fraction < 1:
        raise UserError(f"subject fraction must be in (0, 1), got {fraction}")
    fov = torch.linspace(lo, hi, num_frames, device=device)
    dist = dolly_distance(fov, radius, fraction)
    R, t = look_at(dist, elevation, azimuth, at=at, device=device)
    return Cameras.from_fov(R, t, fov, image_size, image_size), dist


@CAMERA_PATHS.register("relative")
def relative_camera(rotation_deg: Sequence[float] = (0.0, 0.0, 0.0),
                    translation: Sequence[float] = (0.0, 0.0, 0.0), base_distance: float = 3.0,
                    fov: float = 60.0, image_size: int = 256, device=None) -> Cameras:
    """One camera: a relative rotation and translation applied to a base camera.

    In PyTorch3D terms (the course's), the base camera has ``R0 = I`` and
    ``T0 = (0, 0, base_distance)``: it sits at world (0, 0, -base_distance) looking
    along +Z. The new camera is ``R = R_rel @ R0``, ``T = R_rel @ T0 + T_rel`` with
    ``R_rel = euler_xyz(rotation_deg)`` and ``T_rel = translation`` (world units), e.g.
    rotation_deg=(0, 0, -90) spins the image about the view axis, translation=(0, 0, 2)
    moves the camera back by 2.
    """
    if not 0 < fov < 180:
        raise UserError(f"fov must be in (0, 180) degrees, got {fov}")
    r_rel = euler_xyz(config_floats(rotation_deg, "camera.rotation_deg", 3))
    t0 = torch.tensor([0.0, 0.0, float(base_distance)])
    T = r_rel @ t0 + torch.tensor(config_floats(translation, "camera.translation", 3))
    ndc_focal = 1.0 / math.tan(math.radians(fov) / 2)  # square image: NDC spans [-1, 1]
    return from_pytorch3d(r_rel, T, focal=ndc_focal, image_size=(image_size, image_size)).to(device)


# ------------------------------------------------- paths about a scene's up axis
def _plane_basis(up: torch.Tensor, start: Optional[torch.Tensor] = None) -> Tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Unit up ``w`` and two unit axes ``u, v`` spanning the plane perpendicular to it; ``u``
    points along ``start`` projected to the plane when given (the orbit's first camera)."""
    w = torch.nn.functional.normalize(up.double().reshape(3), dim=0)
    cand = [start.double().reshape(3)] if start is not None else []
    cand += [torch.eye(3, dtype=torch.float64)[int(torch.argmin(w.abs()))]]
    for c in cand:
        u = c - (c @ w) * w
        if float(u.norm()) > 1e-6:
            break
    u = u / u.norm()
    return u, torch.linalg.cross(w, u), w


def _cameras_looking_at(eyes: torch.Tensor, centre: torch.Tensor, up: torch.Tensor, fov: float, width: int,
                        height: int) -> Cameras:
    """Cameras at ``eyes`` (N, 3) looking at ``centre`` with image-up along ``up``; ``fov``
    degrees across the smaller image side."""
    n = eyes.shape[0]
    R = look_at_rotation(eyes, centre.expand(n, 3), up.expand(n, 3))
    t = -(R @ eyes[..., None])[..., 0]
    return Cameras.from_fov(R.float(), t.float(), fov, width, height)


def orbit(num_frames: int, centre: Sequence[float], up: Sequence[float], radius: float, elevation: float,
          fov: float, width: int, height: int, start: Optional[Sequence[float]] = None) -> Cameras:
    """``num_frames`` cameras on a circle about the axis ``up`` through ``centre`` (world units),
    ``elevation`` degrees above the plane perpendicular to ``up``, at distance ``radius``,
    looking at ``centre``; the first camera lies towards ``start`` (a direction) when given.
    The last frame stops one step short of the first (loops without a repeated frame)."""
    if int(num_frames) <= 0 or not radius > 0:
        raise UserError(f"orbit needs num_frames > 0 and radius > 0, got {num_frames}, {radius}")
    c = torch.as_tensor(centre, dtype=torch.float64).reshape(3)
    u, v, w = _plane_basis(torch.as_tensor(up, dtype=torch.float64), None if start is None else torch.as_tensor(start))
    th = torch.arange(int(num_frames), dtype=torch.float64) * (2 * math.pi / int(num_frames))
    el = math.radians(float(elevation))
    dirs = math.cos(el) * (torch.cos(th)[:, None] * u + torch.sin(th)[:, None] * v) + math.sin(el) * w
    return _cameras_looking_at(c + float(radius) * dirs, c, w, fov, width, height)


def spiral(num_frames: int, centre: Sequence[float], up: Sequence[float], radius: float, elevation: float,
           fov: float, width: int, height: int, rounds: float = 2.0, elevation_amplitude: float = 15.0,
           radius_amplitude: float = 0.1, start: Optional[Sequence[float]] = None) -> Cameras:
    """An orbit whose elevation swings ``elevation +- elevation_amplitude`` degrees and whose
    distance swings ``radius * (1 +- radius_amplitude)`` once per path while it turns ``rounds``
    times about ``up``."""
    if int(num_frames) <= 0 or not radius > 0:
        raise UserError(f"spiral needs num_frames > 0 and radius > 0, got {num_frames}, {radius}")
    c = torch.as_tensor(centre, dtype=torch.float64).reshape(3)
    u, v, w = _plane_basis(torch.as_tensor(up, dtype=torch.float64), None if start is None else torch.as_tensor(start))
    k = torch.arange(int(num_frames), dtype=torch.float64) / int(num_frames)
    th = 2 * math.pi * float(rounds) * k
    el = torch.deg2rad(float(elevation) + float(elevation_amplitude) * torch.sin(2 * math.pi * k))
    r = float(radius) * (1 + float(radius_amplitude) * torch.sin(2 * math.pi * k + math.pi / 2))
    dirs = torch.cos(el)[:, None] * (torch.cos(th)[:, None] * u + torch.sin(th)[:, None] * v) + torch.sin(el)[:, None] * w
    return _cameras_looking_at(c + r[:, None] * dirs, c, w, fov, width, height)


def rotation_to_quaternion(R: torch.Tensor) -> torch.Tensor:
    """(N, 3, 3) rotations -> (N, 4) unit quaternions (w, x, y, z) with w >= 0 (branch on the
    largest of the four squared components, so no division by a small number)."""
    R = R.double()
    m00, m11, m22 = R[:, 0, 0], R[:, 1, 1], R[:, 2, 2]
    sq = torch.stack([1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22], -1)
    cand = torch.stack([
        torch.stack([sq[:, 0], R[:, 2, 1] - R[:, 1, 2], R[:, 0, 2] - R[:, 2, 0], R[:, 1, 0] - R[:, 0, 1]], -1),
        torch.stack([R[:, 2, 1] - R[:, 1, 2], sq[:, 1], R[:, 1, 0] + R[:, 0, 1], R[:, 0, 2] + R[:, 2, 0]], -1),
        torch.stack([R[:, 0, 2] - R[:, 2, 0], R[:, 1, 0] + R[:, 0, 1], sq[:, 2], R[:, 2, 1] + R[:, 1, 2]], -1),
        torch.stack([R[:, 1, 0] - R[:, 0, 1], R[:, 0, 2] + R[:, 2, 0], R[:, 2, 1] + R[:, 1, 2], sq[:, 3]], -1)], 1)
    best = sq.argmax(-1)
    q = cand[torch.arange(len(R)), best] / (2 * sq.gather(1, best[:, None]).clamp_min(1e-30).sqrt())
    q = torch.nn.functional.normalize(q, dim=-1)
    return torch.where(q[:, :1] < 0, -q, q)


def quaternion_to_rotation(q: torch.Tensor) -> torch.Tensor:
    """(N, 4) quaternions (w, x, y, z), any norm -> (N, 3, 3)."""
    w, x, y, z = torch.nn.functional.normalize(q.double(), dim=-1).unbind(-1)
    return torch.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
                        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
                        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1).reshape(-1, 3, 3)


def slerp(q0: torch.Tensor, q1: torch.Tensor, tau: torch.Tensor) -> torch.Tensor:
    """Spherical interpolation of unit quaternions (N, 4) at fractions ``tau`` (N,), along the
    shorter arc (q1 flipped to the hemisphere of q0); nearly equal ends fall back to lerp."""
    d = (q0 * q1).sum(-1, keepdim=True)
    q1 = torch.where(d < 0, -q1, q1)
    d = d.abs().clamp(max=1.0)
    omega = torch.acos(d)
    so = torch.sin(omega)
    tau = tau[:, None]
    small = so < 1e-6
    a = torch.where(small, 1 - tau, torch.sin((1 - tau) * omega) / torch.where(small, 1.0, so))
    b = torch.where(small, tau, torch.sin(tau * omega) / torch.where(small, 1.0, so))
    return torch.nn.functional.normalize(a * q0 + b * q1, dim=-1)


def catmull_rom(points: torch.Tensor, s: torch.Tensor, closed: bool = False) -> torch.Tensor:
    """Uniform Catmull-Rom spline through K points (K, D) at parameters ``s`` (M,) in [0, K-1]
    ([0, K) when ``closed``): passes through every point, C1 continuous. Open ends repeat
    the end points."""
    K = points.shape[0]
    if K == 1:
        return points.expand(s.shape[0], -1).clone()
    i = torch.clamp(s.floor().long(), 0, K - 1 if closed else K - 2)
    tau = (s - i.to(s.dtype))[:, None]
    idx = torch.stack([i - 1, i, i + 1, i + 2], -1)
    idx = idx % K if closed else idx.clamp(0, K - 1)
    p0, p1, p2, p3 = (points[idx[:, k]] for k in range(4))
    t2, t3 = tau * tau, tau * tau * tau
    return 0.5 * ((2 * p1) + (-p0 + p2) * tau + (2 * p0 - 5 * p1 + 4 * p2 - p3) * t2 + (-p0 + 3 * p1 - 3 * p2 + p3) * t3)


def interpolate_cameras(keys: Cameras, num_frames: int, closed: bool = False) -> Cameras:
    """``num_frames`` cameras through the K key cameras in order: rotations by slerp between
    consecutive keys, centres on a Catmull-Rom spline, intrinsics linearly; frame 0 is key 0
    and (open paths) the last frame is the last key."""
    K, n = keys.batch_size, int(num_frames)
    if n <= 0 or K == 0:
        raise UserError(f"interpolation needs num_frames > 0 and at least one key camera, got {n}, {K}")
    span = float(K if closed else K - 1)
    s = torch.arange(n, dtype=torch.float64) * (span / n if closed else span / max(n - 1, 1))
    i = torch.clamp(s.floor().long(), 0, max(K - 1 if closed else K - 2, 0))
    j = (i + 1) % K if closed else torch.clamp(i + 1, max=K - 1)
    tau = s - i.double()
    q = rotation_to_quaternion(keys.R)
    R = quaternion_to_rotation(slerp(q[i], q[j], tau))
    C = catmull_rom(keys.centers().double(), s, closed)
    lin = lambda v: v.double()[i] * (1 - tau) + v.double()[j] * tau  # noqa: E731
    t = -(R @ C[..., None])[..., 0]
    return Cameras(R.float(), t.float(), lin(keys.fx).float(), lin(keys.fy).float(), lin(keys.cx).float(),
                   lin(keys.cy).float(), keys.width, keys.height)


def read_camera_path(path) -> Cameras:
    """Cameras of a nerfstudio ``camera_path.json``: ``render_width``, ``render_height`` and
    ``camera_path[]`` entries with ``camera_to_world`` (16 numbers, row-major OpenGL
    camera-to-world) and ``fov`` (vertical, degrees). Poses are taken in the world frame of
    the data the model was trained on. Raises :class:`UserError` naming the file and frame
    for no frames, a missing key, a non-finite or non-rigid pose or a bad fov."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"camera path file not found: {path}")
    meta = read_json(path)
    frames = meta.get("camera_path") if isinstance(meta, dict) else None
    if not frames:
        raise UserError(f"{path}: no keyframes (camera_path is empty or missing)")
    try:
        W, H = int(meta["render_width"]), int(meta["render_height"])
    except (KeyError, TypeError, ValueError) as err:
        raise UserError(f"{path}: needs integer render_width and render_height") from err
    c2w, fov = [], []
    for i, fr in enumerate(frames):
        m = fr.get("camera_to_world") if isinstance(fr, dict) else None
        if m is None or len(m) != 16 or "fov" not in fr:
            raise UserError(f"{path}: frame {i}: needs camera_to_world (16 numbers) and fov")
        try:
            c2w.append([float(v) for v in m])
            fov.append(float(fr["fov"]))
        except (TypeError, ValueError) as err:
            raise UserError(f"{path}: frame {i}: {err}") from err
    c2w_t = torch.tensor(c2w, dtype=torch.float64).reshape(-1, 4, 4)
    check_rigid_poses(c2w_t[:, :3, :3], c2w_t[:, :3, 3], str(path))
    fov_t = torch.tensor(fov, dtype=torch.float64)
    bad = ~torch.isfinite(fov_t) | (fov_t <= 0) | (fov_t >= 180)
    if bool(bad.any()):
        raise UserError(f"{path}: frame {int(bad.nonzero()[0])}: fov must be in (0, 180) degrees")
    f = (H / 2.0) / torch.tan(torch.deg2rad(fov_t) / 2)
    return from_opengl_c2w(c2w_t[:, :3], f, f, W / 2.0, H / 2.0, W, H).to(dtype=torch.float32)


def write_camera_path(path, cams: Cameras, fps: float = 24.0) -> Path:
    """Write ``cams`` as a nerfstudio ``camera_path.json`` (inverse of :func:`read_camera_path`;
    vertical fov from ``fy``)."""
    c2w = to_opengl_c2w(cams.to(dtype=torch.float64))
    fov = torch.rad2deg(2 * torch.atan(cams.height / 2.0 / cams.fy.double()))
    meta = {"camera_type": "perspective", "render_width": cams.width, "render_height": cams.height, "fps": fps,
            "seconds": cams.batch_size / float(fps),
            "camera_path": [{"camera_to_world": c2w[i].reshape(-1).tolist(), "fov": float(fov[i]),
                             "aspect": cams.width / cams.height} for i in range(cams.batch_size)]}
    Path(path).write_text(json.dumps(meta, indent=1))
    return Path(path)
