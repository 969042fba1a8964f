"""A small Wavefront OBJ / MTL reader that keeps the file's vertex order and UV seams.

trimesh keeps the vertex order of an OBJ with ``maintain_order=True`` but then stores one
UV per vertex, so a vertex on a UV seam gets only one of its texture coordinates. The
course meshes need the pair (``faces`` into positions, ``faces_uvs`` into texture
coordinates) exactly as written, so we read them ourselves. Only the line routing is a
Python loop; the numbers are converted and the polygons triangulated with numpy.

Supported: ``v x y z [r g b]``, ``vt u [v [w]]``, ``f`` with ``v``, ``v/vt``, ``v//vn``
or ``v/vt/vn`` corners (1-based or negative relative indices), polygons of any size
(fan-triangulated, first corner shared), ``usemtl`` / ``mtllib``. Ignored: normals
(recomputed from geometry), groups, smoothing groups, lines, curves.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Optional

import numpy as np

from l3d_app.errors import UserError


@dataclass
class ObjData:
    """Raw arrays read from an OBJ file (numpy, 0-based indices).

    Attributes:
        verts: (V, 3) float64 positions.
        vert_colors: (V, 3) float64 RGB in [0, 1] when every ``v`` line has one, else None.
        uvs: (T, 2) float64 texture coordinates (v up), possibly T = 0.
        faces: (F, 3) int64 triangles into ``verts`` (range-checked).
        faces_uvs: (F, 3) int64 into ``uvs``, -1 at corners without a ``vt``; None when no
            corner has one.
        face_material: (F,) int64 index into ``material_names``, -1 before any ``usemtl``.
        material_names: names in order of first ``usemtl``.
        mtllibs: the ``mtllib`` arguments, as written.
    """

    verts: np.ndarray
    vert_colors: Optional[np.ndarray]
    uvs: np.ndarray
    faces: np.ndarray
    faces_uvs: Optional[np.ndarray]
    face_material: np.ndarray
    material_names: List[str] = field(default_factory=list)
    mtllibs: List[str] = field(default_factory=list)


def _partition(strings: np.ndarray, sep: str):
    """Vectorised ``str.partition``: (head, tail) string arrays."""
    if hasattr(np, "strings") and hasattr(np.strings, "partition"):  # numpy >= 2.2
        head, _, tail = np.strings.partition(strings, sep)
        return head, tail
    parts = np.char.partition(strings, sep)
    return parts[..., 0], parts[..., 2]


def _floats(rows: List[List[str]], width: int, what: str, path: Path) -> np.ndarray:
    """(N, width) float64 from token rows that all have at least ``width`` entries."""
    if not rows:
        return np.zeros((0, width))
    try:
        if all(len(r) == width for r in rows):
            return np.array(rows, dtype=np.float64)
        return np.array([r[:width] for r in rows], dtype=np.float64)
    except ValueError:
        raise UserError(f"malformed OBJ {path}: a '{what}' line holds something that is not a number") from None


def _indices(strings: np.ndarray, count_before: np.ndarray, n: int, what: str, path: Path) -> np.ndarray:
    """OBJ 1-based / negative-relative index strings -> 0-based int64 (-1 where empty).

    ``count_before`` (same shape) is how many elements of that kind preceded the line.
    Raises UserError for non-integers and for indices outside [0, n).
    """
    present = strings != ""
    try:
        raw = np.where(present, strings, "0").astype(np.int64)
    except ValueError:
        raise UserError(f"malformed OBJ {path}: a face holds a {what} index that is not an integer") from None
    idx = np.where(raw > 0, raw - 1, count_before + raw)
    bad = present & ((raw == 0) | (idx < 0) | (idx >= n))
    if bad.any():
        raise UserError(f"malformed OBJ {path}: face {what} index {int(raw[bad][0])} is out of range "
                        f"(the file defines {n})")
    return np.where(present, idx, -1)


def _fan(counts: np.ndarray) -> tuple:
    """Fan-triangulate polygons stored back to back.

    Args:
        counts: (P,) corners per polygon (each >= 3).
    Returns:
        (F, 3) positions of the triangle corners in the flat corner array, and (F,) the
        polygon of each triangle; triangles come in polygon order.
    """
    starts = np.cumsum(counts) - counts
    ntri = counts - 2
    poly = np.repeat(np.arange(len(counts)), ntri)
    k = np.arange(int(ntri.sum())) - np.repeat(np.cumsum(ntri) - ntri, ntri) + 1
    s = starts[poly]
    return np.stack([s, s + k, s + k + 1], axis=-1), poly


def parse_obj(path: Path) -> ObjData:
    """Read an OBJ file into :class:`ObjData`; UserError (with the path) on malformed content."""
    path = Path(path)
    text = path.read_bytes().decode("utf-8", errors="replace").replace("\\\n", " ")
    v_rows, vt_rows, f_rows = [], [], []
    f_material, f_nv, f_nvt = [], [], []
    materials: Dict[str, int] = {}
    mtllibs: List[str] = []
    current = -1
    for line in text.splitlines():
        tok = line.split()
        if not tok:
            continue
        key = tok[0]
        if key == "v":
            v_rows.append(tok[1:])
        elif key == "vt":
            vt_rows.append((tok[1:] + ["0", "0"])[:2])
        elif key == "f":
            f_rows.append(tok[1:])
            f_material.append(current)
            f_nv.append(len(v_rows))
            f_nvt.append(len(vt_rows))
        elif key == "usemtl":
            name = line.split(None, 1)[1].strip() if len(tok) > 1 else ""
            current = materials.setdefault(name, len(materials))
        elif key == "mtllib" and len(tok) > 1:
            mtllibs.append(line.split(None, 1)[1].strip())

    if not f_rows:
        raise UserError(f"mesh file {path} has no faces (is it a point cloud or not an OBJ mesh?)")
    widths = np.fromiter((len(r) for r in v_rows), dtype=np.int64, count=len(v_rows))
    if len(v_rows) and widths.min() < 3:
        raise UserError(f"malformed OBJ {path}: a 'v' line has fewer than 3 coordinates")
    verts = _floats(v_rows, 3, "v", path)
    colors = None
    if len(v_rows) and widths.min() >= 6 and widths.max() <= 7:
        colors = np.array([r[3:6] for r in v_rows], dtype=np.float64)
        if colors.max(initial=0.0) > 1.0:  # some exporters write 0..255
            colors = colors / 255.0
        colors = np.clip(colors, 0.0, 1.0)
    uvs = _floats(vt_rows, 2, "vt", path)

    counts = np.fromiter((len(r) for r in f_rows), dtype=np.int64, count=len(f_rows))
    if counts.min() < 3:
        raise UserError(f"malformed OBJ {path}: a face has fewer than 3 corners")
    corners = np.array([c for row in f_rows for c in row])
    v_str, rest = _partition(corners, "/")
    vt_str, _ = _partition(rest, "/")
    v_idx = _indices(v_str, np.repeat(f_nv, counts), len(verts), "vertex", path)
    if (v_idx < 0).any():
        raise UserError(f"malformed OBJ {path}: a face corner has no vertex index")
    vt_idx = _indices(vt_str, np.repeat(f_nvt, counts), len(uvs), "texture coordinate", path)
    tri, poly = _fan(counts)
    return ObjData(
        verts=verts, vert_colors=colors, uvs=uvs, faces=v_idx[tri],
        faces_uvs=vt_idx[tri] if (vt_idx >= 0).any() else None,
        face_material=np.asarray(f_material, dtype=np.int64)[poly],
        material_names=list(materials), mtllibs=mtllibs)


def resolve_relative(name: str, folder: Path) -> Optional[Path]:
    """A file named in an OBJ/MTL, looked up beside it (also by basename, also
    with Windows separators); None if it does not exist."""
    name = name.strip().strip('"')
    candidates = [folder / name, folder / name.replace("\\", "/"),
                  folder / Path(name.replace("\\", "/")).name]
    return next((c for c in candidates if c.is_file()), None)


def parse_mtl(path: Path) -> Dict[str, dict]:
    """Materials of an MTL file: ``{name: {"kd": (3,) floats or absent, "map_kd": Path or absent}}``.

    ``map_kd`` is the diffuse texture resolved beside the MTL file (options such as
    ``-s 1 1 1`` before the file name are skipped); a missing image is left out.
    """
    path = Path(path)
    materials: Dict[str, dict] = {}
    current = None
    for line in path.read_bytes().decode("utf-8", errors="replace").splitlines():
        tok = line.split()
        if not tok:
            continue
        key = tok[0].lower()
        if key == "newmtl":
            current = materials.setdefault(line.split(None, 1)[1].strip() if len(tok) > 1 else "", {})
        elif current is None:
            continue
        elif key == "kd" and len(tok) >= 4:
            try:
                current["kd"] = tuple(float(x) for x in tok[1:4])
            except ValueError:
                pass
        elif key == "map_kd" and len(tok) >= 2:
            rest = line.split(None, 1)[1]
            image = resolve_relative(rest, path.parent) or resolve_relative(tok[-1], path.parent)
            if image is not None:
                current["map_kd"] = image
            else:
                current["map_kd_missing"] = tok[-1]
    return materials
