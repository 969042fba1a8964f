"""What every real-capture loader (COLMAP, nerfstudio) does after parsing its poses: read and
resize the images (undistorting once), pick the splits, normalise the scene, bound it.

Conventions shared by ``data=colmap`` and ``data=nerfstudio``:

* Splits: test = every ``test_every``-th image by sorted name (index % test_every == 0,
  the Mip-NeRF 360 / gsplat convention); val = every ``val_every``-th of the rest
  (:func:`~l3d_app.data.nerf_views.carve_val`); train = the remainder.
* Normalisation (``normalize=true``): world points ``x' = s (x - c)`` with ``c`` the mean
  centre of the training cameras and ``s = camera_radius / median |C_i - c|`` over them; the
  inverse is kept as the dataset's ``source_from_world`` (4x4) so exports map back to the
  capture's coordinates. The val and test poses take no part (nor in the box's focus point, nor
  in the unnormalised radius): the set-up reads nothing of the views a run is scored on.
* Scene box: the ``box_percentile`` .. ``100 - box_percentile`` per-axis range of the sparse
  points grown by ``box_margin`` of its extent per side; without points, a cube of half-size
  ``camera_radius / 2`` about the cameras' focus point (:func:`focus_point`: where their optical
  axes meet, which for a capture from above lies below the cameras' mean), or about the origin
  when the axes do not meet in front of the cameras (a forward-facing capture).
* Background: real photographs have one. ``background=auto`` takes the per-channel median of
  the training images' border pixels as the initial colour and sets
  ``background_known=False`` on the dataset: fields should learn the colour behind the box
  (initialised there), since nothing outside the box is modelled.
"""

from __future__ import annotations

from pathlib import Path
from typing import List, Optional, Sequence, Tuple

import numpy as np
import torch

from l3d_app.data.nerf_formats import _read_image, _to_float_rgb
from l3d_app.data.nerf_views import background_rgb, carve_val
from l3d_app.geometry.cameras import Cameras
from l3d_app.errors import UserError
from l3d_app.geometry.distortion import undistort_image


def split_by_name(names: Sequence[str], test_every: int, val_every: int
                  ) -> Tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(train, val, test) index tensors for images already sorted by ``names``."""
    n = len(names)
    idx = torch.arange(n)
    k = int(test_every)
    is_test = (idx % k == 0) if k > 0 else torch.zeros(n, dtype=torch.bool)
    if k > 0 and n > 1 and bool(is_test.all()):
        raise UserError(f"test_every={k} leaves no training images among {n}")
    train, val = carve_val(idx[~is_test], int(val_every))
    return train, val, idx[is_test]


def normalize_scene(R: torch.Tensor, t: torch.Tensor, points: Optional[torch.Tensor], camera_radius: float,
                    fit_on: Optional[torch.Tensor] = None
                    ) -> Tuple[torch.Tensor, Optional[torch.Tensor], torch.Tensor]:
    """Centre the ``fit_on`` cameras at the origin and scale their median distance to ``camera_radius``.

    Args:
        R: (N, 3, 3) world->camera (unchanged by a similarity); t: (N, 3); points: (P, 3) or None.
        fit_on: indices of the cameras that set the centre and scale (the training split); None: all.
    Returns:
        new t (N, 3) of every camera, new points, and the (4, 4) float64 ``source_from_world``.
    """
    R64, t64 = R.double(), t.double()
    centres = -(R64.transpose(1, 2) @ t64[..., None])[..., 0]
    if fit_on is not None and len(fit_on):
        centres = centres[fit_on]
    c = centres.mean(0)
    med = float((centres - c).norm(dim=-1).median()) if len(centres) > 1 else 0.0
    s = float(camera_radius) / med if med > 1e-12 else 1.0
    t_new = s * (t64 + (R64 @ c[:, None])[..., 0])
    pts = None if points is None else (s * (points.double() - c))
    M = torch.eye(4, dtype=torch.float64)
    M[:3, :3] /= s
    M[:3, 3] = c
    return t_new, pts, M


def camera_spread(cameras: Cameras) -> float:
    """Median distance (scene units) of the cameras' centres from their mean."""
    c = cameras.centers().double()
    return float((c - c.mean(0)).norm(dim=-1).median())


def focus_point(cameras: Cameras, min_spread: float = 0.05, min_in_front: float = 0.9) -> Optional[torch.Tensor]:
    """(3,) float64 point nearest, in least squares, to every camera's optical axis, or None.

    Args:
        cameras: N cameras (each looks along its +Z).
        min_spread: smallest eigenvalue of ``mean(I - d d^T)`` accepted (0 when all axes are parallel).
        min_in_front: share of cameras that must have the point in front of them.
    """
    centres = cameras.centers().double()                                       # (N, 3)
    axes = cameras.R.double()[:, 2, :]                                           # (N, 3) unit viewing axes
    proj = torch.eye(3, dtype=torch.float64) - axes[:, :, None] * axes[:, None, :]   # (N, 3, 3)
    A = proj.mean(0)
    if len(centres) < 2 or float(torch.linalg.eigvalsh(A)[0]) < float(min_spread):
        return None
    p = torch.linalg.solve(A, (proj @ centres[..., None])[..., 0].mean(0))
    in_front = (((p - centres) * axes).sum(-1) > 0).double().mean()
    return p if float(in_front) >= float(min_in_front) else None


def scene_box(points: Optional[torch.Tensor], camera_radius: float, percentile: float = 2.0,
              margin: float = 0.1, cameras: Optional[Cameras] = None) -> torch.Tensor:
    """(2, 3) box from robust per-axis percentiles of ``points``; with fewer than 10 points a cube of
    half-size ``camera_radius / 2`` about the ``cameras``' :func:`focus_point`, else about the origin."""
    if points is not None and len(points) >= 10:
        q = torch.tensor([percentile / 100.0, 1.0 - percentile / 100.0], dtype=torch.float64)
        lo, hi = torch.quantile(points.double(), q, dim=0)
        pad = float(margin) * (hi - lo).clamp_min(1e-6)
        return torch.stack([lo - pad, hi + pad]).float()
    h = 0.5 * float(camera_radius)
    focus = None if cameras is None else focus_point(cameras)
    c = torch.zeros(3) if focus is None else focus.float()
    return torch.stack([c - h, c + h])


def load_images(files: Sequence[Path], sizes: Sequence[Tuple[int, int]], intrinsics: np.ndarray,
                dists: np.ndarray, downscale: int, bg: torch.Tensor, group: Sequence[int], source: str,
                image_size: int = 0) -> Tuple[torch.Tensor, np.ndarray]:
    """Read, undistort (once) and downscale the images.

    Args:
        files: N image paths. sizes: N (W, H) the poses' intrinsics refer to.
        intrinsics: (N, 4) fx, fy, cx, cy in pixels at ``sizes``; dists: (N, 6).
        downscale: integer factor. group: N camera ids (images of one camera must share a size).
        image_size: long side (px) the images are then resized to when longer (:func:`resize_long_side`; 0: off).
    Returns:
        (N, H, W, 3) float images and (N, 4) intrinsics at the returned size.
    """
    out, K, size_of = [], np.array(intrinsics, dtype=np.float64).copy(), {}
    for i, f in enumerate(files):
        raw = _read_image(Path(f))
        h0, w0 = raw.shape[:2]
        first = size_of.setdefault(group[i], (w0, h0, f))
        if first[:2] != (w0, h0):
            raise UserError(f"{f}: image is {w0}x{h0} but {Path(first[2]).name} under the same camera "
                            f"{group[i]} is {first[0]}x{first[1]} (mixed sizes under one camera)")
        img = _to_float_rgb(raw, bg, 1)
        W, H = sizes[i]
        sx, sy = w0 / float(W), h0 / float(H)             # pre-downscaled folders (images_2, ...)
        K[i] *= (sx, sy, sx, sy)
        if np.any(dists[i] != 0):
            img, _ = undistort_image(img, *K[i], dists[i])
        if downscale > 1:
            img = _to_float_rgb_pool(img, downscale)
        K[i] /= float(downscale)
        if int(image_size) > 0:
            img, (sx, sy) = resize_long_side(img, int(image_size))
            K[i] *= (sx, sy, sx, sy)
        out.append(img)
    shapes = {tuple(im.shape) for im in out}
    if len(shapes) != 1:
        raise UserError(f"{source}: images have different sizes {sorted(s[:2] for s in shapes)}; "
                        f"one size per dataset is supported")
    return torch.stack(out), K


def resize_long_side(img: torch.Tensor, size: int) -> Tuple[torch.Tensor, Tuple[float, float]]:
    """``img`` (H, W, 3) float resized so that its long side is ``size`` px when it is longer
    (antialiased bilinear, pixel centres at +0.5); returns it and the (x, y) factors new / old
    size, by which pixel coordinates and intrinsics scale. Images not longer are returned as they are."""
    h, w = img.shape[:2]
    if max(h, w) <= int(size):
        return img, (1.0, 1.0)
    s = int(size) / float(max(h, w))
    nh, nw = max(1, round(h * s)), max(1, round(w * s))
    out = torch.nn.functional.interpolate(img.permute(2, 0, 1)[None], size=(nh, nw), mode="bilinear",
                                          align_corners=False, antialias=True)
    return out[0].permute(1, 2, 0).clamp(0, 1).contiguous(), (nw / float(w), nh / float(h))


def _to_float_rgb_pool(img: torch.Tensor, s: int) -> torch.Tensor:
    h, w = img.shape[0] // s * s, img.shape[1] // s * s
    return torch.nn.functional.avg_pool2d(img[:h, :w].permute(2, 0, 1)[None], s)[0].permute(1, 2, 0).contiguous()


def border_background(images: torch.Tensor, background) -> Tuple[torch.Tensor, bool]:
    """(3,) background colour and whether it is known: ``auto`` = median border colour of
    ``images`` (N, H, W, 3), unknown; otherwise :func:`background_rgb`, known."""
    if isinstance(background, str) and background == "auto":
        border = torch.cat([images[:, 0], images[:, -1], images[:, :, 0], images[:, :, -1]], 1).reshape(-1, 3)
        return border.median(0).values.float(), False
    return background_rgb(background), True


def image_files(folder: Path, names: List[str], source: str) -> List[Path]:
    """Paths of ``names`` in ``folder``; a UserError naming the first missing one."""
    if not folder.is_dir():
        raise UserError(f"image folder not found: {folder} (set data.images=FOLDER)")
    files = [folder / n for n in names]
    for f, n in zip(files, names):
        if not f.is_file():
            raise UserError(f"{source}: image '{n}' listed but missing: {f}")
    return files
