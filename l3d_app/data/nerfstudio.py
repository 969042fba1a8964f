"""``data=nerfstudio data.root=DIR``: nerfstudio's ``transforms.json``.

Keys read (shared at the top level, or per frame, a frame's own value winning):
``fl_x, fl_y, cx, cy, w, h`` (pixels; pixel centres at +0.5 as ours), ``k1..k4, p1, p2``
(Brown-Conrady, :mod:`l3d_app.geometry.distortion`; images undistorted once at load) and
``camera_model`` (``OPENCV`` or ``PINHOLE``; fisheye / equirectangular are refused).
``frames[].file_path`` is relative to DIR; ``frames[].transform_matrix`` is an OpenGL
camera-to-world 4x4 (checked finite and rigid). ``applied_transform`` (3x4, the map
nerfstudio applied to the source poses) is folded into the dataset's
``source_from_world``, so exports map back to the capture's original (e.g. COLMAP)
coordinates. ``ply_file_path`` (a coloured point cloud, as ``ns-process-data`` writes it)
gives the initial ``points`` / ``point_colors`` (mapped like the poses).

Splits: ``train_filenames`` / ``val_filenames`` / ``test_filenames`` when present (paths as
in ``file_path``); otherwise test = every ``test_every``-th frame by sorted file name, val =
every ``val_every``-th of the rest. Normalisation, box and background as
:mod:`l3d_app.data.captures`.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Optional, Tuple

import numpy as np
import torch

from l3d_app.data.captures import (border_background, camera_spread, image_files, load_images,
                                   normalize_scene, scene_box, split_by_name)
from l3d_app.data.json_frames import check_frame_entries, json_number
from l3d_app.data.nerf_views import MultiViewData, background_rgb, disjoint_splits
from l3d_app.geometry.pose_checks import check_finite, check_rigid_poses
from l3d_app.errors import UserError
from l3d_app.geometry.cameras import Cameras, from_opengl_c2w
from l3d_app.registry import DATASETS
from l3d_app.runtime.files import read_json
from l3d_app.runtime.paths import resolve_path

INTRINSICS = ("fl_x", "fl_y", "cx", "cy", "w", "h")
DISTORTION = ("k1", "k2", "k3", "k4", "p1", "p2")
MODELS = ("OPENCV", "PINHOLE", "SIMPLE_PINHOLE")


def _norm(path: str) -> str:
    return os.path.normpath(str(path))


def _read_ply_points(path: Path) -> Tuple[np.ndarray, Optional[np.ndarray]]:
    import trimesh

    try:
        cloud = trimesh.load(str(path), process=False)
    except Exception as err:  # noqa: BLE001 - any parser failure is the user's file
        raise UserError(f"cannot read point cloud {path}: {err}") from err
    verts = np.asarray(getattr(cloud, "vertices", np.zeros((0, 3))), dtype=np.float64)
    cols = getattr(cloud, "colors", None)
    if cols is None or len(cols) != len(verts):
        cols = getattr(getattr(cloud, "visual", None), "vertex_colors", None)
    cols = None if cols is None or len(cols) != len(verts) else np.asarray(cols)[:, :3].astype(np.float32) / 255.0
    return verts, cols


@DATASETS.register("nerfstudio")
def nerfstudio(root: str = None, transforms: str = "transforms.json", downscale: int = 1, test_every: int = 8,
               val_every: int = 8, normalize: bool = True, camera_radius: float = 3.0, box_percentile: float = 2.0,
               box_margin: float = 0.1, background="auto", max_views: int = 0, device=None) -> MultiViewData:
    """A nerfstudio folder (see the module docstring)."""
    if root is None or not str(root).strip() or str(root) == "???":
        raise UserError("data=nerfstudio needs a folder: add data.root=DIR (with transforms.json)")
    folder = resolve_path(str(root))
    path = folder / transforms
    if not path.is_file():
        raise UserError(f"nerfstudio transforms file not found: {path}")
    if int(downscale) < 1:
        raise UserError(f"downscale must be an integer >= 1, got {downscale}")
    meta = read_json(path)
    if not isinstance(meta, dict):
        raise UserError(f"{path} must hold a JSON object (with 'frames'), got a {type(meta).__name__}")
    frames = meta.get("frames")
    if not isinstance(frames, list) or not frames:
        raise UserError(f"{path} lists no frames")
    frames = sorted(check_frame_entries(frames, path), key=lambda fr: fr["file_path"])
    if int(max_views) > 0:
        frames = frames[: int(max_views)]
    names = [fr["file_path"] for fr in frames]

    intr, dists, sizes, groups = [], [], [], []
    for i, fr in enumerate(frames):
        get = lambda k, d=None: fr.get(k, meta.get(k, d))  # noqa: E731
        model = str(get("camera_model", "OPENCV"))
        if model not in MODELS:
            raise UserError(f"{path}: frame {names[i]}: camera_model {model} is not supported "
                            f"(supported: {', '.join(MODELS)})")
        missing = [k for k in INTRINSICS if get(k) is None]
        if missing:
            raise UserError(f"{path}: frame {names[i]} has no '{missing[0]}' (neither per frame nor shared)")
        vals = [json_number(get(k), f"{path}: frame {names[i]}: {k}") for k in INTRINSICS]
        d = [json_number(get(k, 0.0), f"{path}: frame {names[i]}: {k}") for k in DISTORTION]
        if not np.isfinite(vals + d).all() or vals[0] <= 0 or vals[1] <= 0:
            raise UserError(f"{path}: frame {names[i]}: intrinsics must be finite with positive focal lengths")
        if int(vals[4]) < 1 or int(vals[5]) < 1:
            raise UserError(f"{path}: frame {names[i]}: image size w x h must be positive, got {vals[4]:g} x {vals[5]:g}")
        intr.append(vals[:4])
        dists.append(d)
        sizes.append((int(vals[4]), int(vals[5])))
        groups.append(tuple(vals + d))             # frames sharing intrinsics must share a size
    labels = {g: k for k, g in enumerate(dict.fromkeys(groups))}
    groups = [f"intrinsics #{labels[g]}" for g in groups]
    try:
        c2w = torch.tensor([fr["transform_matrix"] for fr in frames], dtype=torch.float64)
    except (ValueError, TypeError) as err:
        raise UserError(f"{path}: a transform_matrix is not a 4x4 list of numbers: {err}") from err
    if c2w.shape[1:] not in ((4, 4), (3, 4)):
        raise UserError(f"{path}: transform_matrix must be 4x4, got {tuple(c2w.shape[1:])}")
    check_rigid_poses(c2w[:, :3, :3], c2w[:, :3, 3], path.name, [f"frame {n}" for n in names])

    composite = background_rgb("white") if isinstance(background, str) and background == "auto" \
        else background_rgb(background)
    files = image_files(folder, names, str(path))
    imgs, K = load_images(files, sizes, np.array(intr), np.array(dists), int(downscale), composite, groups, str(path))
    H, W = imgs.shape[1:3]
    Kt = torch.from_numpy(K)
    cams = from_opengl_c2w(c2w[:, :3], Kt[:, 0], Kt[:, 1], Kt[:, 2], Kt[:, 3], W, H)

    pts = cols = None
    if meta.get("ply_file_path"):
        pfile = folder / meta["ply_file_path"]
        if not pfile.is_file():
            raise UserError(f"{path}: ply_file_path {pfile} not found")
        p, c = _read_ply_points(pfile)
        check_finite(torch.from_numpy(p), str(pfile), "point")
        pts, cols = torch.from_numpy(p), None if c is None else torch.from_numpy(c)

    applied = torch.eye(4, dtype=torch.float64)
    if "applied_transform" in meta:
        a = torch.tensor(meta["applied_transform"], dtype=torch.float64)
        if a.shape not in ((3, 4), (4, 4)) or not bool(torch.isfinite(a).all()):
            raise UserError(f"{path}: applied_transform must be a finite 3x4 matrix")
        applied[:3] = a[:3]
    split_idx = {}
    if any(f"{s}_filenames" in meta for s in ("train", "val", "test")):
        where = {_norm(n): i for i, n in enumerate(names)}
        for s in ("train", "val", "test"):
            listed = [_norm(n) for n in meta.get(f"{s}_filenames", [])]
            unknown = [n for n in listed if n not in where]
            if unknown:
                raise UserError(f"{path}: {s}_filenames lists '{unknown[0]}', which no frame has")
            split_idx[s] = torch.tensor(sorted(where[n] for n in listed), dtype=torch.long)
        train, val, test = split_idx["train"], split_idx["val"], split_idx["test"]
        if len(train) == 0:
            raise UserError(f"{path}: train_filenames is empty")
        train, val, test = disjoint_splits(train, val, test, int(val_every), str(path))
    else:
        train, val, test = split_by_name(names, int(test_every), int(val_every))
    M = torch.eye(4, dtype=torch.float64)
    R, t = cams.R, cams.t
    if normalize:
        t, pts, M = normalize_scene(R, t, pts, float(camera_radius), fit_on=train)
    source_from_world = torch.linalg.inv(applied) @ M      # this world -> nerfstudio world -> source
    cams = Cameras(R.float(), t.float(), cams.fx.float(), cams.fy.float(), cams.cx.float(), cams.cy.float(), W, H)

    bg, known = border_background(imgs[train], background)
    radius = float(camera_radius) if normalize else camera_spread(cams[train])
    box = scene_box(pts, radius, float(box_percentile), float(box_margin), cameras=cams[train])
    data = MultiViewData(imgs, cams, train, val, test, bg, box, name=f"nerfstudio:{folder.name}",
                         points=None if pts is None else pts.float(), point_colors=cols,
                         source_from_world=source_from_world, background_known=known)
    return data if device is None else data.to(device)
