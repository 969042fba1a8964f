"""Dolly zoom framed on a scene's largest part, with its projected width held by the extent solver."""

import json
import math

import pytest
import torch

from conftest import course_data
from l3d_app.app import run_task
from l3d_app.geometry.dolly_framing import extent_distances
from l3d_app.geometry.mesh_io import save_mesh
from l3d_app.geometry.mesh_parts import face_components, largest_part_mask, submesh
from l3d_app.geometry.primitives import box, join, plane, transformed


def two_part_mesh():
    """An elongated box (12 faces, the subject) standing on a wide ground plane (8 faces)."""
    subject = box((0.0, 0.0, 0.0), (0.8, 0.5, 1.4), color=(0.8, 0.3, 0.2))
    ground = transformed(plane(6.0, n=2, color=(0.3, 0.6, 0.3)), translation=(0.0, -0.25, 0.0))
    return join([ground, subject])


def test_components_largest_part_and_submesh():
    mesh = two_part_mesh()
    labels = face_components(mesh.faces, mesh.num_verts)
    assert sorted(torch.unique(labels, return_counts=True)[1].tolist()) == [8, 12]
    part = submesh(mesh, largest_part_mask(mesh))
    assert part.num_faces == 12 and part.num_verts == 8
    lo, hi = part.bounds()
    assert hi.tolist() == pytest.approx([0.4, 0.25, 0.7]) and lo.tolist() == pytest.approx([-0.4, -0.25, -0.7])
    # a chain of faces whose labels must travel far: one strip, one part
    n = 200
    strip = torch.stack([torch.arange(n), torch.arange(n) + 1, torch.arange(n) + 2], dim=1)
    assert torch.unique(face_components(strip.flip(0), n + 2)).numel() == 1


def test_extent_distance_closed_form():
    # points (+-a, 0, +-c); camera on +Z looking at the origin: the near points (z = +c, camera depth
    # D - c) are the widest, extent = 2 a f / (D - c) = 2 fraction f tan(fov/2) -> D = c + a / (fraction tan)
    a, c, frac = 0.5, 0.3, 0.4
    pts = torch.tensor([[a, 0, c], [-a, 0, c], [a, 0, -c], [-a, 0, -c]], dtype=torch.float64)
    fov = torch.tensor([5.0, 60.0, 120.0], dtype=torch.float64)
    d = extent_distances(pts, fov, frac)
    expected = c + a / (frac * torch.tan(torch.deg2rad(fov) / 2))
    torch.testing.assert_close(d, expected, rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("framing, bound", [("extent", 0.02), ("sphere", None)])
def test_dolly_holds_the_largest_part_width(compose, tmp_path, framing, bound):
    path = save_mesh(two_part_mesh(), tmp_path / "scene.obj")
    cfg = compose("task=dolly", "data=mesh", f"data.path={path}", "data.normalize=false", "image_size=96",
                  "num_frames=5", "fov_start=5", "fov_end=120", "backdrop=false", "renderer.antialias=2",
                  f"framing={framing}", "print_fov=true", "elevation=20")
    run_task(cfg, out_dir=tmp_path / framing)
    m = json.loads((tmp_path / framing / "metrics.json").read_text())
    assert m["subject_faces"] == 12
    if bound is not None:
        assert m["subject_width_spread"] <= bound
        assert m["subject_width_px"] == pytest.approx(0.45 * 96, rel=0.03)
    else:  # the bounding sphere does not hold a box's width at wide angles: the reason for 'extent'
        assert m["subject_width_spread"] > 0.1


def test_dolly_on_the_course_cow_on_plane(compose, tmp_path):
    path = course_data("cow", "cow_on_plane.obj")
    cfg = compose("task=dolly", "data=mesh", f"data.path={path}", "image_size=96", "num_frames=4",
                  "fov_start=5", "fov_end=120", "backdrop=false", "renderer.antialias=2")
    run_task(cfg, out_dir=tmp_path)
    m = json.loads((tmp_path / "metrics.json").read_text())
    assert m["subject"] == "largest_part" and m["subject_faces"] == 5856   # the cow, not the plane
    assert m["subject_width_spread"] <= 0.02
