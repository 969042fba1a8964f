"""COLMAP sparse models (``cameras``, ``images``, ``points3D`` as ``.bin`` or ``.txt``), read
with NumPy only (COLMAP need not be installed).

Layouts (COLMAP's ``read_write_model.py``; all little-endian):

* ``cameras.bin``: uint64 count; per camera int32 id, int32 model id, uint64 width,
  uint64 height, float64 params[n(model)]. ``cameras.txt``: ``ID MODEL W H PARAMS...``.
* ``images.bin``: uint64 count; per image int32 id, float64 qw qx qy qz tx ty tz, int32
  camera id, the name (NUL-terminated), uint64 n2d, n2d x (float64 x, float64 y, int64
  point3D id). ``images.txt``: two lines per image, ``ID QW QX QY QZ TX TY TZ CAMERA_ID
  NAME`` and the (possibly empty) ``X Y POINT3D_ID ...`` line.
* ``points3D.bin``: uint64 count; per point uint64 id, float64 xyz, uint8 rgb, float64
  error, uint64 track length, length x (int32 image id, int32 point2D index).
  ``points3D.txt``: ``ID X Y Z R G B ERROR TRACK...``.

Poses are world->camera (``X_cam = R(q) X + t``) with camera +X right, +Y down, +Z forward
and pixel centres at +0.5: the library's internal convention, no conversion needed.

Cost: images are walked one by one (a few hundred) but their 2D observations are skipped
by offset arithmetic (or kept as one array each with ``keep_points2d``); points3D records are
located with one cheap offset walk and their fields gathered with one NumPy fancy index.
A file that ends early raises :class:`UserError` naming it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Optional, Tuple

import numpy as np

from l3d_app.errors import UserError

# model id -> (name, number of params)
CAMERA_MODELS: Dict[int, Tuple[str, int]] = {
    0: ("SIMPLE_PINHOLE", 3), 1: ("PINHOLE", 4), 2: ("SIMPLE_RADIAL", 4), 3: ("RADIAL", 5),
    4: ("OPENCV", 8), 5: ("OPENCV_FISHEYE", 8), 6: ("FULL_OPENCV", 12), 7: ("FOV", 5),
    8: ("SIMPLE_RADIAL_FISHEYE", 4), 9: ("RADIAL_FISHEYE", 5), 10: ("THIN_PRISM_FISHEYE", 12),
}
MODEL_IDS = {name: i for i, (name, _) in CAMERA_MODELS.items()}
SUPPORTED = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV")


@dataclass
class ColmapCamera:
    """One COLMAP camera: ``model`` name, image ``width`` x ``height`` px, raw ``params``."""
    id: int
    model: str
    width: int
    height: int
    params: np.ndarray

    def intrinsics(self) -> Tuple[float, float, float, float, np.ndarray]:
        """(fx, fy, cx, cy, dist) with dist = (k1, k2, k3, k4, p1, p2) for the supported models.

        Raises :class:`UserError` for the other models (fisheye, FOV, rational OpenCV)."""
        p, m = [float(v) for v in self.params], self.model
        dist = np.zeros(6)
        if m == "SIMPLE_PINHOLE":
            fx = fy = p[0]; cx, cy = p[1], p[2]  # noqa: E702
        elif m == "PINHOLE":
            fx, fy, cx, cy = p[:4]
        elif m == "SIMPLE_RADIAL":
            fx = fy = p[0]; cx, cy = p[1], p[2]; dist[0] = p[3]  # noqa: E702
        elif m == "RADIAL":
            fx = fy = p[0]; cx, cy = p[1], p[2]; dist[:2] = p[3:5]  # noqa: E702
        elif m == "OPENCV":
            fx, fy, cx, cy = p[:4]; dist[:2] = p[4:6]; dist[4:] = p[6:8]  # noqa: E702
        else:
            raise UserError(f"camera {self.id}: camera model {m} is not supported "
                            f"(supported: {', '.join(SUPPORTED)}; undistort with COLMAP's image_undistorter)")
        if self.width < 1 or self.height < 1:
            raise UserError(f"camera {self.id}: image size must be positive, got {self.width} x {self.height}")
        if not (np.isfinite(p).all() and fx > 0 and fy > 0):
            raise UserError(f"camera {self.id}: parameters must be finite with positive focal lengths, got {p}")
        return fx, fy, cx, cy, dist


@dataclass
class ColmapModel:
    """A sparse model. Images sorted as in the file; arrays are float64 unless noted.

    Attributes:
        cameras: camera id -> :class:`ColmapCamera`.
        image_ids: (N,) int; qvec: (N, 4) (w, x, y, z); tvec: (N, 3); camera_ids: (N,) int;
        names: N image names (relative to the images folder).
        points: (P, 3) xyz; colors: (P, 3) uint8; errors: (P,); point_ids: (P,) int.
        points2d: per image (n, 3) (x, y, point3D id) when read with ``keep_points2d``.
    """
    cameras: Dict[int, ColmapCamera]
    image_ids: np.ndarray
    qvec: np.ndarray
    tvec: np.ndarray
    camera_ids: np.ndarray
    names: List[str]
    points: np.ndarray
    colors: np.ndarray
    errors: np.ndarray
    point_ids: np.ndarray
    points2d: Optional[List[np.ndarray]] = field(default=None)


def qvec_to_rotmat(q: np.ndarray) -> np.ndarray:
    """(N, 4) quaternions (w, x, y, z), any norm -> (N, 3, 3) rotation matrices."""
    q = np.asarray(q, dtype=np.float64).reshape(-1, 4)
    n = np.linalg.norm(q, axis=1, keepdims=True)
    w, x, y, z = (q / np.where(n > 0, n, 1.0)).T
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1)], 1)


# ------------------------------------------------------------------ binary
class _Reader:
    def __init__(self, path: Path):
        self.path, self.buf, self.pos = path, path.read_bytes(), 0

    def need(self, n: int, what: str) -> None:
        if self.pos + n > len(self.buf):
            raise UserError(f"{self.path}: file is truncated (ends inside {what}, byte {len(self.buf)})")

    def read(self, dtype: str, count: int, what: str) -> np.ndarray:
        dt = np.dtype(dtype)
        self.need(dt.itemsize * count, what)
        out = np.frombuffer(self.buf, dtype=dt, count=count, offset=self.pos)
        self.pos += dt.itemsize * count
        return out


def read_cameras_bin(path: Path) -> Dict[int, ColmapCamera]:
    r = _Reader(path)
    cams = {}
    for i in range(int(r.read("<u8", 1, "the camera count")[0])):
        cid, mid = (int(v) for v in r.read("<i4", 2, f"camera record {i}"))
        w, h = (int(v) for v in r.read("<u8", 2, f"camera record {i}"))
        if mid not in CAMERA_MODELS:
            raise UserError(f"{path}: camera {cid}: unknown camera model id {mid}")
        name, n = CAMERA_MODELS[mid]
        cams[cid] = ColmapCamera(cid, name, w, h, r.read("<f8", n, f"camera {cid}'s parameters").copy())
    return cams


def read_images_bin(path: Path, keep_points2d: bool = False):
    r = _Reader(path)
    head = np.dtype([("id", "<i4"), ("q", "<f8", 4), ("t", "<f8", 3), ("cam", "<i4")])
    rows, names, pts2d = [], [], []
    for i in range(int(r.read("<u8", 1, "the image count")[0])):
        rows.append(r.read(head, 1, f"image record {i}")[0])
        end = r.buf.find(b"\x00", r.pos)
        if end < 0:
            raise UserError(f"{path}: file is truncated (ends inside image {i}'s name)")
        try:
            names.append(r.buf[r.pos:end].decode("utf-8"))
        except UnicodeDecodeError as err:
            raise UserError(f"{path}: image {i}'s name is not UTF-8 text (a corrupt or foreign images.bin)") from err
        r.pos = end + 1
        n2d = int(r.read("<u8", 1, f"image {names[-1]}'s observation count")[0])
        obs = r.read([("x", "<f8"), ("y", "<f8"), ("id", "<i8")], n2d, f"image {names[-1]}'s observations")
        if keep_points2d:
            pts2d.append(np.stack([obs["x"], obs["y"], obs["id"].astype(np.float64)], -1))
    arr = np.array(rows, dtype=head) if rows else np.zeros(0, dtype=head)
    return arr["id"].astype(np.int64), arr["q"].reshape(-1, 4), arr["t"].reshape(-1, 3), \
        arr["cam"].astype(np.int64), names, (pts2d if keep_points2d else None)


def read_points3d_bin(path: Path):
    r = _Reader(path)
    n = int(r.read("<u8", 1, "the point count")[0])
    rec = np.dtype([("id", "<u8"), ("xyz", "<f8", 3), ("rgb", "u1", 3), ("err", "<f8"), ("len", "<u8")])
    if n * rec.itemsize > len(r.buf) - r.pos:          # before allocating n offsets
        raise UserError(f"{path}: file is truncated or not a points3D.bin ({n} points do not fit in "
                        f"{len(r.buf)} bytes)")
    offsets = np.empty(n, dtype=np.int64)
    pos, buf = r.pos, r.buf
    unpack = np.frombuffer
    for i in range(n):                       # offset walk only: one uint64 read per point
        offsets[i] = pos
        if pos + rec.itemsize > len(buf):
            raise UserError(f"{path}: file is truncated (ends inside point record {i} of {n})")
        pos += rec.itemsize + 8 * int(unpack(buf, "<u8", 1, pos + rec.itemsize - 8)[0])
    if pos > len(buf):
        raise UserError(f"{path}: file is truncated (ends inside point record {n - 1}'s track)")
    raw = np.frombuffer(buf, dtype=np.uint8)
    recs = raw[offsets[:, None] + np.arange(rec.itemsize)].copy().view(rec).reshape(-1) if n else np.zeros(0, rec)
    return recs["id"].astype(np.int64), recs["xyz"].reshape(-1, 3), recs["rgb"].reshape(-1, 3), recs["err"]


# -------------------------------------------------------------------- text
def _lines(path: Path) -> List[str]:
    return [ln for ln in path.read_text().splitlines() if not ln.startswith("#")]


def _floats(path: Path, line_no: int, tokens: List[str], cast=float) -> list:
    """``tokens`` of a text line as numbers (``cast``); a token that is not one is a UserError."""
    try:
        return [cast(t) for t in tokens]
    except ValueError as err:
        raise UserError(f"{path}: line {line_no}: {err}") from err


def _int(path: Path, line_no: int, token: str) -> int:
    return _floats(path, line_no, [token], int)[0]


def read_cameras_txt(path: Path) -> Dict[int, ColmapCamera]:
    cams = {}
    for k, ln in enumerate(_lines(path)):
        tok = ln.split()
        if not tok:
            continue
        if len(tok) < 4 or tok[1] not in MODEL_IDS:
            raise UserError(f"{path}: camera line '{ln.strip()[:60]}': unknown camera model or short line")
        n = CAMERA_MODELS[MODEL_IDS[tok[1]]][1]
        if len(tok) != 4 + n:
            raise UserError(f"{path}: camera {tok[0]}: {tok[1]} needs {n} parameters, got {len(tok) - 4}")
        vals = _floats(path, k, tok[2:])
        cid = _int(path, k, tok[0])
        cams[cid] = ColmapCamera(cid, tok[1], int(vals[0]), int(vals[1]), np.array(vals[2:]))
    return cams


def read_images_txt(path: Path, keep_points2d: bool = False):
    lines = _lines(path)
    ids, qt, cams, names, pts2d = [], [], [], [], []
    i = 0
    while i < len(lines):
        tok = lines[i].split()
        if not tok:
            i += 1
            continue
        if len(tok) < 10:
            raise UserError(f"{path}: image line '{lines[i].strip()[:60]}' needs ID QW QX QY QZ TX TY TZ CAMERA_ID NAME")
        ids.append(_int(path, i, tok[0]))
        qt.append(_floats(path, i, tok[1:8]))
        cams.append(_int(path, i, tok[8]))
        names.append(" ".join(tok[9:]))
        if keep_points2d:
            obs = lines[i + 1].split() if i + 1 < len(lines) else []
            pts2d.append(np.array(_floats(path, i + 1, obs), dtype=np.float64).reshape(-1, 3))
        i += 2
    qt = np.array(qt, dtype=np.float64).reshape(-1, 7)
    return np.array(ids, dtype=np.int64), qt[:, :4], qt[:, 4:], np.array(cams, dtype=np.int64), names, \
        (pts2d if keep_points2d else None)


def read_points3d_txt(path: Path):
    rows = [ln.split(maxsplit=8)[:8] for ln in _lines(path) if ln.strip()]
    if any(len(r) < 8 for r in rows):
        raise UserError(f"{path}: a point line has fewer than 8 fields (ID X Y Z R G B ERROR)")
    try:
        a = np.array(rows, dtype=np.float64).reshape(-1, 8)
    except ValueError as err:
        raise UserError(f"{path}: {err}") from err
    return a[:, 0].astype(np.int64), a[:, 1:4], a[:, 4:7].astype(np.uint8), a[:, 7]


# ------------------------------------------------------------------ model
def find_model_files(sparse: Path) -> Tuple[Path, Path, Path]:
    """The three files of ``sparse`` (binary preferred), or a UserError naming what is missing."""
    for ext in (".bin", ".txt"):
        files = tuple(sparse / f"{n}{ext}" for n in ("cameras", "images", "points3D"))
        if all(f.is_file() for f in files):
            return files
    raise UserError(f"{sparse} holds no COLMAP model (cameras, images, points3D as .bin or .txt)")


def read_model(sparse: Path, keep_points2d: bool = False) -> ColmapModel:
    """Read a sparse model folder (``.bin`` when all three exist, else ``.txt``)."""
    cams_f, imgs_f, pts_f = find_model_files(Path(sparse))
    binary = cams_f.suffix == ".bin"
    cams = (read_cameras_bin if binary else read_cameras_txt)(cams_f)
    ids, q, t, cam_ids, names, p2d = (read_images_bin if binary else read_images_txt)(imgs_f, keep_points2d)
    pid, xyz, rgb, err = (read_points3d_bin if binary else read_points3d_txt)(pts_f)
    missing = sorted(set(cam_ids.tolist()) - set(cams))
    if missing:
        raise UserError(f"{imgs_f}: image uses camera {missing[0]}, which {cams_f.name} does not define")
    bad = ~np.isfinite(xyz).all(1)
    if bad.any():
        raise UserError(f"{pts_f}: point {int(pid[bad.argmax()])} has a non-finite coordinate (NaN or inf)")
    return ColmapModel(cams, ids, q, t, cam_ids, names, xyz, rgb, err, pid, p2d)
