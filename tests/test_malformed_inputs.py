"""Malformed files and knobs: each is one UserError
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
from l3d_app.runtime.checkpoints import read_checkpoint


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


@pytest.mark.parametrize("change, needle", [
    ({"fl_x": "ten"}, "frame images/f.png: fl_x must be a number, got 'ten'"),
    ({"k1": [0.1]}, "frame images/f.png: k1 must be a number, got \\[0.1\\]"),
    ({"frames": ["images/f.png"]}, "frame 0 must be an object with file_path and transform_matrix, got str"),
    ({"frames": [{"file_path": 3, "transform_matrix": np.eye(4).tolist()}]}, "frame 0 file_path must be a string, got 3"),
])
def test_nerfstudio_wrong_json_types_name_the_file_and_key(tmp_path, change, needle):
    """Wrong JSON types are one line naming the file, the frame and the key (they used to end in a bare
    ValueError from float() or a TypeError from sorting the frames)."""
    frame = {"file_path": "images/f.png", "transform_matrix": np.eye(4).tolist()}
    meta = {"fl_x": 10.0, "fl_y": 10.0, "cx": 8.0, "cy": 8.0, "w": 16, "h": 16, "frames": [frame], **change}
    with pytest.raises(UserError, match=f"transforms.json: {needle}"):
        nerfstudio(_ns(tmp_path / "a", meta))


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


@pytest.mark.parametrize("change, needle", [
    (lambda m: {**m, "camera_angle_x": "wide"}, "camera_angle_x must be a number, got 'wide'"),
    (lambda m: {**m, "camera_angle_x": None}, "camera_angle_x must be a number"),
    (lambda m: {**m, "frames": {"0": m["frames"][0]}}, "frames must be a list, got dict"),
    (lambda m: {**m, "frames": ["x.png"]}, "frame 0 must be an object with file_path and transform_matrix, got str"),
    (lambda m: {**m, "frames": [{**m["frames"][0], "file_path": 7}]}, "frame 0 file_path must be a string, got 7"),
    (lambda m: [m], "expected a JSON object with camera_angle_x and frames, got list"),
])
def test_blender_malformed_json_names_the_file_and_the_key(tmp_path, change, needle):
    """Wrong JSON types are one line naming the file and the key (they used to end in a bare
    ValueError or TypeError from float() or Path())"""
    write_blender(tmp_path)
    meta = json.loads((tmp_path / "transforms_train.json").read_text())
    (tmp_path / "transforms_train.json").write_text(json.dumps(change(meta)))
    with pytest.raises(UserError, match=f"transforms_train.json: {needle}"):
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
    with pytest.raises(UserError, match="cannot read .*empty.npz: EOFError"):
        bunny_points(str(tmp_path / "empty.npz"))


@pytest.mark.parametrize("knob", ["num_frames=0", "num_frames=-3", "image_size=0"])
def test_gs_render_refuses_non_positive_sizes_before_reading_the_ply(compose, tmp_path, knob):
    with pytest.raises(UserError, match="must be a positive number"):
        run_task(compose("task=gs_render", f"ply={tmp_path / 'nothing.ply'}", knob, "tensorboard=false"),
                 out_dir=tmp_path / "run")


# -- the other tasks and loaders --------------------------------------------------------------------

def test_array_files_numpy_cannot_read_are_one_user_error(tmp_path):
    from l3d_app.data.array_files import load_array_file
    for name, data in (("empty.npy", b""), ("garbage.npy", b"\x93NUMPY garbage"), ("empty.npz", b"")):
        (tmp_path / name).write_bytes(data)
        with pytest.raises(UserError, match=f"cannot read .*{name}"):
            load_array_file(tmp_path / name, allow_pickle=False)
    np.save(tmp_path / "ok.npy", np.arange(3.0))
    assert load_array_file(tmp_path / "ok.npy").tolist() == [0.0, 1.0, 2.0]


def test_tiny_nerf_zero_size_and_non_finite_images(tmp_path):
    from l3d_app.data.course_nerf import tiny_nerf
    poses = np.repeat(np.eye(4)[None], 3, 0)
    np.savez(tmp_path / "zero.npz", images=np.zeros((3, 0, 0, 3), np.float32), poses=poses, focal=np.float64(10))
    with pytest.raises(UserError, match="images are 0 x 0 pixels"):
        tiny_nerf(str(tmp_path / "zero.npz"))
    img = np.zeros((3, 4, 4, 3), np.float32)
    img[1, 2, 2, 0] = np.nan
    np.savez(tmp_path / "nan.npz", images=img, poses=poses, focal=np.float64(10))
    with pytest.raises(UserError, match="images contain NaN or Inf"):
        tiny_nerf(str(tmp_path / "nan.npz"))


def test_point_sets_need_points_per_cloud():
    from l3d_app.data.point_sets import PointSplit
    with pytest.raises(UserError, match="P >= 1"):
        PointSplit(torch.zeros(4, 0, 3), labels=torch.zeros(4, dtype=torch.long))


def test_course_rgbd_view_of_zero_pixels():
    from l3d_app.data.course_rgbd import view_cloud
    data = {"rgb1": np.zeros((0, 0, 3)), "depth1": np.zeros((0, 0)), "mask1": np.zeros((0, 0)), "cameras1": {}}
    with pytest.raises(UserError, match="view 1 has 0 x 0 pixels"):
        view_cloud(data, 1, "rgbd.pkl")


def test_depth_colormap_of_unmatched_stereo_depths():
    """+inf (zero disparity) and NaN take the top colour, the scale is the finite maximum: a
    valid stereo_depth run at 32 px crashed on an index of -2^63 before."""
    from l3d_app.render.volume.diagnostics import depth_colormap
    depth = torch.tensor([[1.0, 2.0], [float("inf"), float("nan")]])
    rgb = depth_colormap(depth)
    assert torch.isfinite(rgb).all()
    torch.testing.assert_close(rgb[1, 0], rgb[0, 1])               # inf -> the colour of the max (2.0)
    torch.testing.assert_close(rgb[1, 1], rgb[0, 1])
    assert not torch.equal(rgb[0, 0], rgb[0, 1])


def test_knobs_checked_before_training(compose):
    from l3d_app.render.mesh.renderer import MeshRenderer
    from l3d_app.tasks.common import require_mesh_formats, require_positive
    from l3d_app.tasks.svr_common import require_thresholds
    ok = compose("task=volsdf")
    require_mesh_formats(ok)
    for value, problem in (("[stl]", "non-empty list of ply, obj, glb"), ("[]", "non-empty list")):
        with pytest.raises(UserError, match=problem):
            require_mesh_formats(compose("task=volsdf", f"mesh_formats={value}"))
    with pytest.raises(UserError, match="mesh_format must be one of ply, obj"):
        require_mesh_formats(compose("task=neural_sdf", "mesh_format=stl"), "mesh_format", ("ply", "obj"))
    for value in ("[]", "[-0.1,0.05]"):
        with pytest.raises(UserError, match="thresholds must be a non-empty list of positive numbers"):
            require_thresholds(compose("task=svr_train", f"thresholds={value}"))
    with pytest.raises(UserError, match="iters must be a positive number, got True"):
        require_positive(compose("task=volsdf", "iters=true"), "iters")
    with pytest.raises(ValueError, match=r"point_lights must be a list of \[x, y, z\]"):
        MeshRenderer(point_lights=[[1.0, 2.0]])


@pytest.mark.parametrize("stride", [0, -1])
def test_bunny_stride_below_one(tmp_path, stride):
    np.savez(tmp_path / "b.npz", verts=np.random.default_rng(0).normal(size=(10, 3)))
    with pytest.raises(UserError, match="data.stride must be an integer >= 1"):
        bunny_points(str(tmp_path / "b.npz"), stride=stride)


def _truck(root, sizes=(8, 8, 8), focal=2.0, points=None):
    import imageio.v2 as imageio
    (root / "imgs").mkdir(parents=True)
    (root / "poses").mkdir()
    for k, s in enumerate(sizes):
        imageio.imwrite(root / "imgs" / f"frame{k:06d}.jpg", np.zeros((s, s, 3), np.uint8))
        np.save(root / "poses" / f"frame{k:06d}.npy", np.concatenate([np.eye(3).reshape(-1), [0, 0, 3], [focal] * 2, [0, 0]]))
    if points is not None:
        (root / "points").mkdir()
        np.save(root / "points" / "points_10000.npy", points)
    return str(root)


@pytest.mark.parametrize("kind,problem", [
    ("sizes", r"have different sizes \(h, w\) \[\(8, 8\), \(16, 16\)\]"),
    ("focal", r"focal lengths F \(values 13-14 of each pose\) must be positive"),
    ("points", r"must hold an \(N, 3\) array of points, got shape \(10,\)"),
])
def test_truck_mixed_sizes_zero_focal_flat_points(tmp_path, kind, problem):
    from l3d_app.data.nerf_formats import truck
    root = _truck(tmp_path, sizes=(8, 16, 8) if kind == "sizes" else (8, 8, 8), focal=0.0 if kind == "focal" else 2.0,
                  points=np.zeros(10) if kind == "points" else None)
    with pytest.raises(UserError, match=problem):
        truck(root, test_indices=[2])
    assert truck(_truck(tmp_path / "ok"), test_indices=[2]).images.shape == (3, 8, 8, 3)


@pytest.mark.parametrize("args,problem", [
    (("task=train_prior", "ema_decay=2"), r"ema_decay must be a number in \[0, 1\]"),
    (("task=train_prior", "slot_drop=1.5"), r"slot_drop must be a number in \[0, 1\]"),
    (("task=pca_normals", "up=[0,0,0]"), "up must be a non-zero"),
    (("task=sampling_variance", "slab.start=4", "slab.end=2"), "slab.end must be greater than slab.start"),
    (("task=sampling_variance", "bump.density=-2"), "must be >= 0"),
    (("task=stereo_depth", "focal_px=0"), "focal_px must be a positive number"),
    (("task=stereo_depth", "sweep.baselines=[]"), "sweep lists must be non-empty"),
    (("task=stereo_depth", "sweep.sigmas_px=[-1,0.5]"), "sigmas_px >= 0"),
    (("task=pointnet_robustness", "num_points_list=[]"), "must be non-empty"),
    (("task=pointnet_robustness", "num_points_list=[-5]"), "the counts >= 1"),
])
def test_out_of_range_knobs_fail_before_any_work(compose, tmp_path, args, problem):
    with pytest.raises(UserError, match=problem):
        run_task(compose(*args, "tensorboard=false"), out_dir=tmp_path / "run")
    assert not any((tmp_path / "run").glob("*.png"))


@pytest.mark.parametrize("args,problem", [
    (("task=box", "init_size=[-1,1,1]"), "init_size must be three positive side lengths"),
    (("task=fit_vox", "pos_weight=-2"), "pos_weight must be a positive weight"),
])
def test_box_and_fit_vox_knobs(compose, tmp_path, args, problem):
    with pytest.raises(UserError, match=problem):
        run_task(compose(*args, "tensorboard=false"), out_dir=tmp_path / "run")


def test_course_rgbd_with_no_valid_pixel(tmp_path, monkeypatch):
    import types

    from l3d_app.data import course_rgbd as module
    cam = types.SimpleNamespace(R=np.eye(3)[None], T=np.array([[0.0, 0.0, 3.0]]), fov=np.array([60.0]))
    view = {"rgb1": np.zeros((4, 4, 3)), "depth1": np.ones((4, 4)), "mask1": np.zeros((4, 4)), "cameras1": cam}
    monkeypatch.setattr(module, "load_pickle", lambda file: view)       # the pickle's content, as read
    with pytest.raises(UserError, match="no pixel of view"):
        module.course_rgbd(str(tmp_path / "rgbd.pkl"), view="1")
    view["mask1"] = np.ones((4, 4))
    assert module.course_rgbd(str(tmp_path / "rgbd.pkl"), view="1").points.shape == (16, 3)


def test_svr_eval_view_outside_the_views_per_object(compose, tmp_path, data_cache):
    with pytest.raises(UserError, match=r"eval_view must be in \[0, "):
        run_task(compose("task=svr_train", "eval_view=99", "tensorboard=false", "image_size=16",
                         f"data.cache_dir={data_cache}", "data.train_per_class=2", "data.test_per_class=1",
                         "data.voxel_size=16", "data.num_points=256", "data.occupancy_points=256", "data.depth_views=3"),
                 out_dir=tmp_path / "run")


@pytest.mark.parametrize("args,problem", [
    (("task=stereo_depth", "focal_px=wide"), "focal_px must be a positive number, got 'wide'"),
    (("task=stereo_depth", "sweep.sigmas_px=[a,1]"), r"sweep.sigmas_px must be a list of numbers, got \['a', 1\]"),
    (("task=render360", "points_beside=true", "points_beside_samples=0"), "points_beside_samples must be a positive"),
    (("task=render360", "camera=relative", "camera.rotation_deg=[1,2]"),
     r"camera.rotation_deg must be a list of 3 numbers, got \[1, 2\]"),
    (("task=pointnet_cls", "augment_rotation=true", "rotation_axis=w"), "rotation axis must be x, y or z, got 'w'"),
    (("task=pointnet_robustness", "rotation_axis=w"), "rotation axis must be x, y or z, got 'w'"),
    (("task=pointnet_robustness", "rotation_degrees=[0,a]"), "rotation_degrees must be a list of numbers"),
    (("task=surface_tradeoff", "chamfer_backend=gpu"), "unknown backend 'gpu'"),
    (("task=sds_mesh", "distance_range=[8]"), r"distance range \[lo, hi\] must be a list of 2 numbers, got \[8\]"),
    (("task=sds_mesh", "elevation_range=[0,95]"), r"strictly inside \(-90, 90\)"),
    (("task=sds_nerf", "fov_range=[50,30]"), "fov range must be"),
    # string and list knobs
    (("task=render360", "point_renderer.radius_units=bogus"), "unknown radius_units 'bogus'"),   # renderer unused by mesh data
    (("task=render360", "light_direction=[1,2]"), r"light_direction must be a list of 3 numbers, got \[1, 2\]"),
    (("task=render360", "point_lights=[1,2,3]"), r"point_lights must be a list of \[x, y, z\] positions"),
    (("task=fit_mesh", "renderer.shading=bogus"), "unknown shading 'bogus'"),                   # before training
    (("task=fit_point", "camera.name=bogus"), "unknown camera path 'bogus'"),
    (("task=pointnet_cls", "rotation_axis=bogus"), "rotation axis must be x, y or z"),          # augment_rotation off
    (("task=pointnet_cls", "num_vis=1", "point_renderer.radius_units=bogus"), "unknown radius_units"),
    (("task=gs_render", "ply=none.ply", "depth_cmap=bogus"), "unknown colormap 'bogus'"),
    (("task=gs_render", "ply=none.ply", "up=[0,1]"), "up must be a list of 3 numbers"),
    (("task=gs_render", "ply=none.ply", "depth_range=[7,5]"), "far > near"),
    (("task=render_path", "checkpoint=none", "formats=[]"), "neither empty"),
    (("task=render_path", "checkpoint=none", "formats=5"), "formats must be a name or a list of names, got 5"),
    (("task=render_path", "ply=none.ply", "background=[1,2]"), "background must be a list of 3 numbers"),
    (("task=box", "mode=render", "render_size=[]"), "render_size must be a list of 3 numbers"),
    (("task=box", "true_center=[1,2]"), "true_center must be a list of 3 numbers"),
    (("task=box", "mode=bogus"), "box mode must be fit or render"),
    (("task=pca_normals", "view.at=[0,1]"), "view.at must be a list of 3 numbers"),
    (("task=sds_nerf", "background=[1,2]"), "background must be a list of 3 numbers"),
    (("task=volsdf", "mesh_formats=5"), "mesh_formats must be a name or a list of names"),
])
def test_knobs_checked_before_the_data_is_built(compose, tmp_path, monkeypatch, args, problem):
    """Checked before rendering, loading or training starts."""
    from l3d_app import registry
    from l3d_app.tasks import point_common

    def no_work(*_, **__):
        raise AssertionError("the data was built before the knobs were checked")

    monkeypatch.setattr(registry.DATASETS, "build", no_work)
    monkeypatch.setattr(point_common, "load_data", no_work)
    with pytest.raises(UserError, match=problem):
        run_task(compose(*args, "tensorboard=false"), out_dir=tmp_path / "run")
    assert not [p for p in (tmp_path / "run").rglob("*") if p.is_file()]


def test_mesh_without_surface_and_arrays_without_numbers(tmp_path):
    from l3d_app.data.box_images import load_box_images
    from l3d_app.geometry.mesh_io import load_mesh

    (tmp_path / "point.obj").write_text("v 0 0 0\nv 0 0 0\nv 0 0 0\nf 1 2 3\n")
    (tmp_path / "line.obj").write_text("v 0 0 0\nv 1 1 1\nv 2 2 2\nf 1 2 3\n")
    for name in ("point.obj", "line.obj"):
        with pytest.raises(UserError, match="has no surface: every face has zero area"):
            load_mesh(tmp_path / name)
    (tmp_path / "one.obj").write_text("v 0 0 0\nv 0 0 0\nv 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\nf 1 4 5\n")
    assert load_mesh(tmp_path / "one.obj").faces.shape == (2, 3)      # one face of area 0.5 is a surface
    np.savez(tmp_path / "str.npz", verts=np.array([["a", "b", "c"]] * 4))
    with pytest.raises(UserError, match=r"str.npz:verts must hold numbers, got an array of dtype <U1"):
        bunny_points(str(tmp_path / "str.npz"))
    (tmp_path / "box").mkdir()
    for i in range(4):
        np.save(tmp_path / "box" / f"box_{i}.npy", np.full((256, 256, 3), "x"))
    with pytest.raises(UserError, match="box_0.npy must hold numbers"):
        load_box_images(str(tmp_path / "box"))


def test_neural_sdf_needs_points_with_extent_and_both_splits(compose, tmp_path):
    for points, problem in [([[0.0, 0.0, 0.0]], "at least 2 points, got 1"),
                            ([[1.0, 2.0, 3.0]] * 5, "all its points coincide")]:
        np.savez(tmp_path / "cloud.npz", verts=np.array(points))
        with pytest.raises(UserError, match=problem):
            run_task(compose("task=neural_sdf", "data=bunny", f"data.path={tmp_path / 'cloud.npz'}", "data.stride=1",
                             "tensorboard=false"), out_dir=tmp_path / "run")
    np.savez(tmp_path / "cloud.npz", verts=np.random.default_rng(0).normal(size=(4, 3)))
    with pytest.raises(UserError, match="val_fraction=0.1 of 4 points holds out 0"):
        run_task(compose("task=neural_sdf", "data=bunny", f"data.path={tmp_path / 'cloud.npz'}", "data.stride=1",
                         "val_fraction=0.1", "tensorboard=false"), out_dir=tmp_path / "run")
    run_task(compose("task=neural_sdf", "data=bunny", f"data.path={tmp_path / 'cloud.npz'}", "data.stride=1",
                     "val_fraction=0", "iters=2", "gif_frames=0", "mesh_resolution=8", "eval_points=50",
                     "tensorboard=false"), out_dir=tmp_path / "ok")

    def no_constants(name):
        raise AssertionError(f"metrics.json holds {name}")

    metrics = json.loads((tmp_path / "ok" / "metrics.json").read_text(), parse_constant=no_constants)
    assert metrics["val_surface_abs"] is None and metrics["n_points"] == 4       # no validation: null, not NaN


def test_an_unreadable_pointnet_checkpoint_is_named(tmp_path):
    from l3d_app.pipelines.point_nets import load_model

    (tmp_path / "best.pt").write_text("garbage\n")
    with pytest.raises(UserError, match=r"best.pt is not a readable pointnet best.pt checkpoint \("):
        load_model(tmp_path / "best.pt", "cpu")


@pytest.mark.parametrize("args,problem", [
    (("task=train_nerf", "data.scene_box=[[1,2],[3,4]]"), r"data.scene_box must be \[\[x, y, z\] min, \[x, y, z\] max\]"),
    (("task=train_nerf", "data.elevation_range=[5]"), "elevation_range must be a list of 2 numbers"),
    (("task=volsdf", "+sampler.anchor_window=[1]"), "anchor_window must be a list of 2 numbers"),
    (("task=pointnet_seg", "model=dgcnn", "model.widths=[]"), "dgcnn widths need >= 1 positive entry"),
    (("task=render360", "data=superquadric_parametric", "data.exponents=[1]"), "exponents must be a list of 2 numbers"),
])
def test_list_knobs_of_the_data_and_models_are_named(compose, tmp_path, args, problem):
    with pytest.raises(UserError, match=problem):
        run_task(compose(*args, "tensorboard=false"), out_dir=tmp_path / "run")
    assert not [p for p in (tmp_path / "run").rglob("*") if p.is_file()]


def test_a_bare_name_is_a_list_of_one_never_its_letters():
    from l3d_app.runtime.config_values import config_rows, config_words

    assert config_words("ply", "mesh_formats") == ["ply"]
    assert config_words(["ply", "obj"], "mesh_formats") == ["ply", "obj"]
    with pytest.raises(UserError, match="mesh_formats must be a name or a list of names, got \\[1\\]"):
        config_words([1], "mesh_formats")
    assert config_rows([[0, 0, 1], [1, 2, 3]], "point_lights", None, 3) == [[0.0, 0.0, 1.0], [1.0, 2.0, 3.0]]
    with pytest.raises(UserError, match="box must be a list of 2 lists of 3 numbers"):
        config_rows([[0, 0, 1]], "box", 2, 3)


def test_metrics_json_is_strict_json(tmp_path):
    """A figure that does not exist (NaN) or overflowed (inf) is written as null: JSON has no NaN."""
    from l3d_app.runtime.files import write_json

    write_json(tmp_path / "m.json", {"a": float("nan"), "b": torch.tensor([1.5, float("inf")]), "c": np.float32(2.0),
                                     "d": {"e": (1, float("-inf"))}, "f": True})
    text = (tmp_path / "m.json").read_text()
    assert json.loads(text) == {"a": None, "b": [1.5, None], "c": 2.0, "d": {"e": [1, None]}, "f": True}
    assert "NaN" not in text and "Infinity" not in text
