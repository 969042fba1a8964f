"""Procedural meshes and built-in scenes: closed, outward, right sizes, clear errors."""

from __future__ import annotations

import math

import pytest
import torch

from l3d_app.data.scenes import SCENES, builtin_scene, mesh_file, orientation_scene
from l3d_app.errors import UserError
from l3d_app.geometry import primitives as P
from l3d_app.registry import DATASETS


def signed_volume(mesh) -> float:
    """Divergence theorem: sum of det(v0, v1, v2) / 6 (positive when faces point out)."""
    return float(torch.linalg.det(mesh.verts.double()[mesh.faces]).sum() / 6.0)


def assert_closed_and_consistent(mesh) -> None:
    """Every undirected edge is used by exactly two faces, once in each direction."""
    f = mesh.faces
    directed = f[:, [[0, 1], [1, 2], [2, 0]]].reshape(-1, 2)
    n = mesh.num_verts
    key = directed[:, 0] * n + directed[:, 1]
    reverse = directed[:, 1] * n + directed[:, 0]
    assert key.unique().numel() == key.numel(), "a directed edge is used twice (flipped face)"
    assert torch.isin(reverse, key).all(), "an edge has no opposite half-edge (open or flipped)"
    undirected = directed.sort(dim=1).values
    _, counts = torch.unique(undirected, dim=0, return_counts=True)
    assert (counts == 2).all()


# name, mesh, analytic volume, relative tolerance of the discretisation
CLOSED = [
    ("tetrahedron", lambda: P.tetrahedron(1.3), (2 * math.sqrt(2) * 1.3 / math.sqrt(3)) ** 3 / (6 * math.sqrt(2)), 1e-6),
    ("cube", lambda: P.cube(2.0), 8.0, 1e-6),
    ("box", lambda: P.box((1, 2, 3), (0.5, 1.0, 2.0)), 1.0, 1e-6),
    ("icosphere", lambda: P.icosphere(3, 1.5), 4 / 3 * math.pi * 1.5 ** 3, 0.01),
    ("uv_sphere", lambda: P.uv_sphere(24, 48, 0.5), 4 / 3 * math.pi * 0.5 ** 3, 0.01),
    ("torus", lambda: P.torus(0.7, 0.3, 48, 24), 2 * math.pi ** 2 * 0.7 * 0.3 ** 2, 0.02),
    ("cylinder", lambda: P.cylinder(0.5, 2.0, 64), math.pi * 0.25 * 2.0, 0.005),
    ("cone", lambda: P.cone(0.5, 2.0, 64), math.pi * 0.25 * 2.0 / 3, 0.005),
]


@pytest.mark.parametrize("name,make,volume,rtol", CLOSED, ids=[c[0] for c in CLOSED])
def test_closed_outward_with_analytic_volume(name, make, volume, rtol):
    mesh = make()
    assert mesh.verts.dtype == torch.float32 and mesh.faces.dtype == torch.int64
    assert_closed_and_consistent(mesh)
    vol = signed_volume(mesh)
    assert vol > 0, f"{name} faces point inwards"
    assert vol == pytest.approx(volume, rel=rtol)


@pytest.mark.parametrize("make", [P.tetrahedron, P.cube, lambda: P.icosphere(2)])
def test_convex_shapes_have_every_face_pointing_away_from_centre(make):
    mesh = make()
    centroids = mesh.face_verts().mean(dim=1)
    assert (torch.sum(mesh.face_normals() * centroids, dim=-1) > 0).all()


@pytest.mark.parametrize("level", [0, 1, 2, 3, 4])
def test_icosphere_counts_radius_and_shared_vertices(level):
    mesh = P.icosphere(level, radius=2.5)
    assert mesh.num_verts == 10 * 4 ** level + 2
    assert mesh.num_faces == 20 * 4 ** level
    torch.testing.assert_close(mesh.verts.norm(dim=-1), torch.full((mesh.num_verts,), 2.5), rtol=1e-6, atol=0)
    assert torch.unique(mesh.verts, dim=0).shape[0] == mesh.num_verts  # no duplicated midpoints
    assert_closed_and_consistent(mesh)


def test_icosphere_volume_converges_to_the_sphere():
    errors = [abs(signed_volume(P.icosphere(k)) - 4 / 3 * math.pi) for k in range(5)]
    assert all(b < a / 3 for a, b in zip(errors, errors[1:]))  # ~4x smaller per level


def test_plane_is_open_and_faces_up():
    mesh = P.plane(size=3.0, n=4)
    assert (mesh.num_verts, mesh.num_faces) == (25, 32)
    torch.testing.assert_close(mesh.face_normals(), torch.tensor([[0.0, 1.0, 0.0]]).expand(32, 3))
    assert mesh.face_areas().sum().item() == pytest.approx(9.0)


def test_colour_argument_and_join():
    a = P.cube(1.0, color=(1.0, 0.0, 0.0))
    b = P.tetrahedron(0.5, color=(0.0, 0.0, 1.0))
    assert (a.vert_colors == torch.tensor([1.0, 0.0, 0.0])).all()
    joined = P.join([a, b])
    assert (joined.num_verts, joined.num_faces) == (12, 16)
    assert (joined.faces[12:] - 8 == b.faces).all()
    assert signed_volume(joined) == pytest.approx(signed_volume(a) + signed_volume(b))
    assert (joined.vert_colors[8:] == torch.tensor([0.0, 0.0, 1.0])).all()
    assert P.join([a, P.cube(1.0)]).vert_colors is None  # not every part has colours


@pytest.mark.parametrize("call", [
    lambda: P.icosphere(-1), lambda: P.icosphere(1.5), lambda: P.cube(0.0),
    lambda: P.torus(0.3, 0.5), lambda: P.uv_sphere(1, 8), lambda: P.cube(1.0, color=(2, 0, 0)),
])
def test_bad_arguments_are_user_errors(call):
    with pytest.raises(UserError):
        call()


# ----------------------------------------------------------------------------- scenes
def test_orientation_scene_frames_and_colours_the_axes():
    mesh = orientation_scene()
    assert 2000 <= mesh.num_faces <= 8000
    assert mesh.verts.norm(dim=-1).max() <= 1.0
    assert mesh.vert_colors is not None and 0 <= mesh.vert_colors.min() and mesh.vert_colors.max() <= 1
    assert_closed_and_consistent(mesh)  # disjoint closed parts
    assert signed_volume(mesh) > 0
    # the extreme vertex along +X / +Y / +Z is the tip of the red / green / blue arrow
    for axis in range(3):
        tip = mesh.vert_colors[mesh.verts[:, axis].argmax()]
        assert tip.argmax().item() == axis, f"tip along axis {axis} has colour {tip.tolist()}"
    # the yellow letter stands in the -X, -Z quadrant (asymmetric, reads from +Z)
    yellow = (mesh.vert_colors[:, 0] > 0.9) & (mesh.vert_colors[:, 2] < 0.5)
    assert mesh.verts[yellow, 0].max() < 0 and mesh.verts[yellow, 2].max() < 0


@pytest.mark.parametrize("scene", sorted(SCENES))
def test_every_builtin_scene_builds_through_the_registry(scene):
    mesh = DATASETS.build({"name": "builtin", "scene": scene, "normalize": True})
    assert mesh.verts.norm(dim=-1).max().item() == pytest.approx(1.0, rel=1e-5)
    assert mesh.vert_colors is not None


def test_unknown_builtin_scene_lists_the_known_ones():
    with pytest.raises(UserError) as err:
        builtin_scene("teapot")
    for name in ("orientation", "cube", "icosphere", "torus", "tetrahedron"):
        assert name in str(err.value)


@pytest.mark.parametrize("path", [None, "", "  "])
def test_mesh_source_needs_a_path(path):
    with pytest.raises(UserError, match="data.path"):
        mesh_file(path)


def test_mesh_source_from_registry_without_path_is_a_user_error():
    with pytest.raises(UserError, match="data.path"):
        DATASETS.build({"name": "mesh"})


def test_builtin_tetrahedron_and_cube_counts():
    tetra, box = builtin_scene("tetrahedron"), builtin_scene("cube")
    assert (tetra.num_verts, tetra.num_faces) == (4, 4)
    assert (box.num_verts, box.num_faces) == (8, 12)
