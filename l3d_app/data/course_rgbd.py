"""``data=course_rgbd data.path=rgbd_data.pkl``: the rendering assignment's two RGB-D views.

Layout (as the course's starter code reads it, ``pickle.load``): a dict with ``rgb1``,
``depth1``, ``mask1``, ``cameras1`` and ``rgb2``, ``depth2``, ``mask2``, ``cameras2``:
``rgbK`` (S, S, 3) in [0, 1] (or 0..255), ``depthK`` (S, S) camera Z, ``maskK`` (S, S)
(> 0.5 = object), ``camerasK`` a pickled PyTorch3D ``PerspectiveCameras`` (NDC focal
length / principal point) or ``FoVPerspectiveCameras``. PyTorch3D need NOT be installed:
the pickle is read with a restricted unpickler that turns ``pytorch3d.*`` classes into
plain attribute holders (and refuses any other non-data class).

The course unprojects pixel (row i, column j) at NDC ``(x, y) = (1 - 2j/(S-1), 1 - 2i/(S-1))``
(``torch.linspace(1, -1, S)``: image corners at the pixel CENTRES), not at the pixel centres
``1 - (2j+1)/S`` of our convention. ``course_grid=true`` (default) reproduces the course's
points exactly by handing :func:`~l3d_app.geometry.rgbd.unproject_depth` a camera whose NDC
focal and principal point are scaled by ``(S-1)/S`` (the two grids differ by that factor);
``course_grid=false`` gives the geometrically exact pixel-centre cloud.

``view=1 | 2 | union`` picks one view's cloud or their union; render each as a turntable with
``python main.py -m task=render360 data=course_rgbd data.path=FILE data.view=1,2,union``.
"""

from __future__ import annotations

import io
import pickle
from pathlib import Path

import numpy as np
import torch

from l3d_app.errors import UserError
from l3d_app.geometry.cameras import Cameras, from_pytorch3d
from l3d_app.geometry.pointcloud import PointCloud
from l3d_app.geometry.pose_checks import check_rigid_poses
from l3d_app.geometry.rgbd import concat_clouds, unproject_depth
from l3d_app.registry import DATASETS
from l3d_app.runtime.paths import resolve_path

_SAFE_PREFIXES = ("numpy", "torch", "collections", "copyreg", "_codecs")


class _Pytorch3dObject:
    """Stands in for any pickled ``pytorch3d.*`` object: keeps its attributes."""

    def __setstate__(self, state):
        self.__dict__.update(state if isinstance(state, dict) else {})


class _CourseUnpickler(pickle.Unpickler):
    def find_class(self, module, name):
        if module.startswith("pytorch3d"):
            return type(name, (_Pytorch3dObject,), {})
        if module.split(".")[0] in _SAFE_PREFIXES or (module == "builtins" and name in (
                "dict", "list", "tuple", "set", "frozenset", "int", "float", "bool", "str", "bytes", "complex",
                "bytearray", "slice", "range", "getattr")):
            return super().find_class(module, name)
        raise pickle.UnpicklingError(f"refusing to load {module}.{name}")


def load_pickle(path: Path) -> dict:
    """The course pickle, read without PyTorch3D and without running arbitrary classes."""
    try:
        with open(path, "rb") as f:
            data = _CourseUnpickler(io.BytesIO(f.read())).load()
    except FileNotFoundError as err:
        raise UserError(f"RGB-D data file not found: {path}") from err
    except Exception as err:  # noqa: BLE001 - any unpickling failure is the user's file
        raise UserError(f"cannot read {path} as the course's rgbd_data.pkl: {err}") from err
    if not isinstance(data, dict):
        raise UserError(f"{path}: expected a dict of rgb1/depth1/mask1/cameras1..., got {type(data).__name__}")
    return data


def _t(value) -> torch.Tensor:
    return value.detach().cpu().double() if torch.is_tensor(value) else torch.as_tensor(np.asarray(value), dtype=torch.float64)


def course_camera(cam, size: int, source: str) -> Cameras:
    """Our :class:`Cameras` for a pickled PyTorch3D camera of a square image of ``size`` px."""
    d = getattr(cam, "__dict__", {})
    if "R" not in d or "T" not in d:
        raise UserError(f"{source}: camera has no R / T")
    R, T = _t(d["R"]).reshape(-1, 3, 3)[:1], _t(d["T"]).reshape(-1, 3)[:1]
    if "fov" in d:                                            # FoVPerspectiveCameras
        fov = float(_t(d["fov"]).reshape(-1)[0])
        fov = np.deg2rad(fov) if bool(d.get("degrees", True)) else fov
        focal, pp = 1.0 / np.tan(fov / 2.0), (0.0, 0.0)
    else:
        focal = _t(d.get("focal_length", 1.0)).reshape(-1)[:2]
        focal = focal.expand(2) if focal.numel() == 1 else focal
        pp = _t(d.get("principal_point", torch.zeros(2))).reshape(-1)[:2]
        if d.get("_in_ndc", True) is False:
            raise UserError(f"{source}: screen-space PyTorch3D cameras are not supported (need in_ndc=True)")
    check_rigid_poses(R, T, source, ["camera"])
    return from_pytorch3d(R, T, focal, pp, image_size=(size, size), in_ndc=True)


def view_cloud(data: dict, k: int, source: str, course_grid: bool = True) -> PointCloud:
    """The cloud of view ``k`` (1 or 2) of the course dict."""
    keys = [f"{n}{k}" for n in ("rgb", "depth", "mask", "cameras")]
    missing = [key for key in keys if key not in data]
    if missing:
        raise UserError(f"{source}: no '{missing[0]}' entry (keys: {', '.join(sorted(map(str, data)))})")
    rgb, depth, mask = (_t(data[key]).float() for key in keys[:3])
    if rgb.dim() != 3 or depth.shape != rgb.shape[:2] or mask.shape != depth.shape or depth.shape[0] != depth.shape[1]:
        raise UserError(f"{source}: view {k} needs square rgb (S, S, 3), depth (S, S), mask (S, S); got "
                        f"{tuple(rgb.shape)}, {tuple(depth.shape)}, {tuple(mask.shape)}")
    if depth.shape[0] == 0:
        raise UserError(f"{source}: view {k} has 0 x 0 pixels")
    if float(rgb.max()) > 1.5:
        rgb = rgb / 255.0
    S = depth.shape[0]
    cam = course_camera(data[keys[3]], S, f"{source}: cameras{k}")
    if course_grid:
        s = (S - 1.0) / S                        # course NDC = our pixel-centre NDC * S / (S - 1)
        c = S / 2.0
        cam = Cameras(cam.R, cam.t, cam.fx * s, cam.fy * s, c + (cam.cx - c) * s, c + (cam.cy - c) * s, S, S)
    cam = cam.to(dtype=torch.float32)
    return unproject_depth(depth[None], cam, rgb[None, ..., :3].clamp(0, 1), mask[None] > 0.5)


@DATASETS.register("course_rgbd")
def course_rgbd(path: str = None, view: str = "union", course_grid: bool = True, device=None) -> PointCloud:
    """One view's cloud (``view=1`` or ``2``) or their union (``view=union``)."""
    if path is None or str(path) in ("", "???"):
        raise UserError("data=course_rgbd needs the file: add data.path=rgbd_data.pkl")
    file = resolve_path(str(path))
    data = load_pickle(file)
    views = {"1": [1], "2": [2], "union": [1, 2]}.get(str(view))
    if views is None:
        raise UserError(f"data.view must be 1, 2 or union, got {view!r}")
    cloud = concat_clouds([view_cloud(data, k, str(file), bool(course_grid)) for k in views])
    if cloud.points.shape[0] == 0:
        raise UserError(f"{file}: no pixel of view(s) {views} has a positive depth inside its mask")
    return cloud if device is None else cloud.to(device)
