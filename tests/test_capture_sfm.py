"""Cameras from photos and video (data=images, data=video, task=process_images) on tiny generated captures.

The captures are exact ray casts of a textured corner (tests/capture_scenes.py, numpy only), so
the true camera centres are known; SfM (pycolmap) must recover them up to a similarity.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

sys.path.insert(0, str(Path(__file__).parent))
from capture_scenes import corner_eyes, corner_views, write_views  # noqa: E402

from l3d_app.data.photo_inputs import photo_files, read_photo, sharpness, video_frames  # noqa: E402
from l3d_app.data.photos import images, images_capture, video_capture  # noqa: E402
from l3d_app.data.sfm import judge  # noqa: E402
from l3d_app.errors import UserError  # noqa: E402

N = 8
SIZE = dict(width=160, height=120)


def _finished(cache: Path):
    """Model folders a later run would reuse, and leftovers of any kind (hidden temporary folders)."""
    entries = list(cache.iterdir()) if cache.is_dir() else []
    return [e for e in entries if (e / "sfm.json").is_file()], [e for e in entries if e.name.startswith(".")]


@pytest.fixture(scope="module")
def solved(tmp_path_factory):
    """A good 8-photo capture (plus a text file that must be ignored), solved once."""
    root = tmp_path_factory.mktemp("capture")
    write_views(root / "photos", corner_views(1, N, **SIZE), suffix=".jpg")
    (root / "photos" / "notes.txt").write_text("not a photo")
    folder, report, reused = images_capture(str(root / "photos"), cache_dir=str(root / "cache"))
    return root, folder, report, reused


def _similarity_residual(a: np.ndarray, b: np.ndarray) -> float:
    """RMS distance between ``b`` and ``a`` mapped by the best similarity (Umeyama), over b's spread."""
    ca, cb = a - a.mean(0), b - b.mean(0)
    U, S, Vt = np.linalg.svd(cb.T @ ca)
    d = np.sign(np.linalg.det(U @ Vt))
    D = np.diag([1.0, 1.0, d])
    R = U @ D @ Vt
    s = (S * np.diag(D)).sum() / (ca ** 2).sum()
    return float(np.sqrt(((s * ca @ R.T - cb) ** 2).sum(1).mean()) / np.sqrt((cb ** 2).sum(1).mean()))


def test_photos_solved_to_the_true_cameras(solved):
    root, folder, report, reused = solved
    assert not reused
    assert report.given == N and report.registered == N          # the text file was not taken for a photo
    assert 0 < report.reprojection_error < 1.0 and report.points > 100
    data = images(root=str(root / "photos"), cache_dir=str(root / "cache"), normalize=False)
    names = sorted(p.name for p in (folder / "images").iterdir())
    assert names == [f"view_{i:03d}.png" for i in range(N)]
    centres = data.cameras.centers().double().numpy()
    assert _similarity_residual(corner_eyes(N), centres) < 0.05  # the arc, up to scale, turn and shift (160 px views)


def test_a_solved_capture_splits_like_colmap_and_is_reused(solved):
    root, folder, report, _ = solved
    again, report2, reused = images_capture(str(root / "photos"), cache_dir=str(root / "cache"))
    assert reused and again == folder and report2 == report
    data = images(root=str(root / "photos"), cache_dir=str(root / "cache"), test_every=4, val_every=3)
    assert data.test.tolist() == [0, 4] and data.val.tolist() == [3, 7] and data.train.tolist() == [1, 2, 5, 6]
    assert data.background_known is False                       # photographs: the background is learnt
    # the scene box comes from the sparse points, and up from the cameras: the corner's +z
    assert data.points is not None and len(data.points) == report.points
    lo, hi = data.scene_box
    inside = ((data.points >= lo) & (data.points <= hi)).all(1).float().mean()
    assert inside > 0.9
    raw = images(root=str(root / "photos"), cache_dir=str(root / "cache"), normalize=False)
    # the cameras look down at the corner from above: their mean up points along world up up to SfM's frame
    c = raw.cameras.centers().double()
    height_axis = torch.linalg.svd(c - c.mean(0)).Vh[-1]            # the arc's plane normal
    assert abs(float(torch.dot(raw.up.double(), height_axis))) > 0.9


def test_photos_train_at_image_size_on_the_long_side_with_the_cameras_scaled(solved, compose):
    """SfM at the photos' size (160 x 120, undistorted), training at ``image_size`` = 80 on the long
    side: intrinsics scaled by the exact size ratios, poses unchanged, the same solved model (no
    second solve); the knob's default composes from data=images."""
    root, folder, report, _ = solved
    full = images(root=str(root / "photos"), cache_dir=str(root / "cache"), image_size=0)
    small = images(root=str(root / "photos"), cache_dir=str(root / "cache"), image_size=80)
    (h0, w0), (h, w) = full.image_size, small.image_size
    assert w0 > h0 > 100 and w == 80 and h == round(h0 * 80 / w0)
    for f, s in (("fx", w / w0), ("cx", w / w0), ("fy", h / h0), ("cy", h / h0)):
        torch.testing.assert_close(getattr(small.cameras, f), getattr(full.cameras, f) * s)
    assert torch.equal(small.cameras.R, full.cameras.R) and torch.equal(small.cameras.t, full.cameras.t)
    torch.testing.assert_close(small.images.mean((1, 2)), full.images.mean((1, 2)), atol=0.01, rtol=0)
    assert images(root=str(root / "photos"), cache_dir=str(root / "cache")).image_size == (h0, w0)  # under 256
    assert compose("task=gs_train", "data=images", "data.root=x").data.image_size == 256
    assert len([e for e in (root / "cache").iterdir() if not e.name.startswith(".")]) == 1


def test_changed_photos_solve_again_and_settings_key_the_cache(solved, tmp_path):
    root, folder, _, _ = solved
    photos = tmp_path / "photos"
    write_views(photos, corner_views(1, N, **SIZE), suffix=".jpg")
    from l3d_app.data.sfm_cache import content_key
    files = photo_files(photos)
    k1 = content_key(files, {"a": 1})
    assert content_key(files, {"a": 2}) != k1
    files[0].write_bytes(files[0].read_bytes() + b"\0")
    assert content_key(files, {"a": 1}) != k1


def _refused(tmp_path, views, match, **kw):
    photos = tmp_path / "photos"
    write_views(photos, views, suffix=".png")
    with pytest.raises(UserError, match=match) as err:
        images_capture(str(photos), cache_dir=str(tmp_path / "cache"), **kw)
    assert "\n" not in str(err.value)
    finished, leftovers = _finished(tmp_path / "cache")
    assert finished == [] and leftovers == []                     # nothing a later run could take for a model
    return str(err.value)


def test_photos_that_do_not_overlap_are_refused(tmp_path):
    views = corner_views(1, 3, az_range=(10.0, 30.0), **SIZE) + [corner_views(100 + k, 1, **SIZE)[0] for k in range(5)]
    _refused(tmp_path, views, r"^registered 3 of 8 images: the photos do not overlap enough")


def test_two_unrelated_objects_are_refused(tmp_path):
    views = corner_views(1, 5, **SIZE) + corner_views(2, 5, **SIZE)
    _refused(tmp_path, views, r"registered 5 of 10 images: the photos form 2 separate groups \(5, 5 images\)")


def test_too_few_photos_are_refused_with_exit_2_and_one_line(compose, tmp_path, monkeypatch, capsys):
    from l3d_app.app import run

    monkeypatch.delenv("L3D_DEBUG", raising=False)
    photos = tmp_path / "photos"
    write_views(photos, corner_views(1, 2, **SIZE))
    with pytest.raises(SystemExit) as stop:
        run(compose("task=process_images", f"data.root={photos}", f"data.cache_dir={tmp_path / 'cache'}",
                    "tensorboard=false"), out_dir=tmp_path / "run")
    assert stop.value.code == 2
    lines = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert lines == [f"l3d_app: error: found 2 photos (JPEG/PNG) in {photos}: structure-from-motion needs at least 3 "
                     "overlapping photos (20 or more for a model worth training)"]
    assert not (tmp_path / "cache").exists()


def test_a_corrupt_photo_is_named(tmp_path):
    photos = tmp_path / "photos"
    write_views(photos, corner_views(1, 4, **SIZE), suffix=".jpg")
    (photos / "view_002.jpg").write_bytes(b"\xff\xd8\xff\xe0 truncated")
    with pytest.raises(UserError, match=r"view_002.jpg: cannot be read as an image"):
        images_capture(str(photos), cache_dir=str(tmp_path / "cache"))
    assert _finished(tmp_path / "cache") == ([], [])


def test_exif_orientation_is_honoured(tmp_path):
    from PIL import Image

    img = np.zeros((20, 40, 3), np.uint8)
    img[:, :20] = 255                                  # left half white
    exif = Image.Exif()
    exif[0x0112] = 6                                   # "rotate 90 CW to view"
    Image.fromarray(img).save(tmp_path / "a.jpg", exif=exif, quality=100)
    out = read_photo(tmp_path / "a.jpg")
    assert out.shape == (40, 20, 3)
    assert out[:15].mean() > 200 and out[25:].mean() < 50    # the white half is now on top


def test_missing_pycolmap_names_the_extra(monkeypatch):
    from l3d_app.data.sfm import import_pycolmap

    monkeypatch.setitem(sys.modules, "pycolmap", None)
    with pytest.raises(UserError, match=r"pip install -e '\.\[sfm\]'"):
        import_pycolmap()


def test_judge_lines():
    with pytest.raises(UserError, match="registered 0 of 40 images: no two photos share"):
        judge(40, [], 0.5)
    with pytest.raises(UserError, match="registered 3 of 40 images: the photos do not overlap enough"):
        judge(40, [3], 0.5)
    with pytest.raises(UserError, match=r"registered 20 of 40 images: the photos form 2 separate groups \(20, 18"):
        judge(40, [20, 18], 0.5)
    judge(40, [38, 2], 0.5)                            # a stray pair beside a good model is no second subject


def _write_video(path: Path, frames, fps: int = 8):
    import imageio_ffmpeg

    h, w = frames[0].shape[:2]
    writer = imageio_ffmpeg.write_frames(str(path), (w, h), fps=fps, quality=10, macro_block_size=8)
    writer.send(None)
    for f in frames:
        writer.send(np.ascontiguousarray(f))
    writer.close()


def _blur(img: np.ndarray, k: int = 9) -> np.ndarray:
    """Horizontal box blur of ``k`` pixels (a camera moving sideways)."""
    x = np.cumsum(np.pad(img.astype(np.float64), ((0, 0), (k, 0), (0, 0)), mode="edge"), axis=1)
    return ((x[:, k:] - x[:, :-k]) / k).round().astype(np.uint8)


def test_video_keeps_the_sharpest_frames_and_drops_blurry_ones(tmp_path):
    sharp = corner_views(1, 6, **SIZE)
    frames = []
    for i, f in enumerate(sharp):                     # each stretch: blurred, sharp, blurred; the last all blurred
        frames += [_blur(f), f if i < 5 else _blur(f, 7), _blur(f)]
    path = tmp_path / "walk.mp4"
    _write_video(path, frames)
    picked, note = video_frames(path, 6, 0.5, 0)
    assert note == {"decoded": 18, "kept": 5, "blurry": 1}
    assert all(sharpness(p) > 0.5 * sharpness(s) for p, s in zip(picked, sharp[:5]))


def test_video_solved_with_sequential_matching(tmp_path):
    path = tmp_path / "walk.mp4"
    _write_video(path, corner_views(1, N, **SIZE))
    folder, report, _ = video_capture(str(path), frames=N, cache_dir=str(tmp_path / "cache"))
    assert report.matcher == "sequential" and report.registered == N and report.reprojection_error < 1.0
    assert sorted(p.name for p in (folder / "images").iterdir())[0] == "frame_00000.png"


def test_an_undecodable_video_is_refused(tmp_path):
    path = tmp_path / "broken.mp4"
    path.write_bytes(b"\x00\x00\x00\x18ftypmp42 this is not a video" * 10)
    with pytest.raises(UserError, match=r"broken.mp4: cannot be decoded as a video"):
        video_capture(str(path), cache_dir=str(tmp_path / "cache"))
    assert _finished(tmp_path / "cache") == ([], [])


def test_process_images_prints_the_figures(solved, compose, tmp_path, capsys):
    from l3d_app.app import run

    root, folder, report, _ = solved
    run(compose("task=process_images", f"data.root={root / 'photos'}", f"data.cache_dir={root / 'cache'}",
                "tensorboard=false"), out_dir=tmp_path / "run")
    out = capsys.readouterr()
    metrics = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert metrics["registered"] == N and metrics["given"] == N and metrics["reused"] is True
    assert f"registered {N} of {N} images, mean reprojection error {report.reprojection_error:.3f} px, " \
           f"{report.points} sparse points" in out.out
    assert "reused from the cache" in out.out
