"""data=colmap: text and binary readers agree, cameras and projections match the known scene
(pinhole and distorted models), splits by sorted name, normalisation maps back, bad input."""

import shutil

import numpy as np
import pytest
import torch

from colmap_writer import distort_np, pattern, write_scene
from l3d_app.data.colmap import colmap
from l3d_app.data.colmap_model import read_model
from l3d_app.errors import UserError
from l3d_app.geometry.cameras import look_at_cameras
from l3d_app.geometry.distortion import distort, undistort_points

W, H = 40, 30
DIST = {"PINHOLE": (0, 0, 0, 0), "SIMPLE_PINHOLE": (0, 0, 0, 0), "SIMPLE_RADIAL": (-0.2, 0, 0, 0),
        "RADIAL": (-0.18, 0.05, 0, 0), "OPENCV": (-0.15, 0.03, 0.01, -0.008)}


def scene(n=10, seed=0, square_focal=True):
    """n cameras around the origin (non-square images), 200 points on a sphere of radius 0.6."""
    rng = np.random.default_rng(seed)
    cams = look_at_cameras(3.0, torch.linspace(-10, 50, n), torch.arange(n) * 360.0 / n + 7, 50.0, W)
    R, t = cams.R.double().numpy(), cams.t.double().numpy()
    f = 30.0 + np.arange(n)
    K = np.stack([f, f if square_focal else f * 1.05, np.full(n, W / 2 + 0.7), np.full(n, H / 2 - 0.4)], -1)
    p = rng.normal(size=(200, 3))
    pts = 0.6 * p / np.linalg.norm(p, axis=1, keepdims=True)
    cols = rng.integers(0, 256, (200, 3)).astype(np.uint8)
    return R, t, K, pts, cols


def names_shuffled(n):
    names = [f"view_{i:02d}.png" for i in range(n)]
    return [names[i] for i in np.random.default_rng(1).permutation(n)]


def test_text_and_binary_readers_give_identical_models(tmp_path):
    R, t, K, pts, cols = scene()
    write_scene(tmp_path / "both", R, t, K, (W, H), pts, cols, model="OPENCV", dist=DIST["OPENCV"])
    txt_dir = tmp_path / "txt" / "sparse" / "0"
    txt_dir.mkdir(parents=True)
    for f in ("cameras", "images", "points3D"):
        shutil.copy(tmp_path / "both" / "sparse" / "0" / f"{f}.txt", txt_dir)
    b = read_model(tmp_path / "both" / "sparse" / "0", keep_points2d=True)
    a = read_model(txt_dir, keep_points2d=True)
    assert a.names == b.names and np.array_equal(a.image_ids, b.image_ids)
    assert np.array_equal(a.qvec, b.qvec) and np.array_equal(a.tvec, b.tvec)   # repr() round-trips float64
    assert np.array_equal(a.points, b.points) and np.array_equal(a.colors, b.colors)
    assert a.cameras.keys() == b.cameras.keys()
    for k in a.cameras:
        assert a.cameras[k].model == b.cameras[k].model == "OPENCV"
        assert np.array_equal(a.cameras[k].params, b.cameras[k].params)
        assert (a.cameras[k].width, a.cameras[k].height) == (W, H)
    for pa, pb in zip(a.points2d, b.points2d):
        assert np.array_equal(pa, pb)
    # and the full datasets agree bit for bit
    (tmp_path / "txt" / "images").symlink_to(tmp_path / "both" / "images")
    da, db = colmap(str(tmp_path / "txt")), colmap(str(tmp_path / "both"))
    for f in ("R", "t", "fx", "fy", "cx", "cy"):
        assert torch.equal(getattr(da.cameras, f), getattr(db.cameras, f)), f
    assert torch.equal(da.images, db.images) and torch.equal(da.points, db.points)


@pytest.mark.parametrize("model", list(DIST))
@pytest.mark.parametrize("binary", [True, False], ids=["bin", "txt"])
def test_cameras_and_projections_match_the_known_scene(tmp_path, model, binary):
    R, t, K, pts, cols = scene(square_focal=model != "OPENCV" and model != "PINHOLE")
    dist = DIST[model]
    obs = write_scene(tmp_path, R, t, K, (W, H), pts, cols, model=model, dist=dist, binary=binary, text=not binary)
    d = colmap(str(tmp_path), normalize=False, test_every=0, val_every=0)
    assert d.image_size == (H, W) and len(d.train) == len(R)
    torch.testing.assert_close(d.cameras.R.double(), torch.from_numpy(R), atol=1e-6, rtol=0)
    torch.testing.assert_close(d.cameras.t.double(), torch.from_numpy(t), atol=1e-6, rtol=0)
    torch.testing.assert_close(d.cameras.fx.double(), torch.from_numpy(K[:, 0]), atol=1e-5, rtol=0)
    torch.testing.assert_close(d.cameras.fy.double(), torch.from_numpy(K[:, 1]), atol=1e-5, rtol=0)
    torch.testing.assert_close(d.points.double(), torch.from_numpy(pts), atol=1e-6, rtol=0)
    torch.testing.assert_close(d.point_colors, torch.from_numpy(cols / 255.0).float())
    # pinhole projection of the points, pushed through the known distortion, lands on the observations
    uv, z = d.cameras.to(dtype=torch.float64).project(torch.from_numpy(pts))
    x = (uv[..., 0] - d.cameras.cx.double()[:, None]) / d.cameras.fx.double()[:, None]
    y = (uv[..., 1] - d.cameras.cy.double()[:, None]) / d.cameras.fy.double()[:, None]
    xd, yd = distort_np(x.numpy(), y.numpy(), *dist)
    u_obs = np.stack(obs)[..., 0]
    np.testing.assert_allclose(K[:, :1] * xd + K[:, 2:3], u_obs, atol=1e-4)
    # the undistorted image is the pinhole image of the pattern (bilinear resampling error only)
    v, u = np.meshgrid(np.arange(H) + 0.5, np.arange(W) + 0.5, indexing="ij")
    err = []
    for i in range(len(R)):
        ref = pattern((u - K[i, 2]) / K[i, 0], (v - K[i, 3]) / K[i, 1])
        inner = (slice(3, H - 3), slice(3, W - 3))          # borders may sample outside the frame
        err.append(np.abs(d.images[i].numpy()[inner] - ref[inner]).max())
    assert max(err) < 0.02, err
    if any(dist):   # the distortion is large enough that NOT undistorting would fail the check
        raw = np.asarray(__import__("imageio").v2.imread(tmp_path / "images" / "img_000.png")) / 255.0
        ref = pattern((u - K[0, 2]) / K[0, 0], (v - K[0, 3]) / K[0, 1])
        assert np.abs(raw - ref)[3:H - 3, 3:W - 3].max() > 3 * max(err)


def test_distortion_inverse_matches_float64_fixed_point():
    from colmap_writer import undistort_np

    xy = torch.rand(500, 2, dtype=torch.float64) - 0.5
    k1, k2, p1, p2 = DIST["OPENCV"]
    xd = distort(xy, (k1, k2, 0, 0, p1, p2))
    ref = np.stack(distort_np(xy[:, 0].numpy(), xy[:, 1].numpy(), k1, k2, p1, p2), -1)
    np.testing.assert_allclose(xd.numpy(), ref, atol=1e-14)
    back = undistort_points(xd, (k1, k2, 0, 0, p1, p2))
    xu, yu = undistort_np(xd[:, 0].numpy(), xd[:, 1].numpy(), k1, k2, p1, p2)
    np.testing.assert_allclose(back.numpy(), np.stack([xu, yu], -1), atol=1e-12)


def test_splits_by_sorted_name_normalisation_and_downscale(tmp_path):
    R, t, K, pts, cols = scene(n=17)
    names = names_shuffled(17)
    write_scene(tmp_path, R, t, K, (W, H), pts, cols, names=names)
    d = colmap(str(tmp_path), test_every=8, val_every=4)
    order = sorted(range(17), key=lambda i: names[i])        # dataset view k = file image order[k]
    assert d.test.tolist() == [0, 8, 16]
    assert d.val.tolist() == [4, 9, 13] and len(d.train) == 11
    assert not (set(d.train.tolist()) & set(d.val.tolist()) | set(d.train.tolist()) & set(d.test.tolist()))
    # normalised: the training cameras centred, their median distance 3; the map back is exact
    c = d.cameras.centers().double()
    ct = c[d.train]
    assert ct.mean(0).abs().max() < 1e-5 and float(ct.norm(dim=-1).median()) == pytest.approx(3.0, abs=1e-5)
    M = d.source_from_world
    back = d.points.double() @ M[:3, :3].T + M[:3, 3]
    torch.testing.assert_close(back, torch.from_numpy(pts), atol=1e-5, rtol=0)
    C_src = -np.einsum("nji,nj->ni", R, t)[order]
    torch.testing.assert_close(c @ M[:3, :3].T + M[:3, 3], torch.from_numpy(C_src), atol=1e-5, rtol=0)
    # projections are unchanged by the similarity
    uv, _ = d.cameras.to(dtype=torch.float64).project(d.points.double())
    pc = np.einsum("nij,pj->npi", R[order], pts) + t[order][:, None]
    np.testing.assert_allclose(uv[..., 0].numpy(), K[order, :1] * pc[..., 0] / pc[..., 2] + K[order, 2:3], atol=1e-3)
    # box from the points (sphere of radius 0.6 scaled), up = cameras' mean up
    P = d.points.double().numpy()
    lo, hi = np.percentile(P, 2, axis=0), np.percentile(P, 98, axis=0)
    np.testing.assert_allclose(d.scene_box.numpy(), np.stack([lo - 0.1 * (hi - lo), hi + 0.1 * (hi - lo)]), atol=1e-5)
    assert float(d.up @ torch.tensor([0.0, 1.0, 0.0])) > 0.9
    assert d.background_known is False and d.background.shape == (3,)
    half = colmap(str(tmp_path), downscale=2)
    assert half.image_size == (H // 2, W // 2)
    torch.testing.assert_close(half.cameras.fx, d.cameras.fx / 2)
    torch.testing.assert_close(half.cameras.cx, d.cameras.cx / 2)


def test_the_scored_poses_take_no_part_in_the_set_up(tmp_path):
    """Moving the test and val cameras far off changes nothing of the training cameras' normalised
    poses, the points, the box or the up vector; the reference is the float64 normalisation
    written here from the training cameras alone."""
    n = 17
    R, t, K, pts, cols = scene(n=n)
    names = [f"view_{i:02d}.png" for i in range(n)]          # sorted = file order
    write_scene(tmp_path / "a", R, t, K, (W, H), pts, cols, names=names)
    a = colmap(str(tmp_path / "a"), test_every=8, val_every=4)
    scored = torch.cat([a.val, a.test]).numpy()
    t2 = t.copy()
    t2[scored] += np.array([4.0, -7.0, 30.0])                 # scored cameras moved 31 units away
    write_scene(tmp_path / "b", R, t2, K, (W, H), pts, cols, names=names)
    b = colmap(str(tmp_path / "b"), test_every=8, val_every=4)
    assert torch.equal(a.train, b.train) and torch.equal(a.test, b.test)
    for f in ("R", "t"):
        torch.testing.assert_close(getattr(a.cameras, f)[a.train], getattr(b.cameras, f)[b.train], atol=1e-5, rtol=0)
    torch.testing.assert_close(a.points, b.points, atol=1e-5, rtol=0)
    torch.testing.assert_close(a.scene_box, b.scene_box, atol=1e-5, rtol=0)
    torch.testing.assert_close(a.up, b.up, atol=1e-6, rtol=0)
    # independent reference: centre and scale from the training cameras' centres in float64
    C = -np.einsum("nji,nj->ni", R, t)[a.train.numpy()]
    c0 = C.mean(0)
    s = 3.0 / np.median(np.linalg.norm(C - c0, axis=1))
    np.testing.assert_allclose(b.points.double().numpy(), s * (pts - c0), atol=1e-5)
    # the moved test cameras are still where the same similarity puts them
    C_test = -np.einsum("nji,nj->ni", R, t2)[a.test.numpy()]
    np.testing.assert_allclose(b.cameras.centers().double()[b.test].numpy(), s * (C_test - c0), atol=1e-4)


@pytest.mark.parametrize("size", [20, 32])
def test_image_size_resizes_the_long_side_and_scales_the_intrinsics(tmp_path, size):
    """Halved (20) and 0.8x (32): intrinsics scale by the exact factor, and each pixel centre shows the
    pattern at its own pinhole coordinates (the written images are the analytic pattern)."""
    R, t, K, pts, cols = scene(n=3)
    write_scene(tmp_path, R, t, K, (W, H), pts, cols)
    d = colmap(str(tmp_path), normalize=False, test_every=0, val_every=0, image_size=size)
    s = size / W
    assert d.image_size == (round(H * s), size)
    for f, k in (("fx", 0), ("fy", 1), ("cx", 2), ("cy", 3)):
        torch.testing.assert_close(getattr(d.cameras, f).double(), torch.from_numpy(K[:, k] * s), atol=1e-5, rtol=0)
    h, w = d.image_size
    v, u = np.meshgrid(np.arange(h) + 0.5, np.arange(w) + 0.5, indexing="ij")
    for i in range(3):
        ref = pattern((u - K[i, 2] * s) / (K[i, 0] * s), (v - K[i, 3] * s) / (K[i, 1] * s))
        err = np.abs(d.images[i].numpy() - ref)[2:h - 2, 2:w - 2].max()     # the filter's blur of a smooth pattern
        assert err < 0.015, err                   # half a pixel off reads 0.04-0.07
    assert torch.equal(colmap(str(tmp_path), image_size=W).images, colmap(str(tmp_path)).images)   # not longer: as stored
    with pytest.raises(UserError, match="image_size"):
        colmap(str(tmp_path), image_size=-1)


def test_pre_downscaled_image_folder(tmp_path):
    R, t, K, pts, cols = scene(n=4)
    write_scene(tmp_path, R, t, K, (W, H), pts, cols, image_dir="images_2", image_scale=2)
    d = colmap(str(tmp_path), images="images_2", normalize=False, test_every=0)
    assert d.image_size == (H // 2, W // 2)
    torch.testing.assert_close(d.cameras.fx.double(), torch.from_numpy(K[:, 0] / 2), atol=1e-5, rtol=0)
    torch.testing.assert_close(d.cameras.cy.double(), torch.from_numpy(K[:, 3] / 2), atol=1e-5, rtol=0)


@pytest.mark.parametrize("binary", [True, False], ids=["bin", "txt"])
def test_exporter_round_trips_through_the_reader(tmp_path, binary):
    from l3d_app.data.colmap_export import rotmat_to_qvec, write_colmap

    cams = look_at_cameras(2.5, torch.tensor([-80.0, 0.0, 30.0, 89.0]), torch.tensor([0.0, 100.0, 200.0, 300.0]),
                           45.0, 12)
    imgs = torch.rand(4, 12, 12, 3, generator=torch.Generator().manual_seed(0))
    pts = torch.randn(20, 3, dtype=torch.float64)
    write_colmap(tmp_path, cams, imgs, pts, torch.rand(20, 3), binary=binary)
    d = colmap(str(tmp_path), normalize=False, test_every=0, val_every=0)
    torch.testing.assert_close(d.cameras.R, cams.R, atol=1e-6, rtol=0)
    torch.testing.assert_close(d.cameras.t, cams.t, atol=1e-6, rtol=0)
    torch.testing.assert_close(d.images, imgs, atol=1 / 255, rtol=0)
    torch.testing.assert_close(d.points, pts.float())
    # the quaternion of a 180-degree turn (w = 0) and of the identity
    q = rotmat_to_qvec(np.stack([np.eye(3), np.diag([1.0, -1.0, -1.0])]))
    np.testing.assert_allclose(np.abs(q), [[1, 0, 0, 0], [0, 1, 0, 0]], atol=1e-12)
