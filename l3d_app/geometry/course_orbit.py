"""The course's 32-view camera path for rendering Gaussians (its ``render.py``).

32 cameras at azimuths ``linspace(-180, 180, 32)`` degrees (both ends included, so the first and last
views coincide, as the course's gif does), elevation 30 degrees, distance 6 from ``at`` (the course
centres the splats on their mean), PyTorch3D-style ``look_at`` placement with up ``(0, -1, 0)`` (the
course's captures have -y up), a square image of ``image_size`` pixels with focal length
``5 * image_size / 2`` pixels (a 22.6 degree field of view) and the principal point at the centre.
"""

from __future__ import annotations

from typing import Sequence

import torch

from l3d_app.geometry.cameras import Cameras, look_at

COURSE_VIEWS = 32
COURSE_DISTANCE = 6.0         # world units
COURSE_ELEVATION = 30.0       # degrees
COURSE_UP = (0.0, -1.0, 0.0)
COURSE_FOCAL_SCALE = 5.0      # focal length in half image widths


def course_orbit(image_size: int = 256, at: Sequence[float] = (0.0, 0.0, 0.0), num_views: int = COURSE_VIEWS,
                 distance: float = COURSE_DISTANCE, elevation: float = COURSE_ELEVATION,
                 up: Sequence[float] = COURSE_UP, device=None) -> Cameras:
    """(num_views) square cameras of the course's Gaussian render path around ``at`` (world units)."""
    azim = torch.linspace(-180.0, 180.0, int(num_views))
    R, t = look_at(float(distance), float(elevation), azim, at=[float(v) for v in at], up=[float(v) for v in up])
    f = COURSE_FOCAL_SCALE * int(image_size) / 2.0
    c = int(image_size) / 2.0
    return Cameras(R, t, f, f, c, c, int(image_size), int(image_size)).to(device or "cpu")
