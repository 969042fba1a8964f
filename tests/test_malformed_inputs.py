"""Malformed files and knobs found by a bad-input audit (2026-11-27): each is one UserError
naming the file and the problem, never a ZeroDivisionError, a 70 TiB allocation, a
quantile of nothing, an unpickling traceback or a run that trains on a NaN focal length."""

from __future__ import annotations

import json
import struct

import numpy as np
import pytest
import torch
from test_multiview_faults import write_blender

from l3d_app.app import run_task
from l3d_app.data.bunny import bunny_points
from l3d_app.data.colmap_model import ColmapCamera, read_images_bin, read_images_txt, read_points3d_bin
from l3d_app.data.nerf_formats import blender
from l3d_app.data.nerfstudio import nerfstudio
from l3d_app.errors import UserError
from l3d_app.geometry.gaussian_ply import load_gaussian_ply, save_gaussian_ply
from l3d_app.runtime.training import read_checkpoint


def _ns(root, meta):
    root.mkdir(parents=True, exist_ok=True)
    (root / "transforms.json").write_text(json.dumps(meta))
    return str(root)


def test_nerfstudio_top_level_list_and_zero_image_size(tmp_path):
    with pytest.raises(UserError, match="must hold a JSON object"):
        nerfstudio(_ns(tmp_path / "a", []))
    frame = {"file_path": "images/f.png", "transform_matrix": np.eye(4).tolist()}
    meta = {"fl_x": 10.0, "fl_y": 10.0, "cx": 8.0, "cy": 8.0, "w": 0, "h": 16, "frames": [frame]}
    with pytest.raises(UserError, match=r"image size w x h must be positive, got 0 x 16"):
        nerfstudio(_ns(tmp_path / "b", meta))


@pytest.mark.parametrize("width,params,problem", [
    (0, [10.0, 10.0, 8.0, 8.0], "image size must be positive"),
    (16, [float("nan"), 10.0, 8.0, 8.0], "finite with positive focal lengths"),
    (16, [-10.0, 10.0, 8.0, 8.0], "finite with positive focal lengths"),
])
def test_colmap_camera_size_and_parameters(width, params, problem):
    with pytest.raises(UserError, match=problem):
        ColmapCamera(1, "PINHOLE", width, 16, np.array(params)).intrinsics()
    assert ColmapCamera(1, "PINHOLE", 16, 16, np.array([10.0, 11.0, 8.0, 7.0])).intrinsics()[:4] == (10.0, 11.0, 8.0, 7.0)


def test_colmap_point_count_the_file_cannot_hold_is_refused_before_allocating(tmp_path):
    path = tmp_path / "points3D.bin"
    path.write_bytes(struct.pack("<Q", 10 ** 13) + bytes(64))       # 10^13 points in 72 bytes
    with pytest.raises(UserError, match="do not fit in 72 bytes"):
        read_points3d_bin(path)


def test_colmap_image_name_not_utf8_and_text_id_not_an_integer(tmp_path):
    head = struct.pack("<i4d3di", 1, 1, 0, 0, 0, 0, 0, 0, 1)
    path = tmp_path / "images.bin"
    path.write_bytes(struct.pack("<Q", 1) + head + b"\xa5\xff\x00" + struct.pack("<Q", 0))
    with pytest.raises(UserError, match="not UTF-8 text"):
        read_images_bin(path)
    txt = tmp_path / "images.txt"
    txt.write_text("x1 1 0 0 0 0 0 0 1 a.png\n\n")
    with pytest.raises(UserError, match=r"images.txt: line 0: invalid literal for int\(\)"):
        read_images_txt(txt)


@pytest.mark.parametrize("fov", [0.0, float("nan"), 3.5])
def test_blender_field_of_view_outside_0_pi(tmp_path, fov):
    write_blender(tmp_path)
    meta = json.loads((tmp_path / "transforms_train.json").read_text())
    (tmp_path / "transforms_train.json").write_text(json.dumps({**meta, "camera_angle_x": fov}))
    with pytest.raises(UserError, match=r"camera_angle_x must be a field of view in \(0, pi\)"):
        blender(str(tmp_path))


def test_blender_ragged_matrix_names_the_frame(tmp_path):
    write_blender(tmp_path)
    meta = json.loads((tmp_path / "transforms_train.json").read_text())
    meta["frames"][0]["transform_matrix"] = [[1, 0, 0, 0], [0, 1]]
    (tmp_path / "transforms_train.json").write_text(json.dumps(meta))
    with pytest.raises(UserError, match="frame 0 transform_matrix is not a 4x4 list of numbers"):
        blender(str(tmp_path))


def _ply(tmp_path, n=5, rest=15):
    g = torch.Generator().manual_seed(0)
    path = save_gaussian_ply(tmp_path / "g.ply", torch.randn(n, 3, generator=g), torch.zeros(n, 3),
                             torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1), torch.zeros(n),
                             torch.rand(n, 1, 3, generator=g), torch.zeros(n, rest, 3))
    return path, path.read_bytes()


def test_gaussian_ply_zero_truncated_headerless_non_finite_and_odd_sh(tmp_path):
    path, raw = _ply(tmp_path)
    assert load_gaussian_ply(path)["means"].shape == (5, 3)               # the valid file reads
    head, body = raw.split(b"end_header\n")
    cases = {
        "holds no Gaussians": head.replace(b"element vertex 5", b"element vertex 0") + b"end_header\n",
        "file is truncated": raw[:-10],
        "no 'element vertex' line": head.replace(b"element vertex 5\n", b"") + b"end_header\n" + body,
        "f_rest properties; a 3DGS PLY has 0, 9, 24 or 45":
            head.replace(b"property float f_rest_44\n", b"") + b"end_header\n" + body,
    }
    nan_body = bytearray(body)
    nan_body[0:4] = struct.pack("<f", float("nan"))                     # the first splat's x
    cases["non-finite values in ['x']"] = head + b"end_header\n" + bytes(nan_body)
    for problem, data in cases.items():
        path.write_bytes(data)
        with pytest.raises(UserError, match=problem.replace("(", r"\(").replace("[", r"\[")):
            load_gaussian_ply(path)


@pytest.mark.parametrize("content", [b"", b"not a checkpoint", None])
def test_unreadable_checkpoint(tmp_path, content):
    path = tmp_path / "checkpoint.pt"
    if content is None:
        torch.save({"step": 3}, path)                                  # a torch file, not ours
        match = "no 'trainable' state"
    else:
        path.write_bytes(content)
        match = "is not a readable checkpoint"
    with pytest.raises(UserError, match=match):
        read_checkpoint(path)


def test_bunny_npz_that_is_not_one(tmp_path):
    (tmp_path / "empty.npz").write_bytes(b"")
    with pytest.raises(UserError, match="is not a readable .npz"):
        bunny_points(str(tmp_path / "empty.npz"))


@pytest.mark.parametrize("knob", ["num_frames=0", "num_frames=-3", "image_size=0"])
def test_gs_render_refuses_non_positive_sizes_before_reading_the_ply(compose, tmp_path, knob):
    with pytest.raises(UserError, match="must be a positive number"):
        run_task(compose("task=gs_render", f"ply={tmp_path / 'nothing.ply'}", knob, "tensorboard=false"),
                 out_dir=tmp_path / "run")
