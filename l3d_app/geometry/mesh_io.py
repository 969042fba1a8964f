"""Read and write triangle meshes (OBJ, PLY, GLB/GLTF, OFF, STL) as :class:`Mesh`.

``load_mesh`` never touches the network: files are read from disk through trimesh, except
OBJ files with ``keep_vertex_order=True``, which :mod:`l3d_app.geometry.obj_io` reads
itself so that the vertex order and the UV seams (``faces_uvs``) are exactly the file's
(the course cow: 2930 vertices, 5856 faces, 3225 texture coordinates). Every problem with
the user's file is a one-line :class:`UserError` naming the file.

``save_mesh`` writes OBJ (with ``.mtl`` + PNG when textured, vertex colours as
``v x y z r g b``) or binary PLY (uchar vertex colours), each file first under a temporary
name and then renamed, so a reader never sees half a file.
"""

from __future__ import annotations

import io
import logging
import os
from pathlib import Path
from typing import Optional, Union

import numpy as np
import torch

from l3d_app.errors import UserError
from l3d_app.geometry.mesh import Mesh
from l3d_app.geometry.obj_io import parse_mtl, parse_obj, resolve_relative

log = logging.getLogger(__name__)

SUPPORTED_EXTENSIONS = (".obj", ".ply", ".glb", ".gltf", ".off", ".stl")
SAVE_EXTENSIONS = (".obj", ".ply")
PathLike = Union[str, os.PathLike]


# ----------------------------------------------------------------------------- loading
def load_mesh(path: PathLike, keep_vertex_order: bool = True, device=None) -> Mesh:
    """Load a triangle mesh file.

    Args:
        path: an ``.obj``, ``.ply``, ``.glb``, ``.gltf``, ``.off`` or ``.stl`` file.
        keep_vertex_order: keep the file's vertices as they are (no merging, no
            reordering, OBJ UV seams kept as separate ``faces_uvs``). False lets trimesh
            process the mesh (OBJ vertices split at UV seams, duplicates merged).
            STL files are triangle soups and are always merged.
        device: where the tensors go (default CPU).
    Returns:
        :class:`Mesh` with float32 ``verts`` (V, 3), long ``faces`` (F, 3), and, where
        the file has them, ``vert_colors`` (V, 3) in [0, 1] or a UV texture
        (``verts_uvs`` (T, 2) v up, ``faces_uvs`` (F, 3), ``texture`` (Ht, Wt, 3)).
        Several geometries in one file (a GLB scene) are concatenated, with their
        scene transforms applied.
    Raises:
        UserError: missing file, unsupported extension, or a file that is not a valid
            triangle mesh (no faces, indices out of range, NaN vertices, every face of zero
            area, garbage).
    """
    path = Path(os.path.expanduser(str(path)))
    if not path.exists():
        raise UserError(f"mesh file not found: {path}")
    if path.is_dir():
        raise UserError(f"mesh path is a directory, not a file: {path}")
    ext = path.suffix.lower()
    if ext not in SUPPORTED_EXTENSIONS:
        raise UserError(f"unsupported mesh format '{ext or path.name}' for {path}; "
                        f"supported: {', '.join(SUPPORTED_EXTENSIONS)}")
    mesh = None
    if ext == ".obj" and keep_vertex_order:
        mesh = _load_obj_ordered(path)
    if mesh is None:
        process = ext == ".stl" or not keep_vertex_order
        mesh = _load_with_trimesh(path, process=process)
    return mesh if device is None else mesh.to(device)


def _checked_mesh(path: Path, verts, faces, vert_colors=None, verts_uvs=None,
                  faces_uvs=None, texture=None) -> Mesh:
    """Validate numpy arrays with messages that name the file, then build the Mesh."""
    with np.errstate(over="ignore"):  # values beyond float32 become Inf and are reported below
        verts = np.asarray(verts, dtype=np.float32).reshape(-1, 3)
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    if len(faces) == 0:
        raise UserError(f"mesh file {path} has no faces (is it a point cloud?)")
    if faces.min() < 0 or faces.max() >= len(verts):
        raise UserError(f"mesh file {path} is malformed: face indices out of range "
                        f"[0, {len(verts)}) (found {int(faces.min())}..{int(faces.max())})")
    if not np.isfinite(verts).all():
        raise UserError(f"mesh file {path} is malformed: vertices contain NaN or Inf")
    if not _has_area(verts, faces):
        raise UserError(f"mesh file {path} has no surface: every face has zero area "
                        f"(its vertices coincide or lie on a line)")

    def t(x, dtype):
        return None if x is None else torch.as_tensor(np.ascontiguousarray(x), dtype=dtype)

    return Mesh(verts=t(verts, torch.float32), faces=t(faces, torch.int64),
                vert_colors=t(vert_colors, torch.float32), verts_uvs=t(verts_uvs, torch.float32),
                faces_uvs=t(faces_uvs, torch.int64), texture=t(texture, torch.float32))


def _has_area(verts: np.ndarray, faces: np.ndarray, chunk: int = 1 << 16) -> bool:
    """True when some face of (V, 3) ``verts`` and (F, 3) ``faces`` has a non-zero area (float64
    cross products, a chunk of faces at a time: a real mesh answers in its first chunk)."""
    v64 = verts.astype(np.float64)
    for start in range(0, len(faces), chunk):
        tri = v64[faces[start:start + chunk]]                                      # (f, 3, 3)
        if np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]).any():
            return True
    return False


def read_image(path: Path) -> np.ndarray:
    """(H, W, 3) float32 RGB in [0, 1], top row first (alpha dropped); UserError if unreadable."""
    from PIL import Image

    try:
        with Image.open(path) as img:
            return np.asarray(img.convert("RGB"), dtype=np.float32) / 255.0
    except Exception as exc:  # PIL raises many types for bad images
        raise UserError(f"could not read texture image {path}: {exc}") from None


def _load_obj_ordered(path: Path) -> Optional[Mesh]:
    """OBJ in file order with per-face UV indices; None when the materials need
    trimesh's texture packing (several texture images, or textured and untextured
    faces mixed): trimesh then loads it per material (without ``maintain_order``, which
    mis-assigns faces across materials in trimesh 5.2) and packs a texture atlas."""
    data = parse_obj(path)
    materials = {}
    for lib in data.mtllibs:
        found = resolve_relative(lib, path.parent)
        if found is None:
            log.warning("material library %s named by %s not found; ignoring it", lib, path)
            continue
        materials.update(parse_mtl(found))
    used = [int(m) for m in np.unique(data.face_material)]
    mats = {m: materials.get(data.material_names[m], {}) if m >= 0 else {} for m in used}
    for m in mats.values():
        if "map_kd_missing" in m:
            log.warning("texture %s for %s not found; loading without it", m["map_kd_missing"], path)
    images = {m: d["map_kd"] for m, d in mats.items() if "map_kd" in d}
    kw = dict(vert_colors=data.vert_colors)
    if images:
        single = len(set(images.values())) == 1 and len(images) == len(used)
        if not single or data.faces_uvs is None or (data.faces_uvs < 0).any():
            log.info("%s mixes materials; loading it through trimesh (texture atlas)", path)
            return None
        kw.update(verts_uvs=data.uvs, faces_uvs=data.faces_uvs,
                  texture=read_image(next(iter(images.values()))))
    elif data.vert_colors is None:
        kd = np.array([mats[m].get("kd", (1.0, 1.0, 1.0)) for m in used], dtype=np.float64)
        if len(np.unique(kd, axis=0)) > 1:  # several plain colours: average them onto vertices
            face_rgb = kd[np.searchsorted(used, data.face_material)]
            acc = np.zeros((len(data.verts), 4))
            np.add.at(acc, data.faces.reshape(-1), np.repeat(np.c_[face_rgb, np.ones(len(face_rgb))], 3, 0))
            kw["vert_colors"] = np.clip(acc[:, :3] / np.maximum(acc[:, 3:], 1), 0, 1)
    return _checked_mesh(path, data.verts, data.faces, **kw)


def _load_with_trimesh(path: Path, process: bool) -> Mesh:
    import trimesh

    try:
        loaded = trimesh.load(str(path), process=process)
    except Exception as exc:  # trimesh raises many types for bad files
        detail = str(exc).strip().splitlines()[0][:200] if str(exc).strip() else ""
        raise UserError(f"could not read mesh file {path}: not a valid {path.suffix[1:].upper()} mesh "
                        f"({type(exc).__name__}{': ' + detail if detail else ''})") from None
    geoms = loaded.dump() if isinstance(loaded, trimesh.Scene) else (
        list(loaded) if isinstance(loaded, (list, tuple)) else [loaded])
    meshes = [g for g in geoms if isinstance(g, trimesh.Trimesh) and len(g.faces)]
    if not meshes:
        kinds = sorted({type(g).__name__ for g in geoms}) or ["nothing"]
        hint = " (a point cloud is not a mesh)" if "PointCloud" in kinds else ""
        raise UserError(f"mesh file {path} has no faces: it holds {', '.join(kinds)}{hint}")
    tm = meshes[0] if len(meshes) == 1 else trimesh.util.concatenate(meshes)
    return _checked_mesh(path, tm.vertices, tm.faces, **_trimesh_appearance(tm))


def _trimesh_appearance(tm) -> dict:
    """Colours or UV texture of a trimesh.Trimesh as Mesh keyword arrays (may be empty)."""
    visual = tm.visual
    nv = len(tm.vertices)
    if visual.kind == "texture":
        material = getattr(visual, "material", None)
        image = getattr(material, "image", None) or getattr(material, "baseColorTexture", None)
        if visual.uv is not None and len(visual.uv) == nv and image is not None:
            rgb = np.asarray(image.convert("RGB"), dtype=np.float32) / 255.0
            return dict(verts_uvs=np.asarray(visual.uv, dtype=np.float64), faces_uvs=tm.faces, texture=rgb)
        try:  # no usable image: the material's colour, sampled per vertex
            visual = visual.to_color()
        except Exception:
            return {}
    if visual.kind in ("vertex", "face"):
        colors = np.asarray(visual.vertex_colors, dtype=np.float64)[:, :3] / 255.0
        if len(colors) == nv:
            return dict(vert_colors=colors)
    return {}


# ----------------------------------------------------------------------------- saving
def save_mesh(mesh: Mesh, path: PathLike) -> Path:
    """Write ``mesh`` to ``path`` (.obj or .ply) atomically; returns the path.

    OBJ: positions (with ``r g b`` after them when the mesh has vertex colours) and
    faces; a UV-textured mesh also writes ``<stem>.mtl`` and ``<stem>_texture.png``
    beside it. PLY: binary little-endian, vertex colours as uchar ``red green blue``;
    a UV texture is not stored in PLY (a warning says so).
    """
    path = Path(os.path.expanduser(str(path)))
    ext = path.suffix.lower()
    if ext not in SAVE_EXTENSIONS:
        raise UserError(f"cannot save a mesh as '{ext or path.name}'; supported: {', '.join(SAVE_EXTENSIONS)}")
    path.parent.mkdir(parents=True, exist_ok=True)
    verts = mesh.verts.detach().cpu().to(torch.float32).numpy()
    faces = mesh.faces.detach().cpu().numpy().astype(np.int64)
    colors = None if mesh.vert_colors is None else mesh.vert_colors.detach().cpu().float().clamp(0, 1).numpy()
    if ext == ".ply":
        if mesh.has_texture:
            log.warning("PLY has no UV texture; %s is written without it", path)
        _atomic_write(path, _ply_bytes(verts, faces, colors))
    else:
        _write_obj(mesh, path, verts, faces, colors)
    return path


def _atomic_write(path: Path, data: bytes) -> None:
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        with open(tmp, "wb") as fh:
            fh.write(data)
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


def _ply_bytes(verts: np.ndarray, faces: np.ndarray, colors: Optional[np.ndarray]) -> bytes:
    vdtype = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    if colors is not None:
        vdtype += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    vrec = np.empty(len(verts), dtype=vdtype)
    for i, axis in enumerate("xyz"):
        vrec[axis] = verts[:, i]
    if colors is not None:
        rgb = np.round(colors * 255.0).astype(np.uint8)
        for i, channel in enumerate(("red", "green", "blue")):
            vrec[channel] = rgb[:, i]
    frec = np.empty(len(faces), dtype=[("n", "u1"), ("idx", "<i4", (3,))])
    frec["n"] = 3
    frec["idx"] = faces
    props = "".join(f"property {'float' if t == '<f4' else 'uchar'} {n}\n" for n, t in vdtype)
    header = ("ply\nformat binary_little_endian 1.0\ncomment written by l3d_app\n"
              f"element vertex {len(verts)}\n{props}"
              f"element face {len(faces)}\nproperty list uchar int vertex_indices\nend_header\n")
    return header.encode("ascii") + vrec.tobytes() + frec.tobytes()


def _rows(fmt: str, array: np.ndarray) -> str:
    buf = io.StringIO()
    np.savetxt(buf, array, fmt=fmt)
    return buf.getvalue()


def _write_obj(mesh: Mesh, path: Path, verts, faces, colors) -> None:
    head = "# written by l3d_app\n"
    v = verts if colors is None else np.concatenate([verts, colors.astype(np.float32)], axis=1)
    body = _rows("v" + " %.9g" * v.shape[1], v)
    if mesh.has_texture:
        mtl, png = path.with_suffix(".mtl"), path.with_name(path.stem + "_texture.png")
        _atomic_write(png, _png_bytes(mesh.texture))
        _atomic_write(mtl, f"newmtl material_0\nKd 1 1 1\nmap_Kd {png.name}\n".encode())
        head += f"mtllib {mtl.name}\nusemtl material_0\n"
        body += _rows("vt %.9g %.9g", mesh.verts_uvs.detach().cpu().double().numpy())
        fuv = mesh.faces_uvs.detach().cpu().numpy().astype(np.int64) + 1
        body += _rows("f %d/%d %d/%d %d/%d", np.stack([faces + 1, fuv], -1).reshape(-1, 6))
    else:
        body += _rows("f %d %d %d", faces + 1)
    _atomic_write(path, (head + body).encode("ascii"))


def _png_bytes(texture: torch.Tensor) -> bytes:
    from PIL import Image

    rgb = (texture.detach().cpu().float().clamp(0, 1).numpy() * 255.0 + 0.5).astype(np.uint8)
    buf = io.BytesIO()
    Image.fromarray(rgb).save(buf, format="PNG")
    return buf.getvalue()
