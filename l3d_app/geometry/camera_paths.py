"""Camera paths: turntables and dolly zooms, as batched :class:`Cameras`."""

from __future__ import annotations

import math
from typing import Sequence, Tuple

import torch

from l3d_app.errors import UserError
from l3d_app.geometry.cameras import Cameras, from_pytorch3d, look_at
from l3d_app.geometry.transforms import euler_xyz
from l3d_app.registry import CAMERA_PATHS


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
              at: Sequence[float] = (0.0, 0.0, 0.0), device=None) -> Cameras:
    """``num_frames`` cameras evenly spaced in azimuth over 360 degrees (the last frame
    stops one step short of the first, so the gif loops without a repeated frame).

    distance in world units, elevation and fov in degrees, image_size in pixels (square).
    """
    if num_frames <= 0:
        raise UserError(f"num_frames must be positive, got {num_frames}")
    if distance <= 0:
        raise UserError(f"distance must be positive, got {distance}")
    azim = torch.arange(num_frames, dtype=torch.float32, device=device) * (360.0 / num_frames)
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
    r_rel = euler_xyz(rotation_deg)
    t0 = torch.tensor([0.0, 0.0, float(base_distance)])
    T = r_rel @ t0 + torch.as_tensor(translation, dtype=torch.float32)
    ndc_focal = 1.0 / math.tan(math.radians(fov) / 2)  # square image: NDC spans [-1, 1]
    return from_pytorch3d(r_rel, T, focal=ndc_focal, image_size=(image_size, image_size)).to(device)
