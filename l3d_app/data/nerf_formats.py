"""Loaders for real multi-view formats into :class:`~l3d_app.data.nerf_views.MultiViewData`.

* ``data=blender data.root=DIR``: NeRF-synthetic folders. ``transforms_{train,val,test}.json``
  each hold ``camera_angle_x`` (horizontal field of view, radians) and ``frames[]`` with
  ``file_path`` (relative to DIR, ``.png`` added when missing) and ``transform_matrix``
  (4x4 OpenGL camera-to-world: +X right, +Y up, looking down -Z), converted with
  :func:`~l3d_app.geometry.cameras.from_opengl_c2w`. RGBA PNGs are composited on the
  configured background (``rgb * a + bg * (1 - a)``); ``downscale`` shrinks images by an
  integer factor (area averaging of premultiplied colour) and the focal length with them.
  A missing ``transforms_val.json``: validation is carved from the training views (every
  ``val_every``-th, :func:`~l3d_app.data.nerf_views.carve_val`), never from test. Up is +Z
  (Blender's world). Every ``transform_matrix`` must be finite and rigid
  (:func:`~l3d_app.geometry.pose_checks.check_rigid_poses`), else one line names the frame.
* ``data=truck data.root=DIR``: the course truck scene (``../shared/data/README.md``):
  ``imgs/frameXXXXXX.jpg`` and ``poses/frameXXXXXX.npy`` = ``[R (9, row-major) | T (3) |
  F (2, NDC) | C (2, NDC)]`` in the PyTorch3D convention, converted with
  :func:`~l3d_app.geometry.cameras.from_pytorch3d`; the course test split
  ``[33, 67, 101, 134, 168]``; the scene box is the bounding box of
  ``points/points_10000.npy`` grown by ``box_margin`` of its extent per side; those points
  are the dataset's initial ``points`` (no colours). Validation: every ``val_every``-th of
  the 197 training frames; the 5 published test frames are never touched. Up: the
  cameras' mean up vector.

Relative roots are resolved with :func:`~l3d_app.runtime.paths.resolve_path`.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Sequence

import numpy as np
import torch

from l3d_app.data.array_files import load_array_file, numeric_array
from l3d_app.data.json_frames import check_frame_entries, json_number
from l3d_app.data.nerf_views import MultiViewData, background_rgb, carve_val, scene_box_tensor
from l3d_app.geometry.pose_checks import check_finite, check_rigid_poses
from l3d_app.errors import UserError
from l3d_app.geometry.cameras import from_opengl_c2w, from_pytorch3d, stack_cameras
from l3d_app.registry import DATASETS
from l3d_app.runtime.files import read_json
from l3d_app.runtime.paths import resolve_path

SPLITS = ("train", "val", "test")


def _read_image(path: Path) -> np.ndarray:
    import imageio.v2 as imageio

    if not path.is_file():
        raise UserError(f"image file missing: {path}")
    try:
        return np.asarray(imageio.imread(path))
    except Exception as err:  # noqa: BLE001 - any decoder failure is the user's file
        raise UserError(f"cannot read image {path}: {err}") from err


def _to_float_rgb(img: np.ndarray, bg: torch.Tensor, downscale: int) -> torch.Tensor:
    """uint8/uint16 (H, W[, 3|4]) -> (H/s, W/s, 3) float in [0, 1] composited on ``bg``."""
    return _to_float_rgb_alpha(img, bg, downscale)[0]


def _to_float_rgb_alpha(img: np.ndarray, bg: torch.Tensor, downscale: int):
    """As :func:`_to_float_rgb`, plus the (H/s, W/s) alpha in [0, 1] of an RGBA image (None for RGB)."""
    scale = 65535.0 if img.dtype == np.uint16 else 255.0
    x = torch.from_numpy(img.astype(np.float32) / scale)
    if x.dim() == 2:
        x = x[..., None].expand(-1, -1, 3)
    if x.shape[-1] == 4:
        x = torch.cat([x[..., :3] * x[..., 3:], x[..., 3:]], dim=-1)     # premultiplied, then pooled
    else:
        x = x[..., :3]
    if downscale > 1:
        h, w = x.shape[0] // downscale * downscale, x.shape[1] // downscale * downscale
        x = torch.nn.functional.avg_pool2d(x[:h, :w].permute(2, 0, 1)[None], downscale)[0].permute(1, 2, 0)
    alpha = None
    if x.shape[-1] == 4:
        alpha = x[..., 3].clamp(0, 1).contiguous()
        x = x[..., :3] + (1.0 - x[..., 3:]) * bg
    return x.clamp(0, 1).contiguous(), alpha


@DATASETS.register("blender")
def blender(root: str = None, background="white", downscale: int = 1,
            scene_box: Sequence[Sequence[float]] = ((-1.5,) * 3, (1.5,) * 3), max_views: int = 0,
            val_every: int = 8, mesh_path: str = None, device=None) -> MultiViewData:
    """A NeRF-synthetic folder (see the module docstring); ``max_views`` > 0 keeps the first
    views of each split (quick runs); ``val_every`` carves validation from train when the
    folder has no ``transforms_val.json``; ``mesh_path`` (relative to ``root`` or absolute):
    the true surface, in the cameras' world frame, for the surface scores (e.g. the
    ``mesh.ply`` that ``bench/make_scenes.py`` writes)."""
    if root is None or not str(root).strip() or str(root) == "???":
        raise UserError("data=blender needs a folder: add data.root=DIR (with transforms_train.json ...)")
    folder = resolve_path(str(root))
    if not folder.is_dir():
        raise UserError(f"blender data folder not found: {folder}")
    if int(downscale) < 1:
        raise UserError(f"downscale must be an integer >= 1, got {downscale}")
    bg = background_rgb(background)
    images, alphas, cams, splits, start = [], [], [], {}, 0
    for split in SPLITS:
        path = folder / f"transforms_{split}.json"
        if not path.is_file():
            if split == "val":
                splits[split] = torch.zeros(0, dtype=torch.long)
                continue
            raise UserError(f"missing {path.name} in {folder}")
        meta = read_json(path)
        if not isinstance(meta, dict):
            raise UserError(f"{path}: expected a JSON object with camera_angle_x and frames, got {type(meta).__name__}")
        for key in ("camera_angle_x", "frames"):
            if key not in meta:
                raise UserError(f"{path} has no '{key}' key")
        fov = json_number(meta["camera_angle_x"], f"{path}: camera_angle_x")      # before any image is read
        if not 0.0 < fov < math.pi:                    # also false for NaN
            raise UserError(f"{path}: camera_angle_x must be a field of view in (0, pi) radians, got {fov}")
        frames = check_frame_entries(meta["frames"], path)
        frames = frames[: int(max_views)] if int(max_views) > 0 else frames
        if not frames:
            raise UserError(f"{path} lists no frames")
        c2w, imgs = [], []
        for i, fr in enumerate(frames):
            file = folder / Path(fr["file_path"])
            if file.suffix == "":
                file = file.with_suffix(".png")
            rgb, alpha = _to_float_rgb_alpha(_read_image(file), bg, int(downscale))
            imgs.append(rgb)
            alphas.append(alpha)
            try:
                m = torch.tensor(fr["transform_matrix"], dtype=torch.float64)
            except (ValueError, TypeError) as err:
                raise UserError(f"{path}: frame {i} transform_matrix is not a 4x4 list of numbers: {err}") from err
            if m.shape not in ((4, 4), (3, 4)):
                raise UserError(f"{path}: frame {i} transform_matrix must be 4x4, got {tuple(m.shape)}")
            c2w.append(m[:3])
        c2w_all = torch.stack(c2w)
        check_rigid_poses(c2w_all[:, :3, :3], c2w_all[:, :3, 3], path.name,
                          [f"frame {i} ({fr['file_path']})" for i, fr in enumerate(frames)])
        sizes = {tuple(im.shape) for im in imgs}
        if len(sizes) != 1:
            raise UserError(f"{path}: images have different sizes {sorted(sizes)}")
        h, w = imgs[0].shape[:2]
        focal = 0.5 * w / math.tan(0.5 * fov)
        cams.append(from_opengl_c2w(c2w_all, focal, focal, w / 2.0, h / 2.0, w, h).to(dtype=torch.float32))
        images += imgs
        splits[split] = torch.arange(start, start + len(imgs))
        start += len(imgs)
    if len({(c.width, c.height) for c in cams}) != 1:
        raise UserError(f"splits in {folder} have different image sizes")
    if not (folder / "transforms_val.json").is_file():
        splits["train"], splits["val"] = carve_val(splits["train"], int(val_every))
    box = scene_box_tensor(scene_box)
    mesh = None
    if mesh_path:
        from l3d_app.geometry.mesh_io import load_mesh

        mesh_file = Path(mesh_path) if Path(mesh_path).is_absolute() else folder / str(mesh_path)
        if not mesh_file.is_file():
            raise UserError(f"data.mesh_path: no such file {mesh_file}")
        mesh = load_mesh(mesh_file)
    masks = torch.stack(alphas) if all(a is not None for a in alphas) else None   # RGBA everywhere: coverage
    data = MultiViewData(torch.stack(images), stack_cameras(cams), splits["train"], splits["val"], splits["test"],
                         bg, box, name=f"blender:{folder.name}", up=torch.tensor([0.0, 0.0, 1.0]), mesh=mesh,
                         masks=masks)
    return data if device is None else data.to(device)


@DATASETS.register("truck")
def truck(root: str = "../shared/data/truck", test_indices: Sequence[int] = (33, 67, 101, 134, 168),
          background="black", box_margin: float = 0.1, val_every: int = 20, device=None) -> MultiViewData:
    """The course truck scene (see the module docstring): 202 images (90, 160, 3)."""
    folder = resolve_path(str(root))
    img_dir, pose_dir = folder / "imgs", folder / "poses"
    if not img_dir.is_dir() or not pose_dir.is_dir():
        raise UserError(f"truck data needs {folder}/imgs and {folder}/poses (set data.root=DIR)")
    files = sorted(img_dir.glob("*.jpg"))
    if not files:
        raise UserError(f"no .jpg images in {img_dir}")
    images, poses = [], []
    for f in files:
        pose_file = pose_dir / (f.stem + ".npy")
        if not pose_file.is_file():
            raise UserError(f"pose file missing: {pose_file}")
        pose = numeric_array(load_array_file(pose_file, allow_pickle=False), str(pose_file), np.float64).reshape(-1)
        if pose.shape[0] != 16:
            raise UserError(f"{pose_file} must hold 16 values [R(9) T(3) F(2) C(2)], got {pose.shape[0]}")
        poses.append(pose)
        images.append(torch.from_numpy(_read_image(f)[..., :3].astype(np.float32) / 255.0))
    sizes = sorted({tuple(im.shape[:2]) for im in images})
    if len(sizes) != 1:
        raise UserError(f"truck images in {img_dir} have different sizes (h, w) {sizes}")
    p = torch.tensor(np.stack(poses))
    check_rigid_poses(p[:, :9].reshape(-1, 3, 3), p[:, 9:12], str(pose_dir), [f.stem + ".npy" for f in files])
    check_finite(p[:, 12:], str(pose_dir), "pose intrinsics of frame")
    if not bool((p[:, 12:14] > 0).all()):
        raise UserError(f"{pose_dir}: focal lengths F (values 13-14 of each pose) must be positive")
    h, w = images[0].shape[:2]
    cams = from_pytorch3d(p[:, :9].reshape(-1, 3, 3), p[:, 9:12], p[:, 12:14], p[:, 14:16],
                          image_size=(h, w), in_ndc=True).to(dtype=torch.float32)
    n = len(files)
    test = torch.tensor([int(i) for i in test_indices], dtype=torch.long)
    if len(test) and (int(test.max()) >= n or int(test.min()) < 0):
        raise UserError(f"truck test indices {list(test_indices)} out of range for {n} images")
    held = set(test.tolist())
    train, val = carve_val(torch.tensor([i for i in range(n) if i not in held], dtype=torch.long), int(val_every))
    pts_file = folder / "points" / "points_10000.npy"
    pts = None
    if pts_file.is_file():
        raw_pts = numeric_array(load_array_file(pts_file, allow_pickle=False), str(pts_file))
        if raw_pts.ndim != 2 or raw_pts.shape[1] != 3 or raw_pts.shape[0] == 0:
            raise UserError(f"{pts_file} must hold an (N, 3) array of points, got shape {raw_pts.shape}")
        pts = torch.from_numpy(raw_pts)
        check_finite(pts, str(pts_file), "point")
        lo, hi = pts.min(0).values, pts.max(0).values
    else:
        centres = cams.centers()
        lo, hi = centres.min(0).values, centres.max(0).values
    pad = float(box_margin) * (hi - lo)
    data = MultiViewData(torch.stack(images), cams, train, val, test,
                         background_rgb(background), torch.stack([lo - pad, hi + pad]), name="truck", points=pts)
    return data if device is None else data.to(device)
