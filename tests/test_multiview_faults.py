"""Multi-view loaders: validation carved from train (never test), and bad poses in any camera
format stop the run with one line naming the file and frame (exit 2 through main.py)."""

import json
import os
import subprocess
import sys
from pathlib import Path

import imageio.v2 as imageio
import numpy as np
import pytest
import torch

from l3d_app.data.nerf_formats import blender
from l3d_app.data.nerf_views import carve_val
from l3d_app.errors import UserError
from l3d_app.geometry.cameras import look_at_cameras, to_opengl_c2w

REPO = Path(__file__).resolve().parents[1]


def write_blender(root, n_train=9, n_test=2, with_val=False, size=8):
    """A NeRF-synthetic folder: n_train / (2 val) / n_test RGBA views around the origin."""
    n = n_train + n_test + 2
    cams = look_at_cameras(4.0, 20.0, torch.arange(n) * 360.0 / n, 40.0, size)
    c2w = to_opengl_c2w(cams)
    fov_x = 2 * float(torch.atan(size / 2 / cams.fx[0]))
    counts = {"train": n_train, "val": 2, "test": n_test}
    i = 0
    for split in ("train", "val", "test"):
        frames = []
        for _ in range(counts[split]):
            (root / split).mkdir(parents=True, exist_ok=True)
            imageio.imwrite(root / split / f"r_{i}.png", np.full((size, size, 4), 200, np.uint8))
            frames.append({"file_path": f"./{split}/r_{i}", "transform_matrix": c2w[i].tolist()})
            i += 1
        if split != "val" or with_val:
            (root / f"transforms_{split}.json").write_text(json.dumps({"camera_angle_x": fov_x, "frames": frames}))
    return cams


def test_carve_val_takes_every_kth_training_view_and_never_empties_train():
    tr = torch.arange(10, 30)
    train, val = carve_val(tr, 8)
    assert val.tolist() == [17, 25] and len(train) == 18 and not set(train.tolist()) & set(val.tolist())
    assert carve_val(tr[:3], 8)[1].numel() == 0 and carve_val(tr, 0)[1].numel() == 0


def test_blender_val_from_json_or_carved_from_train_never_test(tmp_path):
    write_blender(tmp_path / "a", with_val=True)
    d = blender(str(tmp_path / "a"))
    assert d.train.tolist() == list(range(9)) and d.val.tolist() == [9, 10] and d.test.tolist() == [11, 12]
    write_blender(tmp_path / "b", with_val=False)
    d = blender(str(tmp_path / "b"), val_every=4)
    assert d.val.tolist() == [3, 7] and d.train.tolist() == [0, 1, 2, 4, 5, 6, 8] and d.test.tolist() == [9, 10]
    assert d.up.tolist() == [0.0, 0.0, 1.0] and d.points is None and d.mesh is None
    assert torch.equal(d.source_from_world, torch.eye(4, dtype=torch.float64))


def _corrupt(root, frame, value):
    meta = json.loads((root / "transforms_train.json").read_text())
    meta["frames"][frame]["transform_matrix"] = value(np.array(meta["frames"][frame]["transform_matrix"])).tolist()
    (root / "transforms_train.json").write_text(json.dumps(meta))


def _nan(m):
    m[1, 2] = float("nan")
    return m


def _scaled(m):
    m[:3, :3] *= 1.5
    return m


def _sheared(m):
    m[0, 1] += 0.2
    return m


@pytest.mark.parametrize("value, problem", [(_nan, "non-finite"), (_scaled, "not rigid"), (_sheared, "not rigid")])
def test_blender_bad_pose_names_file_and_frame(tmp_path, value, problem):
    write_blender(tmp_path)
    _corrupt(tmp_path, 4, value)
    with pytest.raises(UserError, match=rf"transforms_train.json: frame 4 .*{problem}"):
        blender(str(tmp_path))


def test_truck_bad_pose_names_the_frame(tmp_path):
    from l3d_app.data.nerf_formats import truck

    (tmp_path / "imgs").mkdir()
    (tmp_path / "poses").mkdir()
    for k in range(3):
        imageio.imwrite(tmp_path / "imgs" / f"frame{k:06d}.jpg", np.zeros((8, 8, 3), np.uint8))
        pose = np.concatenate([np.eye(3).reshape(-1), [0, 0, 3], [2, 2], [0, 0]])
        if k == 1:
            pose[9] = np.inf
        np.save(tmp_path / "poses" / f"frame{k:06d}.npy", pose)
    with pytest.raises(UserError, match="frame000001.npy: camera pose has a non-finite"):
        truck(str(tmp_path), test_indices=[2])


def test_nan_pose_through_main_exits_2_with_one_line(tmp_path):
    write_blender(tmp_path / "scene")
    _corrupt(tmp_path / "scene", 2, _nan)
    env = dict(os.environ, L3D_NO_PROGRESS="1")
    out = subprocess.run([sys.executable, str(REPO / "main.py"), "task=train_nerf", "data=blender",
                          f"data.root={tmp_path / 'scene'}", f"hydra.run.dir={tmp_path / 'run'}", "threads=1"],
                         cwd=REPO, capture_output=True, text=True, env=env, timeout=300)
    assert out.returncode == 2, out.stderr
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in out.stderr, out.stderr
    assert "transforms_train.json" in lines[0] and "frame 2" in lines[0] and "non-finite" in lines[0]
    assert not (tmp_path / "run" / "metrics.json").exists() and not (tmp_path / "run" / "checkpoint.pt").exists()


# ------------------------------------------------------------------ COLMAP
def _colmap_scene(root, n=4, model="PINHOLE", binary=True):
    from colmap_writer import write_scene

    cams = look_at_cameras(3.0, 15.0, torch.arange(n) * 90.0, 50.0, 16)
    K = np.tile([[14.0, 14.0, 8.0, 8.0]], (n, 1))
    pts = np.random.default_rng(0).normal(size=(30, 3)) * 0.3
    write_scene(root, cams.R.double().numpy(), cams.t.double().numpy(), K, (16, 16), pts,
                np.zeros((30, 3), np.uint8), model=model, binary=binary, text=not binary)
    return root


def test_colmap_missing_image(tmp_path):
    from l3d_app.data.colmap import colmap

    (_colmap_scene(tmp_path) / "images" / "img_002.png").unlink()
    with pytest.raises(UserError, match=r"image 'img_002.png' listed but missing"):
        colmap(str(tmp_path))


@pytest.mark.parametrize("binary", [True, False], ids=["bin", "txt"])
def test_colmap_unsupported_camera_model(tmp_path, binary):
    from l3d_app.data.colmap import colmap

    _colmap_scene(tmp_path, model="OPENCV_FISHEYE", binary=binary)
    with pytest.raises(UserError, match=r"camera 1: camera model OPENCV_FISHEYE is not supported"):
        colmap(str(tmp_path))


@pytest.mark.parametrize("name", ["cameras.bin", "images.bin", "points3D.bin"])
def test_colmap_truncated_bin(tmp_path, name):
    from l3d_app.data.colmap import colmap

    f = _colmap_scene(tmp_path) / "sparse" / "0" / name
    raw = f.read_bytes()
    f.write_bytes(raw[: len(raw) - 7])
    with pytest.raises(UserError, match=rf"{name}: file is truncated"):
        colmap(str(tmp_path))


@pytest.mark.parametrize("binary", [True, False], ids=["bin", "txt"])
def test_colmap_nan_in_points3d(tmp_path, binary):
    import struct

    from l3d_app.data.colmap import colmap

    sp = _colmap_scene(tmp_path, binary=binary) / "sparse" / "0"
    if binary:
        raw = bytearray((sp / "points3D.bin").read_bytes())
        raw[8 + 8 + 8:8 + 8 + 16] = struct.pack("<d", float("nan"))      # point 1's y
        (sp / "points3D.bin").write_bytes(bytes(raw))
    else:
        lines = (sp / "points3D.txt").read_text().splitlines()
        tok = lines[0].split()
        tok[2] = "nan"
        (sp / "points3D.txt").write_text("\n".join([" ".join(tok)] + lines[1:]) + "\n")
    with pytest.raises(UserError, match=r"points3D\.(bin|txt): point 1 has a non-finite coordinate"):
        colmap(str(tmp_path))


def test_colmap_mixed_sizes_under_one_camera(tmp_path):
    from l3d_app.data.colmap import colmap

    _colmap_scene(tmp_path, binary=False)
    sp = tmp_path / "sparse" / "0"
    imgs = sp / "images.txt"
    lines = imgs.read_text().splitlines()
    out = []
    for ln in lines:                                    # every image uses camera 1
        tok = ln.split()
        if len(tok) == 10:
            tok[8] = "1"
            ln = " ".join(tok)
        out.append(ln)
    imgs.write_text("\n".join(out) + "\n")
    imageio.imwrite(tmp_path / "images" / "img_003.png", np.zeros((20, 16, 3), np.uint8))
    with pytest.raises(UserError, match=r"img_003.png: image is 16x20 but img_000.png under the same camera 1 is 16x16"):
        colmap(str(tmp_path))


def test_colmap_nan_pose(tmp_path):
    from l3d_app.data.colmap import colmap

    _colmap_scene(tmp_path, binary=False)
    imgs = tmp_path / "sparse" / "0" / "images.txt"
    lines = imgs.read_text().splitlines()
    out = []
    for ln in lines:
        tok = ln.split()
        if len(tok) == 10 and tok[9] == "img_001.png":
            tok[6] = "nan"
            ln = " ".join(tok)
        out.append(ln)
    imgs.write_text("\n".join(out) + "\n")
    with pytest.raises(UserError, match=r"images.txt: img_001.png: camera pose has a non-finite"):
        colmap(str(tmp_path))


def test_blender_mesh_path_loads_the_true_surface_or_names_the_missing_file(tmp_path):
    import trimesh

    from l3d_app.data.nerf_formats import blender

    write_blender(tmp_path)
    box = trimesh.creation.box((0.4, 0.6, 0.8))
    box.export(tmp_path / "mesh.ply")
    data = blender(root=str(tmp_path), mesh_path="mesh.ply")
    ext = (data.mesh.verts.max(0).values - data.mesh.verts.min(0).values).tolist()
    assert ext == pytest.approx([0.4, 0.6, 0.8], abs=1e-6) and data.mesh.faces.shape == (12, 3)
    assert blender(root=str(tmp_path)).mesh is None
    with pytest.raises(UserError, match="no_such.ply"):
        blender(root=str(tmp_path), mesh_path="no_such.ply")
