"""data=nerfstudio: shared and per-frame intrinsics, distortion undistorted at load, split files,
applied_transform and the ply points mapped back, bad poses named."""

import json
from dataclasses import replace

import imageio.v2 as imageio
import numpy as np
import pytest
import torch

from colmap_writer import distort_np, pattern, undistort_np
from l3d_app.data.nerfstudio import nerfstudio
from l3d_app.errors import UserError
from l3d_app.geometry.cameras import look_at_cameras, to_opengl_c2w

W, H = 40, 30
DIST = dict(k1=-0.15, k2=0.03, k3=0.0, k4=0.0, p1=0.01, p2=-0.008)


def write_ns(root, n=10, per_frame_focal=None, dist=None, split_files=False, applied=None, ply=False):
    cams = look_at_cameras(3.0, torch.linspace(-5, 45, n), torch.arange(n) * 360.0 / n, 50.0, W)
    c2w = to_opengl_c2w(cams.to(dtype=torch.float64)).numpy()
    shared = {"camera_model": "OPENCV", "fl_x": 30.0, "fl_y": 31.0, "cx": W / 2 + 0.5, "cy": H / 2 - 0.5, "w": W, "h": H}
    d = dist or {}
    shared.update(d)
    frames, K = [], []
    (root / "images").mkdir(parents=True, exist_ok=True)
    for i in range(n):
        fr = {"file_path": f"images/frame_{i:05d}.png", "transform_matrix": c2w[i].tolist()}
        fx, fy, cx, cy = shared["fl_x"], shared["fl_y"], shared["cx"], shared["cy"]
        if per_frame_focal and i in per_frame_focal:
            fr["fl_x"] = fr["fl_y"] = per_frame_focal[i]
            fx = fy = per_frame_focal[i]
        K.append((fx, fy, cx, cy))
        v, u = np.meshgrid(np.arange(H) + 0.5, np.arange(W) + 0.5, indexing="ij")
        xu, yu = undistort_np((u - cx) / fx, (v - cy) / fy, d.get("k1", 0), d.get("k2", 0), d.get("p1", 0),
                              d.get("p2", 0))
        imageio.imwrite(root / fr["file_path"], np.round(pattern(xu, yu) * 255).astype(np.uint8))
        frames.append(fr)
    meta = {**shared, "frames": frames[::-1]}          # file order differs from sorted order
    if split_files:
        meta["train_filenames"] = [f"images/frame_{i:05d}.png" for i in range(n) if i % 3]
        meta["val_filenames"] = ["./images/frame_00003.png"]
        meta["test_filenames"] = ["images/frame_00000.png", "images/frame_00006.png"]
    if applied is not None:
        meta["applied_transform"] = applied[:3].tolist()
    pts = np.random.default_rng(0).normal(size=(50, 3)) * 0.4
    if ply:
        import trimesh

        cols = np.random.default_rng(1).integers(0, 256, (50, 4)).astype(np.uint8)
        cols[:, 3] = 255
        trimesh.PointCloud(pts, colors=cols).export(root / "sparse_pc.ply")
        meta["ply_file_path"] = "sparse_pc.ply"
        pts = (pts, cols[:, :3] / 255.0)
    (root / "transforms.json").write_text(json.dumps(meta))
    return cams, np.array(K), pts


def test_cameras_intrinsics_and_undistortion(tmp_path):
    cams, K, _ = write_ns(tmp_path, per_frame_focal={4: 27.0}, dist=DIST)
    d = nerfstudio(str(tmp_path), normalize=False, test_every=0, val_every=0)
    torch.testing.assert_close(d.cameras.R, cams.R, atol=1e-5, rtol=0)
    torch.testing.assert_close(d.cameras.t, cams.t, atol=1e-5, rtol=0)
    torch.testing.assert_close(d.cameras.fx.double(), torch.from_numpy(K[:, 0]), atol=1e-5, rtol=0)
    torch.testing.assert_close(d.cameras.fy.double(), torch.from_numpy(K[:, 1]), atol=1e-5, rtol=0)
    assert float(d.cameras.fx[4]) == 27.0 and float(d.cameras.fy[3]) == 31.0
    v, u = np.meshgrid(np.arange(H) + 0.5, np.arange(W) + 0.5, indexing="ij")
    for i in range(len(K)):
        ref = pattern((u - K[i, 2]) / K[i, 0], (v - K[i, 3]) / K[i, 1])
        assert np.abs(d.images[i].numpy() - ref)[3:-3, 3:-3].max() < 0.02
    raw = imageio.imread(tmp_path / "images" / "frame_00000.png") / 255.0
    ref = pattern((u - K[0, 2]) / K[0, 0], (v - K[0, 3]) / K[0, 1])
    assert np.abs(raw - ref)[3:-3, 3:-3].max() > 0.06          # distortion visible before undistortion
    # a world point projects where the distorted observation model says
    p = torch.tensor([[0.2, -0.1, 0.3]], dtype=torch.float64)
    uv, _ = d.cameras.to(dtype=torch.float64).project(p)
    pc = cams.to(dtype=torch.float64).world_to_view(p)
    xd, _ = distort_np((pc[..., 0] / pc[..., 2]).numpy(), (pc[..., 1] / pc[..., 2]).numpy(), -0.15, 0.03, 0.01, -0.008)
    x_from_uv = (uv[..., 0].numpy() - K[:, 2:3]) / K[:, 0:1]
    np.testing.assert_allclose(distort_np(x_from_uv, (pc[..., 1] / pc[..., 2]).numpy(), -0.15, 0.03, 0.01, -0.008)[0],
                               xd, atol=1e-6)


def test_split_files_and_default_splits(tmp_path):
    write_ns(tmp_path / "a", split_files=True)
    d = nerfstudio(str(tmp_path / "a"))
    assert d.test.tolist() == [0, 6] and d.val.tolist() == [3] and d.train.tolist() == [1, 2, 4, 5, 7, 8]
    write_ns(tmp_path / "b", n=17)
    d = nerfstudio(str(tmp_path / "b"), val_every=4)
    assert d.test.tolist() == [0, 8, 16] and d.val.tolist() == [4, 9, 13]


def test_split_files_are_made_disjoint(tmp_path, capsys):
    """nerfstudio's own files list the same frames as val and test: validation is then carved from
    the training views (a note says so), never read off the test views; a frame listed for training
    and testing is refused; MultiViewData itself refuses overlapping splits."""
    write_ns(tmp_path / "a", split_files=True)
    meta = json.loads((tmp_path / "a" / "transforms.json").read_text())
    meta["val_filenames"] = list(meta["test_filenames"])
    (tmp_path / "a" / "transforms.json").write_text(json.dumps(meta))
    d = nerfstudio(str(tmp_path / "a"), val_every=3)
    assert d.test.tolist() == [0, 6] and d.val.tolist() == [4, 8] and d.train.tolist() == [1, 2, 5, 7]
    assert "2 validation views are also test views; validation carved from the training views" in capsys.readouterr().err
    meta["val_filenames"] = [meta["test_filenames"][0], "images/frame_00003.png"]      # one shared: dropped
    (tmp_path / "a" / "transforms.json").write_text(json.dumps(meta))
    assert nerfstudio(str(tmp_path / "a")).val.tolist() == [3]
    meta["train_filenames"].append("images/frame_00006.png")
    (tmp_path / "a" / "transforms.json").write_text(json.dumps(meta))
    with pytest.raises(UserError, match=r"views \[6\] are listed for both training and testing"):
        nerfstudio(str(tmp_path / "a"))
    with pytest.raises(UserError, match=r"views \[4\] are in both the val and the test split"):
        replace(d, test=torch.tensor([0, 4]))


def test_applied_transform_and_ply_points_map_back(tmp_path):
    a = np.eye(4)
    a[:3, :3] = np.array([[1, 0, 0], [0, 0, 1], [0, -1, 0]])     # nerfstudio's usual axis swap
    a[:3, 3] = (0.1, 0.2, -0.3)
    cams, _, (pts, cols) = write_ns(tmp_path, applied=a, ply=True)
    d = nerfstudio(str(tmp_path))
    M = d.source_from_world
    back = d.points.double() @ M[:3, :3].T + M[:3, 3]
    expect = (pts - a[:3, 3]) @ a[:3, :3]                           # A^-1 x for a rigid A
    np.testing.assert_allclose(back.numpy(), expect, atol=1e-5)
    np.testing.assert_allclose(d.point_colors.numpy(), cols, atol=1e-6)
    centres = d.cameras.centers().double() @ M[:3, :3].T + M[:3, 3]
    np.testing.assert_allclose(centres.numpy(), (cams.centers().double().numpy() - a[:3, 3]) @ a[:3, :3], atol=1e-4)
    # box from the points; up = cameras' mean up (+Y here)
    assert bool((d.scene_box[0] < d.points.median(0).values).all()) and float(d.up[1]) > 0.9


@pytest.mark.parametrize("bad, problem", [("nan", "non-finite"), ("scale", "not rigid")])
def test_bad_pose_names_the_frame(tmp_path, bad, problem):
    write_ns(tmp_path)
    meta = json.loads((tmp_path / "transforms.json").read_text())
    fr = [f for f in meta["frames"] if f["file_path"].endswith("00002.png")][0]
    m = np.array(fr["transform_matrix"])
    if bad == "nan":
        m[0, 3] = np.nan
    else:
        m[:3, :3] *= 2
    fr["transform_matrix"] = m.tolist()
    (tmp_path / "transforms.json").write_text(json.dumps(meta))
    with pytest.raises(UserError, match=rf"transforms.json: frame images/frame_00002.png: .*{problem}"):
        nerfstudio(str(tmp_path))


def test_unsupported_model_and_missing_intrinsics(tmp_path):
    write_ns(tmp_path)
    meta = json.loads((tmp_path / "transforms.json").read_text())
    meta["camera_model"] = "OPENCV_FISHEYE"
    (tmp_path / "transforms.json").write_text(json.dumps(meta))
    with pytest.raises(UserError, match="camera_model OPENCV_FISHEYE is not supported"):
        nerfstudio(str(tmp_path))
    meta["camera_model"] = "OPENCV"
    del meta["fl_y"]
    (tmp_path / "transforms.json").write_text(json.dumps(meta))
    with pytest.raises(UserError, match="has no 'fl_y'"):
        nerfstudio(str(tmp_path))


def test_box_without_points_is_centred_where_the_cameras_look(tmp_path):
    """No point cloud: the box is centred on the point the optical axes meet at (the look-at target of
    write_ns's cameras, the source origin), not on the cameras' mean, which lies above it here."""
    from l3d_app.data.captures import focus_point, scene_box
    from l3d_app.geometry.cameras import Cameras

    write_ns(tmp_path)                                      # cameras at elevations -5..45, looking at 0
    d = nerfstudio(str(tmp_path))
    M = d.source_from_world
    target = (torch.zeros(3, dtype=torch.float64) - M[:3, 3]) @ torch.linalg.inv(M[:3, :3]).T   # source 0 -> ours
    centre = d.scene_box.double().mean(0)
    torch.testing.assert_close(centre, target, atol=1e-4, rtol=0)
    assert float(target.norm()) > 0.3                       # the cameras' mean is not the target
    # parallel axes (a forward-facing capture): no focus point; the box stays about the origin
    one = torch.ones(6)
    flat = Cameras(torch.eye(3).expand(6, 3, 3).clone(), torch.randn(6, 3, generator=torch.Generator().manual_seed(0)),
                   30 * one, 30 * one, 20 * one, 15 * one, W, H)
    assert focus_point(flat) is None
    torch.testing.assert_close(scene_box(None, 3.0, cameras=flat), torch.tensor([[-1.5] * 3, [1.5] * 3]))
    # the point behind the cameras (all looking away from it) is refused too
    cams = look_at_cameras(3.0, torch.full((8,), 10.0), torch.arange(8) * 45.0, 50.0, W)
    away = Cameras(cams.R, -cams.t, cams.fx, cams.fy, cams.cx, cams.cy, cams.width, cams.height)
    torch.testing.assert_close(focus_point(cams), torch.zeros(3, dtype=torch.float64), atol=1e-5, rtol=0)
    assert focus_point(away) is None
