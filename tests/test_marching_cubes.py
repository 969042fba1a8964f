"""Marching cubes on analytic SDFs: world coordinates, outward winding, volumes, empty sets."""

import math

import pytest
import torch

from l3d_app.errors import UserError
from l3d_app.geometry.marching_cubes import evaluate_grid, grid_points, sdf_to_mesh
from l3d_app.geometry.sdf import Box, Sphere, Torus


def signed_volume(mesh):
    fv = mesh.verts.double()[mesh.faces]
    return float((fv[:, 0] * torch.cross(fv[:, 1], fv[:, 2], dim=-1)).sum() / 6)


def test_sphere_vertices_on_radius_and_outward():
    centre = torch.tensor([0.3, -0.2, 0.1])
    sdf = Sphere(0.6, tuple(centre.tolist()))
    mesh = sdf_to_mesh(sdf, 32)
    lo, hi = mesh.bounds()
    spacing = float((hi - lo).max()) / 31   # an upper bound of the grid spacing
    r = (mesh.verts - centre).norm(dim=-1)
    assert (r - 0.6).abs().max() < spacing
    vol = signed_volume(mesh)
    assert vol > 0 and vol == pytest.approx(4 / 3 * math.pi * 0.6 ** 3, rel=0.02)
    # right-hand face normals point away from the centre
    n = mesh.face_normals()
    out = (mesh.face_verts().mean(1) - centre)
    assert ((n * out).sum(-1) > 0).float().mean() > 0.99
    assert mesh.vert_colors is not None and mesh.vert_colors.min() >= 0


def test_explicit_bounds_world_coordinates():
    sdf = Box((0.5, 0.5, 0.5), center=(1.0, 2.0, 3.0))
    mesh = sdf_to_mesh(sdf, 41, bounds=((0.5, 1.5, 2.5), (1.5, 2.5, 3.5)), colors=None)
    lo, hi = mesh.bounds()
    assert torch.allclose(lo, torch.tensor([0.75, 1.75, 2.75]), atol=0.03)
    assert torch.allclose(hi, torch.tensor([1.25, 2.25, 3.25]), atol=0.03)
    assert signed_volume(mesh) == pytest.approx(0.125, rel=0.05)
    assert mesh.vert_colors is None


def test_torus_volume():
    mesh = sdf_to_mesh(Torus(0.7, 0.3), 64)
    assert signed_volume(mesh) == pytest.approx(2 * math.pi ** 2 * 0.7 * 0.3 ** 2, rel=0.02)


def test_level_offsets_the_surface():
    mesh = sdf_to_mesh(Sphere(0.5), 32, level=0.2)
    assert (mesh.verts.norm(dim=-1) - 0.7).abs().max() < 0.05


def test_chunked_grid_matches_full_grid():
    sdf = Torus(0.5, 0.2)
    lo, hi = (-1.0, -0.5, -1.0), (1.0, 0.5, 1.0)
    full = sdf(grid_points(lo, hi, 17))
    assert torch.equal(evaluate_grid(sdf, lo, hi, 17, chunk_size=1), full)
    # calls that split a 17 x 17 slab unevenly (100), span whole slabs and a part (500), and the default
    seen = []

    def counted(p):
        seen.append(tuple(p.shape))
        return sdf(p)

    for chunk in (100, 500, None):
        seen.clear()
        assert torch.equal(evaluate_grid(counted, lo, hi, 17, chunk_size=chunk), full)
        assert max(n for n, _ in seen) <= (chunk or 17 ** 3) and sum(n for n, _ in seen) == 17 ** 3


def test_empty_level_set_is_user_error():
    with pytest.raises(UserError, match="empty"):
        sdf_to_mesh(Sphere(0.5, (5.0, 0, 0)), 16, bounds=((-1, -1, -1), (1, 1, 1)))
    with pytest.raises(UserError, match="empty"):
        sdf_to_mesh(Sphere(3.0), 16, bounds=((-1, -1, -1), (1, 1, 1)))
    with pytest.raises(UserError):
        sdf_to_mesh(Sphere(0.5), 2)
