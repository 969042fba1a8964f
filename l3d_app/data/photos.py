"""``data=images data.root=DIR`` and ``data=video data.path=FILE``: cameras by structure-from-motion.

A folder of photos (:func:`images_capture`) or a video (:func:`video_capture`) is solved once
by pycolmap (:mod:`l3d_app.data.sfm`: exhaustive matching for photos, sequential for video
frames) into a cached COLMAP model (:mod:`l3d_app.data.sfm_cache`, under ``cache_dir``), and
then read exactly as ``data=colmap`` reads a capture (:func:`l3d_app.data.colmap.colmap`:
every ``test_every``-th image by name is a test view, val every ``val_every``-th of the rest,
scene normalised on the training cameras, box from the sparse points, up from the cameras,
the background learnt), at ``image_size`` px on the long side (:data:`TRAIN_SIZE`).
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Tuple

from l3d_app.data.colmap import colmap
from l3d_app.data.nerf_views import MultiViewData
from l3d_app.data.photo_inputs import photo_files, read_photo, shrink, video_frames
from l3d_app.data.sfm import SfmReport
from l3d_app.data.sfm_cache import content_key, solved_capture, staged_names
from l3d_app.errors import UserError
from l3d_app.registry import DATASETS, check_keywords
from l3d_app.runtime.paths import resolve_path

SFM_KEYS = ("max_size", "max_features", "min_registered", "seed", "overlap")
# Long side (px) a capture trains at: the largest images the defaults of train_nerf, gs_train and volsdf
# were chosen at and met their targets within 600 s on 2 CPU cores (the benchmark scenes, 128 and 256 px).
# SfM keeps its own size (max_size): more pixels place the cameras better at no cost to training.
TRAIN_SIZE = 256


def _solve_settings(max_features: int, min_registered: float, seed: int) -> dict:
    if not 0.0 < float(min_registered) <= 1.0:
        raise UserError(f"min_registered must be a share in (0, 1], got {min_registered}")
    return {"max_features": int(max_features), "min_registered": float(min_registered), "seed": int(seed)}


def images_capture(root, max_size: int = 1600, min_images: int = 3, max_features: int = 8192,
                   min_registered: float = 0.5, seed: int = 0, cache_dir: str = "outputs/.cache/sfm"
                   ) -> Tuple[Path, SfmReport, bool]:
    """Solve (or reuse) the cameras of the photos in ``root``. Returns (model folder, report, reused).

    Args:
        max_size: long side (px) the photos are shrunk to before SfM and training (0: as taken).
        min_images: fewest photos accepted. Others: see :func:`~l3d_app.data.sfm.solve_cameras`.
    """
    if root is None or not str(root).strip() or str(root) == "???":
        raise UserError("data=images needs a folder of photos: add data.root=DIR")
    folder = resolve_path(str(root))
    files = photo_files(folder)
    if len(files) < max(2, int(min_images)):
        raise UserError(f"found {len(files)} photos (JPEG/PNG) in {folder}: structure-from-motion needs at least "
                        f"{max(2, int(min_images))} overlapping photos (20 or more for a model worth training)")
    solve = {**_solve_settings(max_features, min_registered, seed), "matcher": "exhaustive"}
    key = content_key(files, {**solve, "max_size": int(max_size), "kind": "images"})
    names = staged_names(files)
    return solved_capture(resolve_path(cache_dir), folder.name or "images", key,
                          lambda: (names, lambda i: shrink(read_photo(files[i]), int(max_size))), solve)


def video_capture(path, frames: int = 120, min_sharpness: float = 0.5, max_size: int = 1600, min_images: int = 3,
                  overlap: int = 10, max_features: int = 8192, min_registered: float = 0.5, seed: int = 0,
                  cache_dir: str = "outputs/.cache/sfm") -> Tuple[Path, SfmReport, bool]:
    """Solve (or reuse) the cameras of ``frames`` sharp frames of the video at ``path`` (see
    :func:`~l3d_app.data.photo_inputs.video_frames`); sequential matching with ``overlap`` successors."""
    if path is None or not str(path).strip() or str(path) == "???":
        raise UserError("data=video needs a video file: add data.path=FILE.mp4")
    if int(frames) < 2:
        raise UserError(f"data.frames must be at least 2, got {frames}")
    video = resolve_path(str(path))
    if not video.is_file():
        raise UserError(f"video not found: {video}")
    solve = {**_solve_settings(max_features, min_registered, seed), "matcher": "sequential", "overlap": int(overlap)}
    key = content_key([video], {**solve, "max_size": int(max_size), "frames": int(frames),
                                "min_sharpness": float(min_sharpness), "kind": "video"})

    def staged():
        imgs, note = video_frames(video, int(frames), float(min_sharpness), int(max_size))
        print(f"l3d_app: note: {video.name}: {note['decoded']} frames decoded, {note['kept']} kept, "
              f"{note['blurry']} dropped as blurry", file=sys.stderr)
        if len(imgs) < max(2, int(min_images)):
            raise UserError(f"{video}: {len(imgs)} sharp frames of {note['decoded']} decoded: structure-from-motion "
                            f"needs at least {max(2, int(min_images))} (a longer or steadier video, or more data.frames)")
        return [f"frame_{i:05d}.png" for i in range(len(imgs))], lambda i: imgs[i]

    return solved_capture(resolve_path(cache_dir), video.stem or "video", key, staged, solve)


def _dataset(folder: Path, name: str, kwargs: dict, device) -> MultiViewData:
    fixed = sorted(set(kwargs) & {"root", "images", "sparse"})
    if fixed:
        raise UserError(f"data.{fixed[0]} is set by structure-from-motion for {name.split(':')[0]}: leave it out")
    check_keywords(f"data '{name.split(':')[0]}'", colmap, kwargs)
    data = colmap(root=str(folder), images="images", sparse="sparse", device=device, **kwargs)
    data.name = name
    return data


@DATASETS.register("images")
def images(root=None, max_size: int = 1600, min_images: int = 3, max_features: int = 8192, min_registered: float = 0.5,
           seed: int = 0, cache_dir: str = "outputs/.cache/sfm", image_size: int = TRAIN_SIZE, device=None,
           **colmap_kwargs) -> MultiViewData:
    """A folder of photos, cameras by SfM, then as ``data=colmap`` (``colmap_kwargs``: its knobs) with
    the images resized to ``image_size`` px on the long side (:data:`TRAIN_SIZE`)."""
    folder, _, _ = images_capture(root, max_size, min_images, max_features, min_registered, seed, cache_dir)
    return _dataset(folder, f"images:{resolve_path(str(root)).name}", {**colmap_kwargs, "image_size": image_size},
                    device)


@DATASETS.register("video")
def video(path=None, frames: int = 120, min_sharpness: float = 0.5, max_size: int = 1600, min_images: int = 3,
          overlap: int = 10, max_features: int = 8192, min_registered: float = 0.5, seed: int = 0,
          cache_dir: str = "outputs/.cache/sfm", image_size: int = TRAIN_SIZE, device=None,
          **colmap_kwargs) -> MultiViewData:
    """Frames of a video, cameras by SfM, then as ``data=colmap`` (``colmap_kwargs``: its knobs) with
    the frames resized to ``image_size`` px on the long side (:data:`TRAIN_SIZE`)."""
    folder, _, _ = video_capture(path, frames, min_sharpness, max_size, min_images, overlap, max_features,
                                 min_registered, seed, cache_dir)
    return _dataset(folder, f"video:{resolve_path(str(path)).stem}", {**colmap_kwargs, "image_size": image_size},
                    device)
