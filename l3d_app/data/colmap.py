"""``data=colmap data.root=DIR``: a COLMAP capture, ``DIR/<images>/`` + ``DIR/sparse/0/``
(``cameras``, ``images``, ``points3D`` as ``.bin`` or ``.txt``, read by
:mod:`l3d_app.data.colmap_model`).

Camera models PINHOLE, SIMPLE_PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV; distorted images are
undistorted once at load (:func:`~l3d_app.geometry.distortion.undistort_image`, same
intrinsics), so the dataset's cameras are pinhole. ``images=images_2`` reads a pre-downscaled
folder (intrinsics scaled by the actual image size), ``downscale`` shrinks further by an
integer factor, and ``image_size`` > 0 resizes the long side to that many pixels (intrinsics scaled by
the exact factor). Splits, normalisation, scene box and background: :mod:`l3d_app.data.captures`.
The sparse points (normalised) and their colours are the dataset's initial ``points`` /
``point_colors``; up is the cameras' mean up vector.
"""

from __future__ import annotations

import numpy as np
import torch

from l3d_app.data.captures import (border_background, camera_spread, image_files, load_images,
                                   normalize_scene, scene_box, split_by_name)
from l3d_app.data.colmap_model import find_model_files, qvec_to_rotmat, read_model
from l3d_app.data.nerf_views import MultiViewData, background_rgb
from l3d_app.geometry.pose_checks import check_rigid_poses
from l3d_app.errors import UserError
from l3d_app.geometry.cameras import Cameras
from l3d_app.registry import DATASETS
from l3d_app.runtime.paths import resolve_path


@DATASETS.register("colmap")
def colmap(root: str = None, images: str = "images", sparse: str = "sparse/0", downscale: int = 1,
           test_every: int = 8, val_every: int = 8, normalize: bool = True, camera_radius: float = 3.0,
           box_percentile: float = 2.0, box_margin: float = 0.1, background="auto", max_views: int = 0,
           image_size: int = 0, device=None) -> MultiViewData:
    """A COLMAP folder (see the module docstring). ``max_views`` > 0 keeps the first views by
    name (quick runs; splits are taken after); ``image_size`` > 0: long side (px) the images are
    resized to after ``downscale`` when longer."""
    if root is None or not str(root).strip() or str(root) == "???":
        raise UserError("data=colmap needs a folder: add data.root=DIR (with images/ and sparse/0/)")
    folder = resolve_path(str(root))
    if not folder.is_dir():
        raise UserError(f"colmap data folder not found: {folder}")
    if int(downscale) < 1:
        raise UserError(f"downscale must be an integer >= 1, got {downscale}")
    if int(image_size) < 0:
        raise UserError(f"image_size must be a long side in pixels >= 0 (0: as stored), got {image_size}")
    sparse_dir = folder / sparse
    model = read_model(sparse_dir)
    if len(model.names) == 0:
        raise UserError(f"{sparse_dir}: the model has no registered images")
    order = sorted(range(len(model.names)), key=lambda i: model.names[i])
    if int(max_views) > 0:
        order = order[: int(max_views)]
    names = [model.names[i] for i in order]
    q, tvec, cam_ids = model.qvec[order], model.tvec[order], model.camera_ids[order]
    bad_q = ~np.isfinite(q).all(1) | (np.linalg.norm(q, axis=1) < 1e-8)
    src = str(find_model_files(sparse_dir)[1])
    if bad_q.any():
        raise UserError(f"{src}: image {names[int(bad_q.argmax())]}: camera pose has a non-finite or zero quaternion")
    R = torch.from_numpy(qvec_to_rotmat(q))
    t = torch.from_numpy(tvec.copy())
    check_rigid_poses(R, t, src, names)

    intr, dists, sizes = [], [], []
    for cid in cam_ids.tolist():
        cam = model.cameras[cid]
        fx, fy, cx, cy, dist = cam.intrinsics()
        intr.append((fx, fy, cx, cy))
        dists.append(dist)
        sizes.append((cam.width, cam.height))
    files = image_files(folder / images, names, src)
    composite = background_rgb("white") if isinstance(background, str) and background == "auto" \
        else background_rgb(background)
    imgs, K = load_images(files, sizes, np.array(intr), np.array(dists), int(downscale), composite,
                          cam_ids.tolist(), str(folder / images), int(image_size))
    pts = torch.from_numpy(model.points.copy()) if len(model.points) else None
    cols = torch.from_numpy(model.colors.astype(np.float32) / 255.0) if pts is not None else None
    train, val, test = split_by_name(names, int(test_every), int(val_every))
    M = torch.eye(4, dtype=torch.float64)
    if normalize:
        t, pts, M = normalize_scene(R, t, pts, float(camera_radius), fit_on=train)
    H, W = imgs.shape[1:3]
    Kt = torch.from_numpy(K)
    cams = Cameras(R.float(), t.float(), Kt[:, 0].float(), Kt[:, 1].float(), Kt[:, 2].float(), Kt[:, 3].float(), W, H)
    bg, known = border_background(imgs[train], background)
    box = scene_box(pts, float(camera_radius) if normalize else camera_spread(cams[train]),
                    float(box_percentile), float(box_margin), cameras=cams[train])
    data = MultiViewData(imgs, cams, train, val, test, bg, box, name=f"colmap:{folder.name}",
                         points=None if pts is None else pts.float(), point_colors=cols,
                         source_from_world=M, background_known=known)
    return data if device is None else data.to(device)
