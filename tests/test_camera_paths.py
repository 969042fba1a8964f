"""Camera paths: the course's relative camera transforms, turntables and dolly zoom."""

import math

import pytest
import torch

from l3d_app.errors import UserError
from l3d_app.geometry.camera_paths import dolly_distance, dolly_zoom, relative_camera, turntable
from l3d_app.geometry.mesh_colors import gradient_colors
from l3d_app.geometry.primitives import cube

SIZE, FOV = 256, 60.0
F = (SIZE / 2) / math.tan(math.radians(FOV) / 2)  # pixel focal
C = SIZE / 2


def project(cam, point):
    uv, z = cam.project(torch.tensor([point], dtype=torch.float32))
    return uv[0, 0].tolist(), float(z[0, 0])


@pytest.mark.parametrize("rotation, translation, point, expected", [
    # base camera (PyTorch3D T0 = (0, 0, 3)): +X world is image-left (PyTorch3D view +X left)
    ((0, 0, 0), (0, 0, 0), (1, 0, 0), (C - F / 3, C)),
    # rotate about the view axis by -90 degrees: +X world moves to the top of the image
    ((0, 0, -90), (0, 0, 0), (1, 0, 0), (C, C - F / 3)),
    # move back by 2: the point is at depth 5
    ((0, 0, 0), (0, 0, 2), (1, 0, 0), (C - F / 5, C)),
    # shift by (0.5, -0.5, 0): the origin moves left and down
    ((0, 0, 0), (0.5, -0.5, 0), (0, 0, 0), (C - F * 0.5 / 3, C + F * 0.5 / 3)),
    # rotate 90 about y and translate (-3, 0, 3): the origin stays centred, seen from the side
    ((0, 90, 0), (-3, 0, 3), (0, 0, 0), (C, C)),
    ((0, 90, 0), (-3, 0, 3), (0, 0, 1), (C + F / 3, C)),
])
def test_relative_camera_known_points(rotation, translation, point, expected):
    cam = relative_camera(rotation, translation, base_distance=3.0, fov=FOV, image_size=SIZE)
    uv, _ = project(cam, point)
    assert uv == pytest.approx(list(expected), abs=1e-3)


def test_relative_side_view_looks_from_the_side():
    cam = relative_camera((0, 90, 0), (-3, 0, 3), base_distance=3.0, fov=FOV, image_size=SIZE)
    centre = cam.centers()[0]
    assert abs(abs(float(centre[0])) - 3.0) < 1e-5 and abs(float(centre[2])) < 1e-5


def test_turntable_orbits_at_distance_and_elevation():
    cams = turntable(8, distance=2.5, elevation=30.0, fov=50.0, image_size=32)
    centres = cams.centers()
    torch.testing.assert_close(centres.norm(dim=-1), torch.full((8,), 2.5))
    torch.testing.assert_close(centres[:, 1], torch.full((8,), 2.5 * math.sin(math.radians(30))))
    uv, _ = cams.project(torch.zeros(1, 3))
    torch.testing.assert_close(uv, torch.full((8, 1, 2), 16.0))
    with pytest.raises(UserError):
        turntable(0, 2.5, 0.0, 50.0, 32)


def test_dolly_distance_keeps_sphere_silhouette_fraction():
    fov = torch.tensor([10.0, 40.0, 90.0, 120.0], dtype=torch.float64)
    d = dolly_distance(fov, radius=1.0, fraction=0.4)
    # silhouette half-angle asin(r/d); its tangent relative to tan(fov/2) is the fraction
    frac = torch.tan(torch.asin(1.0 / d)) / torch.tan(torch.deg2rad(fov) / 2)
    torch.testing.assert_close(frac, torch.full_like(frac, 0.4))
    with pytest.raises(UserError):
        dolly_zoom(4, (10.0, 200.0), 1.0, 0.4, 32)


def test_gradient_colors_blend_along_axis():
    mesh = cube(size=2.0)
    out = gradient_colors(mesh, "z", (0, 0, 1), (1, 0, 0))
    z = mesh.verts[:, 2]
    torch.testing.assert_close(out.vert_colors[z.argmin()], torch.tensor([0.0, 0.0, 1.0]))
    torch.testing.assert_close(out.vert_colors[z.argmax()], torch.tensor([1.0, 0.0, 0.0]))
    with pytest.raises(UserError):
        gradient_colors(mesh, "w")


def test_turntable_azimuth_offset_puts_views_between_the_frames():
    """sds_mesh / sds_nerf watch their runs on views half a step off the reported turntable:
    4 views offset by 7.5 degrees lie at azimuths 7.5 + 90 k, none on the 24 frames (15 degree steps)."""
    frames = turntable(24, 3.0, 0.0, 40.0, 16)
    views = turntable(4, 3.0, 0.0, 40.0, 16, azimuth_offset=7.5)
    azimuth = lambda c: torch.atan2(c[:, 0], c[:, 2]) * 180.0 / math.pi   # noqa: E731 (about +Y, elevation 0)
    a_f, a_v = azimuth(frames.centers()), azimuth(views.centers())
    steps = ((a_v - a_f[0]) % 360.0) / 15.0
    assert torch.allclose(steps - steps.floor(), torch.full_like(steps, 0.5), atol=1e-4), steps
    assert torch.allclose((a_v[1:] - a_v[:-1]) % 360.0, torch.full((3,), 90.0), atol=1e-3)
