"""Mesh files: the course cow, round trips, the OBJ reader's corners, and clear errors."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from l3d_app.errors import UserError
from l3d_app.geometry import primitives as P
from l3d_app.geometry.mesh import Mesh
from l3d_app.geometry.mesh_io import SUPPORTED_EXTENSIONS, load_mesh, save_mesh

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


def cow_path(name: str = "cow.obj") -> Path:
    path = SHARED_DATA / "cow" / name
    if not path.exists():
        pytest.skip(f"course data not present: {path}")
    return path


def write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


def corner_uvs(mesh: Mesh) -> np.ndarray:
    """(F, 3, 2) texture coordinate at each face corner."""
    return mesh.verts_uvs[mesh.faces_uvs].numpy()


# ----------------------------------------------------------------------------- course cow
def test_cow_keeps_file_order_and_uv_seams():
    mesh = load_mesh(cow_path())
    assert (mesh.num_verts, mesh.num_faces) == (2930, 5856)
    assert mesh.verts_uvs.shape == (3225, 2) and mesh.faces_uvs.shape == (5856, 3)
    assert mesh.texture.shape == (1024, 1024, 3) and mesh.texture.dtype == torch.float32
    assert 0.0 <= mesh.texture.min() and mesh.texture.max() <= 1.0 and mesh.texture.std() > 0.05
    torch.testing.assert_close(mesh.verts[0], torch.tensor([0.348799, -0.334989, -0.0832331]))
    assert mesh.faces[0].tolist() == [738, 734, 735]  # "f 739/1 735/2 736/3"
    assert mesh.faces_uvs[0].tolist() == [0, 1, 2]
    # same geometry and the same UV at every face corner as trimesh's seam-splitting load
    split = load_mesh(cow_path(), keep_vertex_order=False)
    assert (split.num_verts, split.num_faces) == (3225, 5856)
    np.testing.assert_allclose(mesh.face_verts().numpy(), split.face_verts().numpy(), atol=1e-6)
    np.testing.assert_allclose(corner_uvs(mesh), corner_uvs(split), atol=1e-6)


def test_textured_obj_round_trip(tmp_path):
    cow = load_mesh(cow_path())
    out = save_mesh(cow, tmp_path / "sub" / "cow.obj")
    back = load_mesh(out)
    assert sorted(p.name for p in out.parent.iterdir()) == ["cow.mtl", "cow.obj", "cow_texture.png"]
    assert torch.equal(back.verts, cow.verts) and torch.equal(back.faces, cow.faces)
    assert torch.equal(back.faces_uvs, cow.faces_uvs) and torch.equal(back.verts_uvs, cow.verts_uvs)
    assert torch.equal(back.texture, cow.texture)  # 8-bit PNG in, 8-bit PNG out


# ----------------------------------------------------------------------------- round trips
@pytest.fixture
def coloured_sphere():
    mesh = P.icosphere(2, radius=0.7)
    mesh.vert_colors = torch.rand(mesh.num_verts, 3, generator=torch.Generator().manual_seed(0))
    return mesh


@pytest.mark.parametrize("ext,color_tol", [("obj", 1e-6), ("ply", 0.5 / 255 + 1e-6)])
def test_round_trip_positions_faces_colours(tmp_path, coloured_sphere, ext, color_tol):
    path = save_mesh(coloured_sphere, tmp_path / f"sphere.{ext}")
    back = load_mesh(path)
    assert torch.equal(back.verts, coloured_sphere.verts)  # float32 written exactly
    assert torch.equal(back.faces, coloured_sphere.faces)
    assert (back.vert_colors - coloured_sphere.vert_colors).abs().max() <= color_tol
    assert [p.name for p in tmp_path.iterdir()] == [path.name]  # no temporary file left


def test_save_replaces_an_existing_file_and_rejects_other_formats(tmp_path):
    path = tmp_path / "m.ply"
    save_mesh(P.icosphere(1), path)
    save_mesh(P.cube(), path)
    assert load_mesh(path).num_faces == 12
    with pytest.raises(UserError, match=r"\.obj, \.ply"):
        save_mesh(P.cube(), tmp_path / "m.stl")


def test_uv_seam_survives_obj_round_trip(tmp_path):
    # two triangles share an edge in 3D but not in UV space: 4 positions, 6 UVs
    texture = torch.arange(2 * 3 * 3, dtype=torch.float32).reshape(2, 3, 3) / 255.0
    mesh = Mesh(verts=torch.tensor([[0.0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]]),
                faces=torch.tensor([[0, 1, 2], [0, 2, 3]]),
                verts_uvs=torch.tensor([[0.0, 0], [0.5, 0], [0.5, 1], [0.5, 0.0], [1, 1], [0.5, 1]]),
                faces_uvs=torch.tensor([[0, 1, 2], [3, 4, 5]]), texture=texture)
    back = load_mesh(save_mesh(mesh, tmp_path / "seam.obj"))
    assert back.num_verts == 4
    assert torch.equal(back.faces_uvs, mesh.faces_uvs) and torch.equal(back.verts_uvs, mesh.verts_uvs)
    assert torch.equal(back.texture, texture)


# ----------------------------------------------------------------------------- OBJ reader
def test_obj_polygons_negative_indices_and_corner_forms(tmp_path):
    path = write(tmp_path / "poly.obj", """# comment
v 0 0 0
v 1 0 0
v 1 1 0
v 0 1 0
v 0.5 1.5 0
vn 0 0 1
f 1//1 2//1 3//1 5//1 4//1
f -5/ -3 -1
f 1/ 2 3
""")
    mesh = load_mesh(path)
    # pentagon fanned from its first corner, in file order, then two triangles
    assert mesh.faces.tolist() == [[0, 1, 2], [0, 2, 4], [0, 4, 3], [0, 2, 4], [0, 1, 2]]
    assert mesh.verts_uvs is None and mesh.vert_colors is None


def test_obj_vertex_colours_and_material_colours(tmp_path):
    coloured = load_mesh(write(tmp_path / "c.obj", "v 0 0 0 1 0 0\nv 1 0 0 0 255 0\nv 0 1 0 0 0 1\nf 1 2 3\n"))
    assert coloured.vert_colors is not None  # 0..255 values rescaled as a whole
    assert coloured.vert_colors.max() <= 1.0 and coloured.vert_colors[1, 1] == 1.0
    write(tmp_path / "kd.mtl", "newmtl a\nKd 1 0 0\nnewmtl b\nKd 0 0 1\n")
    mesh = load_mesh(write(tmp_path / "kd.obj", "mtllib kd.mtl\nv 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\n"
                                                 "usemtl a\nf 1 2 3\nusemtl b\nf 1 3 4\n"))
    torch.testing.assert_close(mesh.vert_colors, torch.tensor(
        [[0.5, 0, 0.5], [1, 0, 0], [0.5, 0, 0.5], [0, 0, 1]]))


def test_obj_with_two_texture_images_gets_an_atlas(tmp_path):
    from PIL import Image

    for name, rgb in (("r.png", (255, 0, 0)), ("b.png", (0, 0, 255))):
        Image.fromarray(np.full((4, 4, 3), rgb, np.uint8)).save(tmp_path / name)
    write(tmp_path / "two.mtl", "newmtl a\nmap_Kd r.png\nnewmtl b\nmap_Kd b.png\n")
    mesh = load_mesh(write(tmp_path / "two.obj", "mtllib two.mtl\nv 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\n"
                                                  "vt 0 0\nvt 1 0\nvt 1 1\nvt 0 1\n"
                                                  "usemtl a\nf 1/1 2/2 3/3\nusemtl b\nf 1/1 3/3 4/4\n"))
    assert mesh.num_faces == 2 and mesh.has_texture
    uv = mesh.verts_uvs[mesh.faces_uvs].mean(dim=1)  # sample each face's centre
    h, w, _ = mesh.texture.shape
    col = ((uv[:, 0] * w).long().clamp(0, w - 1))
    row = (((1 - uv[:, 1]) * h).long().clamp(0, h - 1))
    colours = mesh.texture[row, col]
    is_red_face = mesh.face_verts()[:, :, 1].sum(dim=1) < 1.5  # face "a" has y = 0, 0, 1
    assert torch.equal(colours[is_red_face][0], torch.tensor([1.0, 0, 0]))
    assert torch.equal(colours[~is_red_face][0], torch.tensor([0.0, 0, 1]))


# ----------------------------------------------------------------------------- other formats
def test_glb_scene_is_concatenated_with_transforms_and_colours(tmp_path):
    import trimesh  # a main dependency: missing is a failure, not a skip
    a = trimesh.creation.box()
    a.visual.vertex_colors = [255, 0, 0, 255]
    b = trimesh.creation.icosphere(subdivisions=1)
    b.visual.vertex_colors = [0, 0, 255, 255]
    scene = trimesh.Scene()
    scene.add_geometry(a)
    scene.add_geometry(b, transform=trimesh.transformations.translation_matrix([5.0, 0, 0]))
    scene.export(tmp_path / "two.glb")
    mesh = load_mesh(tmp_path / "two.glb", device="cpu")
    assert mesh.num_faces == 12 + 80 and mesh.num_verts == 8 + 42
    assert mesh.verts[:, 0].max().item() == pytest.approx(6.0, abs=1e-5)
    blue = mesh.vert_colors[:, 2] > 0.9
    assert blue.sum() == 42 and (mesh.verts[blue, 0] > 3.9).all()


def test_stl_triangle_soup_is_merged_and_off_reads(tmp_path):
    import trimesh  # a main dependency: missing is a failure, not a skip
    trimesh.creation.box().export(tmp_path / "box.stl")
    trimesh.creation.box().export(tmp_path / "box.off")
    assert (load_mesh(tmp_path / "box.stl").num_verts, load_mesh(tmp_path / "box.stl").num_faces) == (8, 12)
    assert load_mesh(tmp_path / "box.off").num_faces == 12


# ----------------------------------------------------------------------------- errors
MALFORMED = {
    "garbage.obj": ("hello world\nthis is not a mesh\n", "no faces"),
    "empty.obj": ("", "no faces"),
    "points.obj": ("v 0 0 0\nv 1 0 0\nv 0 1 0\n", "no faces"),
    "range.obj": ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 4\n", "out of range"),
    "zero.obj": ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 0 1 2\n", "out of range"),
    "uvrange.obj": ("v 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nf 1/1 2/2 3/1\n", "out of range"),
    "nan.obj": ("v 0 0 nan\nv 1 0 0\nv 0 1 0\nf 1 2 3\n", "NaN"),
    "huge.obj": ("v 0 0 1e39\nv 1 0 0\nv 0 1 0\nf 1 2 3\n", "NaN or Inf"),  # beyond float32
    "word.obj": ("v 0 0 x\nv 1 0 0\nv 0 1 0\nf 1 2 3\n", "not a number"),
    "face.obj": ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 a 3\n", "not an integer"),
    "edge.obj": ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2\n", "fewer than 3"),
    "garbage.ply": ("not a ply at all", "could not read"),
    "truncated.ply": ("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nend_header\n1\n", "could not read"),
    "range.off": ("OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 7\n", "PATH"),
    "garbage.glb": ("x" * 40, "could not read"),
    "garbage.gltf": ("{not json", "could not read"),
    "garbage.stl": ("solid x\nfoo bar\n", "no faces"),
}


@pytest.mark.parametrize("name", sorted(MALFORMED))
def test_malformed_files_are_one_line_user_errors(tmp_path, name):
    text, fragment = MALFORMED[name]
    path = write(tmp_path / name, text)
    with pytest.raises(UserError) as err:
        load_mesh(path)
    message = str(err.value)
    assert "\n" not in message and str(path) in message
    assert fragment == "PATH" or fragment in message


def test_point_cloud_ply_is_not_a_mesh(tmp_path):
    path = tmp_path / "cloud.ply"
    header = "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\nend_header\n"
    write(path, header + "0 0 0\n1 0 0\n0 1 0\n")
    with pytest.raises(UserError, match="point cloud"):
        load_mesh(path)


def test_missing_file_and_unsupported_extension(tmp_path):
    with pytest.raises(UserError, match="mesh file not found: .*nope.obj"):
        load_mesh(tmp_path / "nope.obj")
    with pytest.raises(UserError) as err:
        load_mesh(write(tmp_path / "cloud.xyz", "1 2 3\n"))
    assert all(ext in str(err.value) for ext in SUPPORTED_EXTENSIONS)
    with pytest.raises(UserError, match="directory"):
        load_mesh(tmp_path)


def test_mesh_source_normalises_into_the_unit_sphere(tmp_path):
    import l3d_app.data.scenes  # noqa: F401  (registers the "mesh" data source; alone, nothing else has)
    from l3d_app.registry import DATASETS

    path = save_mesh(P.transformed(P.torus(), translation=(10.0, -3.0, 2.0), scale=7.0), tmp_path / "t.ply")
    mesh = DATASETS.build({"name": "mesh", "path": str(path)})
    lo, hi = mesh.bounds()
    torch.testing.assert_close((lo + hi) / 2, torch.zeros(3), atol=1e-5, rtol=0)
    assert mesh.verts.norm(dim=-1).max().item() == pytest.approx(1.0, rel=1e-5)
