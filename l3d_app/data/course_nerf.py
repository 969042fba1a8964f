"""Two NeRF tutorial layouts, as :class:`~l3d_app.data.nerf_views.MultiViewData`.

* ``data=tiny_nerf data.path=tiny_nerf_data.npz``: the NeRF tutorial staple, one ``.npz`` with
  ``images`` (N, H, W, 3) float in [0, 1] (black background), ``poses`` (N, 4, 4) OpenGL
  camera-to-world (NeRF convention, +Z up world) and ``focal`` (pixels). The tutorial trains on
  the first 100 views and shows view 101: here test = views ``n_train``.. (default 100..), val =
  every ``val_every``-th of the first ``n_train``.
* ``data=course_lego data.root=DIR data.scene=lego|materials``: the neural-rendering
  assignment's data as its ``dataset.py`` (PyTorch3D's NeRF project layout) reads it:
  ``DIR/<scene>.pth`` = ``torch.save({"cameras": {"R": (N,3,3), "T": (N,3),
  "focal_length": (N,2), "principal_point": (N,2)}, "split": [train, val, test]})`` with
  PyTorch3D ``PerspectiveCameras`` in NDC, and ``DIR/<scene>.png`` = the N images stacked
  vertically in one PNG (``torch.chunk`` along rows). ``image_size=[H, W]`` resizes
  bilinearly as the course does (NDC intrinsics are unchanged by an isotropic resize); the
  course's own train / val / test split is used as is.

Poses are checked finite and rigid (:mod:`l3d_app.geometry.pose_checks`).
"""

from __future__ import annotations

import math
from typing import Optional, Sequence

import numpy as np
import torch

from l3d_app.data.nerf_formats import _read_image, _to_float_rgb
from l3d_app.data.nerf_views import MultiViewData, background_rgb, carve_val, disjoint_splits, scene_box_tensor
from l3d_app.geometry.pose_checks import check_rigid_poses
from l3d_app.errors import UserError
from l3d_app.geometry.cameras import from_opengl_c2w, from_pytorch3d
from l3d_app.registry import DATASETS
from l3d_app.runtime.paths import resolve_path


COURSE_VAL_EVERY = 10   # course_lego: validation carved from train when the file's val split is its test split


@DATASETS.register("tiny_nerf")
def tiny_nerf(path: str = None, n_train: int = 100, val_every: int = 10, background="black",
              scene_box: Sequence[Sequence[float]] = ((-2.0,) * 3, (2.0,) * 3), device=None) -> MultiViewData:
    """``tiny_nerf_data.npz`` (see the module docstring)."""
    if path is None or str(path) in ("", "???"):
        raise UserError("data=tiny_nerf needs the file: add data.path=tiny_nerf_data.npz")
    file = resolve_path(str(path))
    if not file.is_file():
        raise UserError(f"tiny_nerf file not found: {file}")
    try:
        z = np.load(file)
        images, poses, focal = z["images"], z["poses"], float(np.asarray(z["focal"]).reshape(-1)[0])
    except KeyError as err:
        raise UserError(f"{file}: no {err} array (needs images, poses, focal)") from err
    except Exception as err:  # noqa: BLE001 - any reader failure is the user's file
        raise UserError(f"cannot read {file}: {err}") from err
    if images.ndim != 4 or images.shape[-1] not in (3, 4) or poses.shape != (len(images), 4, 4):
        raise UserError(f"{file}: images must be (N, H, W, 3) and poses (N, 4, 4), got {images.shape}, {poses.shape}")
    if not (math.isfinite(focal) and focal > 0):
        raise UserError(f"{file}: focal must be a positive number, got {focal}")
    c2w = torch.from_numpy(poses.astype(np.float64))
    check_rigid_poses(c2w[:, :3, :3], c2w[:, :3, 3], file.name)
    n, (H, W) = len(images), images.shape[1:3]
    if H < 1 or W < 1:
        raise UserError(f"{file}: images are {H} x {W} pixels")
    if not np.isfinite(images).all():
        raise UserError(f"{file}: images contain NaN or Inf")
    k = min(int(n_train), n - 1)
    if k < 1:
        raise UserError(f"{file}: needs at least 2 views (train + test), got {n}")
    imgs = torch.from_numpy(images.astype(np.float32))
    imgs = imgs / 255.0 if float(imgs.max()) > 1.5 else imgs
    bg = background_rgb(background)
    if imgs.shape[-1] == 4:
        imgs = imgs[..., :3] * imgs[..., 3:] + bg * (1 - imgs[..., 3:])
    cams = from_opengl_c2w(c2w[:, :3], focal, focal, W / 2.0, H / 2.0, W, H).to(dtype=torch.float32)
    train, val = carve_val(torch.arange(k), int(val_every))
    box = scene_box_tensor(scene_box)
    data = MultiViewData(imgs.clamp(0, 1).contiguous(), cams, train, val, torch.arange(k, n), bg, box,
                         name=f"tiny_nerf:{file.stem}", up=torch.tensor([0.0, 0.0, 1.0]))
    return data if device is None else data.to(device)


@DATASETS.register("course_lego")
def course_lego(root: str = None, scene: str = "lego", image_size: Optional[Sequence[int]] = None,
                background="black", scene_box: Sequence[Sequence[float]] = ((-1.5,) * 3, (1.5,) * 3),
                device=None) -> MultiViewData:
    """``DIR/<scene>.pth`` + ``DIR/<scene>.png`` (see the module docstring)."""
    if root is None or str(root) in ("", "???"):
        raise UserError("data=course_lego needs a folder: add data.root=DIR (with lego.pth and lego.png)")
    folder = resolve_path(str(root))
    pth, png = folder / f"{scene}.pth", folder / f"{scene}.png"
    for f in (pth, png):
        if not f.is_file():
            raise UserError(f"course NeRF data: {f} not found (data.scene={scene})")
    try:
        meta = torch.load(pth, map_location="cpu", weights_only=True)
        cam = meta["cameras"]
        R, T = cam["R"].double(), cam["T"].double()
        focal, pp = cam["focal_length"].double(), cam["principal_point"].double()
        split = [torch.as_tensor(s, dtype=torch.long).reshape(-1) for s in meta["split"]]
    except KeyError as err:
        raise UserError(f"{pth}: missing key {err} (needs cameras.R/T/focal_length/principal_point and split)") from err
    except Exception as err:  # noqa: BLE001 - any reader failure is the user's file
        raise UserError(f"cannot read {pth}: {err}") from err
    n = R.shape[0]
    if len(split) != 3 or T.shape != (n, 3) or focal.shape[0] != n or pp.shape[0] != n:
        raise UserError(f"{pth}: expected N cameras with R (N,3,3), T (N,3), focal (N,2), pp (N,2) and 3 splits")
    check_rigid_poses(R, T, pth.name)
    bg = background_rgb(background)
    strip = _to_float_rgb(_read_image(png), bg, 1)
    if strip.shape[0] % n:
        raise UserError(f"{png}: height {strip.shape[0]} is not a multiple of the {n} cameras in {pth.name}")
    images = torch.stack(torch.chunk(strip, n, dim=0))
    if image_size is not None:
        h, w = (int(v) for v in image_size)
        if h < 1 or w < 1:
            raise UserError(f"image_size must be two positive sizes, got {[h, w]}")
        if abs(h / images.shape[1] - w / images.shape[2]) > 1e-3:
            raise UserError(f"image_size {[h, w]} is not an isotropic resize of {list(images.shape[1:3])}")
        images = torch.nn.functional.interpolate(images.permute(0, 3, 1, 2), size=(h, w), mode="bilinear"
                                                 ).permute(0, 2, 3, 1).contiguous()
    H, W = images.shape[1:3]
    for s in split:
        if len(s) and (int(s.max()) >= n or int(s.min()) < 0):
            raise UserError(f"{pth}: split index out of range for {n} cameras")
    if len(split[0]) == 0:
        raise UserError(f"{pth}: the train split is empty")
    cams = from_pytorch3d(R, T, focal, pp, image_size=(H, W), in_ndc=True).to(dtype=torch.float32)
    box = scene_box_tensor(scene_box)
    train, val, test = disjoint_splits(split[0], split[1], split[2], COURSE_VAL_EVERY, str(pth))
    data = MultiViewData(images, cams, train, val, test, bg, box, name=f"course_lego:{scene}")
    return data if device is None else data.to(device)
