"""Built-in single-view-reconstruction dataset: procedural chairs, tables and lamps.

Every object is a union of CLOSED primitive meshes (boxes, cylinders, frustums from
:mod:`l3d_app.geometry.primitives`) with random proportions and thin parts (legs, stems,
rails): chairs come from :data:`l3d_app.data.shape_parts.GENERATORS` (the PointNet
dataset's chair generator), tables and lamps are built here (shape_parts' lamp shades are
open surfaces, which have no inside for voxels/occupancy). Objects stand on +Y, face +Z, and
are centred (bounding-box centre at the origin) and scaled so that the farthest vertex is
at distance 1: every object lies in the canonical box ``[-1, 1]^3`` (:data:`BOUNDS`).

Per object the dataset stores (all in the canonical object frame, world units):

* ``views_per_object`` input images rendered by our
  :class:`~l3d_app.render.mesh.renderer.MeshRenderer` (Lambert, fixed light, white
  background, 2x supersampling), from cameras looking at the origin from ``distance`` with
  random elevation in ``elevation_range`` and azimuth in ``azimuth_range`` (degrees);
* ``num_points`` surface samples (area-uniform), the ground truth for chamfer / F1;
* a ``voxel_size``^3 occupancy grid over :data:`BOUNDS` (inside test at the cell centres,
  :func:`~l3d_app.geometry.voxels.voxel_centers`; the same grid convention as
  :func:`~l3d_app.geometry.voxels.voxelize_mesh`, whose winding number it matches here);
* ``occupancy_points`` query points with inside labels (half uniform in the box, half
  surface samples jittered by N(0, 0.05^2)), for implicit decoders;
* camera-Z depth maps and silhouettes of the mesh from ``depth_views`` FIXED cameras shared
  by all objects (Fibonacci spiral, elevations [-20, 60] degrees), the only supervision of
  the 2D-supervised point generator (0 depth = background);
* the mesh itself (for ground-truth pictures).

Generated on first use and cached as ``svr_shapes_<hash>.pt`` in ``cache_dir`` (the hash
covers every knob); object ``i`` of class ``c`` is seeded by ``(seed, c, i)``, so a
dataset is the same on every machine, and growing ``train_per_class`` keeps the objects.
"""

from __future__ import annotations

import hashlib
import json
import math
from dataclasses import dataclass
from typing import Callable, Dict, List, Optional, Sequence, Tuple

import numpy as np
import torch

from l3d_app.data.shape_parts import GENERATORS as PART_GENERATORS
from l3d_app.data.val_split import carve_val
from l3d_app.errors import UserError
from l3d_app.geometry import primitives as prim
from l3d_app.geometry.cameras import Cameras, look_at_cameras
from l3d_app.geometry.mesh import Mesh
from l3d_app.geometry.sampling import sample_surface
from l3d_app.geometry.transforms import axis_rotation
from l3d_app.geometry.voxels import voxel_centers
from l3d_app.registry import DATASETS
from l3d_app.runtime.config_values import config_words
from l3d_app.runtime.files import atomic_path
from l3d_app.runtime.paths import resolve_path
from l3d_app.runtime.progress import progress

CLASS_NAMES = ("chair", "table", "lamp")
BOUNDS = ((-1.0, -1.0, -1.0), (1.0, 1.0, 1.0))
VERSION = 1  # bump when the generators or stored fields change (invalidates caches)


# ------------------------------------------------------------------- generators
def frustum(r_bottom: float, r_top: float, height: float, n: int = 16) -> Mesh:
    """Closed truncated cone along Y, centred: the capped cylinder with its top ring scaled
    by ``r_top / r_bottom`` (radii > 0, world units). 2n + 2 vertices, 4n faces."""
    cyl = prim.cylinder(float(r_bottom), float(height), n)
    v = cyl.verts.clone()
    v[:n, [0, 2]] *= float(r_top) / float(r_bottom)  # the first ring is the top (+height/2)
    return cyl.with_verts(v)


def _box(center, size) -> Mesh:
    return prim.box([float(c) for c in center], [float(s) for s in size])


def _cyl(center, radius, height, n: int = 12) -> Mesh:
    return prim.transformed(prim.cylinder(float(radius), float(height), n),
                            translation=[float(c) for c in center])


def table(rng: np.random.Generator) -> List[Mesh]:
    """A table: rectangular or round top; four thin legs (with optional rails), a pedestal
    with a foot disc, or two trestle panels."""
    w, d = rng.uniform(1.0, 1.7), rng.uniform(0.6, 1.1)
    h, t = rng.uniform(0.55, 0.95), rng.uniform(0.04, 0.09)
    round_top = rng.random() < 0.3
    parts = [_cyl((0, h - t / 2, 0), 0.5 * w, t, 32) if round_top else _box((0, h - t / 2, 0), (w, t, d))]
    if round_top:
        d = w
    style = rng.random()
    if style < 0.6:  # four legs
        lt = rng.uniform(0.04, 0.09)
        inset = rng.uniform(0.02, 0.12)
        sx_, sz_ = (0.35, 0.35) if round_top else (w / 2 - lt / 2 - inset, d / 2 - lt / 2 - inset)
        for sx in (-1, 1):
            for sz in (-1, 1):
                c = (sx * sx_, (h - t) / 2, sz * sz_)
                parts.append(_cyl(c, lt / 2, h - t, 10) if rng.random() < 0.5 else _box(c, (lt, h - t, lt)))
        if rng.random() < 0.5:  # rails between the legs, low down
            y = rng.uniform(0.12, 0.3) * h
            parts.append(_box((0, y, sz_), (2 * sx_, lt * 0.6, lt * 0.6)))
            parts.append(_box((0, y, -sz_), (2 * sx_, lt * 0.6, lt * 0.6)))
    elif style < 0.8:  # pedestal
        r = rng.uniform(0.04, 0.1)
        parts.append(_cyl((0, (h - t) / 2, 0), r, h - t, 12))
        parts.append(_cyl((0, 0.025, 0), rng.uniform(0.25, 0.4), 0.05, 24))
    else:  # trestle: two thin panels near the ends
        pt = rng.uniform(0.04, 0.08)
        for sx in (-1, 1):
            parts.append(_box((sx * (w / 2 - 0.1), (h - t) / 2, 0), (pt, h - t, d * 0.8)))
    return parts


def lamp(rng: np.random.Generator) -> List[Mesh]:
    """A lamp: disc or box base, a thin stem (straight, or bent with a tilted shade), and a
    closed drum / cone / inverted-cone shade."""
    bh, br = rng.uniform(0.04, 0.12), rng.uniform(0.2, 0.4)
    parts = [_cyl((0, bh / 2, 0), br, bh, 24) if rng.random() < 0.6
             else _box((0, bh / 2, 0), (1.8 * br, bh, 1.8 * br))]
    stem_h, stem_r = rng.uniform(0.8, 1.6), rng.uniform(0.02, 0.04)
    parts.append(_cyl((0, bh + stem_h / 2, 0), stem_r, stem_h, 10))
    top = np.array([0.0, bh + stem_h, 0.0])
    sh = rng.uniform(0.25, 0.55)
    r_bot, r_top = rng.uniform(0.2, 0.45), rng.uniform(0.08, 0.3)
    kind = rng.random()
    if kind < 0.35:
        r_top = r_bot  # drum
    elif kind < 0.5:
        r_bot, r_top = r_top, r_bot  # opens upwards (torchiere)
    shade = frustum(r_bot, r_top, sh, 24)
    if rng.random() < 0.35:  # bent arm, shade hanging at its end
        arm_l, arm_a = rng.uniform(0.3, 0.6), rng.uniform(40.0, 80.0)
        rot = axis_rotation("x", arm_a)
        parts.append(prim.transformed(_cyl((0, arm_l / 2, 0), stem_r, arm_l, 10), rotation=rot,
                                      translation=top.tolist()))
        top = top + (rot.double() @ torch.tensor([0.0, arm_l, 0.0], dtype=torch.float64)).numpy()
        parts.append(prim.transformed(shade, rotation=axis_rotation("x", arm_a + 90.0),
                                      translation=top.tolist()))
    else:
        parts.append(prim.transformed(shade, translation=(top + [0.0, sh * 0.2, 0.0]).tolist()))
    return parts


def chair(rng: np.random.Generator) -> List[Mesh]:
    """A chair from the PointNet part dataset's generator (labels dropped)."""
    return [m for m, _ in PART_GENERATORS["chair"](rng)]


GENERATORS: Dict[str, Callable[[np.random.Generator], List[Mesh]]] = {
    "chair": chair, "table": table, "lamp": lamp}


def make_object(category: str, rng: np.random.Generator) -> Tuple[Mesh, List[Mesh]]:
    """One object of ``category`` in the canonical frame (bounding-box centre at the origin,
    farthest vertex at distance 1): the joined mesh and its convex closed parts."""
    parts = GENERATORS[category](rng)
    mesh = prim.join(parts)
    lo, hi = mesh.bounds()
    centre = (lo + hi) / 2
    scale = 1.0 / float((mesh.verts - centre).norm(dim=-1).max().clamp_min(1e-12))
    parts = [Mesh(verts=((p.verts - centre) * scale).float(), faces=p.faces) for p in parts]
    return prim.join(parts), parts


def inside_convex_union(parts: Sequence[Mesh], points: torch.Tensor) -> torch.Tensor:
    """(P,) bool: the point lies inside at least one of the CLOSED CONVEX ``parts``.

    A point is inside a convex part when it is behind every face plane,
    ``max_f n_f . (p - v_f) <= 0`` (outward face normals): one (P, F) matrix product
    instead of the generalised winding number's O(P F) solid angles (about 35x faster
    here; the two agree on these shapes, see tests/test_svr_shapes.py). Only valid for
    convex closed parts, which is how every generator here builds its objects.
    """
    mesh = prim.join(parts)
    normals = mesh.face_normals(unit=False).to(points.dtype)        # (F, 3), zero if degenerate
    offsets = (normals * mesh.verts[mesh.faces[:, 0]].to(points.dtype)).sum(-1)  # (F,)
    signed = points @ normals.T - offsets                             # (P, F), > 0 outside a face
    part = torch.repeat_interleave(torch.arange(len(parts)), torch.tensor([p.num_faces for p in parts]))
    worst = torch.full((points.shape[0], len(parts)), -math.inf, dtype=points.dtype)
    worst = worst.scatter_reduce(1, part.expand(points.shape[0], -1), signed, "amax")
    return (worst <= 0).any(dim=1)


# ---------------------------------------------------------------------- cameras
def depth_cameras(n: int, distance: float, fov: float, image_size: int) -> Cameras:
    """The ``n`` fixed supervision cameras: a Fibonacci spiral, elevations [-20, 60] degrees."""
    k = torch.arange(n, dtype=torch.float64)
    lo, hi = math.sin(math.radians(-20.0)), math.sin(math.radians(60.0))
    elev = torch.rad2deg(torch.asin(lo + (hi - lo) * (k + 0.5) / max(n, 1)))
    azim = torch.remainder(k * 137.50776405 + 15.0, 360.0)
    return look_at_cameras(distance, elev.float(), azim.float(), fov, image_size)


# ------------------------------------------------------------------------- data
@dataclass
class SVRData:
    """The dataset (CPU tensors). N objects, V views each, S depth views.

    Attributes:
        images: (N, V, H, W, 3) float32 in [0, 1], input views.
        elevation, azimuth: (N, V) degrees, the input cameras (look-at the origin).
        points: (N, P, 3) surface samples; voxels: (N, R, R, R) bool over :data:`BOUNDS`.
        occ_points: (N, Q, 3) query points; occ_labels: (N, Q) bool (inside).
        depth: (N, S, H, W) camera-Z depth from :attr:`depth_cameras`, 0 on background.
        verts, faces: concatenated meshes; vert_counts, face_counts: (N,) sizes.
        labels: (N,) class index in :attr:`class_names`; train, val, test: object indices
            (val carved from the generated training objects, see :func:`svr_shapes`).
        distance, fov: input/depth camera distance (world units) and field of view (deg).
    """

    images: torch.Tensor
    elevation: torch.Tensor
    azimuth: torch.Tensor
    points: torch.Tensor
    voxels: torch.Tensor
    occ_points: torch.Tensor
    occ_labels: torch.Tensor
    depth: torch.Tensor
    verts: torch.Tensor
    faces: torch.Tensor
    vert_counts: torch.Tensor
    face_counts: torch.Tensor
    labels: torch.Tensor
    class_names: Tuple[str, ...]
    train: torch.Tensor
    test: torch.Tensor
    distance: float
    fov: float
    source: str = ""
    val: Optional[torch.Tensor] = None

    @property
    def image_size(self) -> int:
        return int(self.images.shape[2])

    @property
    def depth_cameras(self) -> Cameras:
        return depth_cameras(int(self.depth.shape[1]), self.distance, self.fov, self.image_size)

    def cameras(self, objects: torch.Tensor, views: torch.Tensor) -> Cameras:
        """Input cameras of (object, view) pairs, each (B,) long."""
        return look_at_cameras(self.distance, self.elevation[objects, views], self.azimuth[objects, views],
                               self.fov, self.image_size)

    def mesh(self, i: int) -> Mesh:
        """Ground-truth mesh of object ``i``."""
        v0 = int(self.vert_counts[:i].sum())
        f0 = int(self.face_counts[:i].sum())
        v = self.verts[v0:v0 + int(self.vert_counts[i])]
        f = self.faces[f0:f0 + int(self.face_counts[i])]  # stored per object (0-based)
        return Mesh(verts=v, faces=f)


def render_object(mesh: Mesh, cams: Cameras, antialias: int = 2) -> torch.Tensor:
    """(B, H, W, 3) Lambert renders under a fixed light on white (the input images)."""
    from l3d_app.render.mesh.renderer import MeshRenderer

    renderer = MeshRenderer(shading="lambert", background=(1.0, 1.0, 1.0), ambient=0.35, diffuse=0.65,
                            specular=0.0, light_direction=(0.4, 1.0, 0.7), antialias=int(antialias))
    return renderer(mesh, cams)["image"]


def render_depth(mesh: Mesh, cams: Cameras) -> torch.Tensor:
    """(B, H, W) camera-Z depth of the nearest surface (0 on background), no supersampling."""
    from l3d_app.render.mesh.renderer import MeshRenderer

    return MeshRenderer(shading="unlit")(mesh, cams)["depth"]


def generate_object(category: str, seed: Sequence[int], knobs: Dict) -> Dict[str, torch.Tensor]:
    """All stored fields of one object (see the module docstring); ``seed`` fixes everything."""
    rng = np.random.default_rng(list(seed))
    mesh, parts = make_object(category, rng)
    gen = torch.Generator().manual_seed(int(rng.integers(2 ** 62)))
    V, S, size = knobs["views_per_object"], knobs["depth_views"], knobs["image_size"]
    elev = torch.tensor(rng.uniform(*knobs["elevation_range"], size=V), dtype=torch.float32)
    azim = torch.tensor(rng.uniform(*knobs["azimuth_range"], size=V), dtype=torch.float32)
    cams = look_at_cameras(knobs["distance"], elev, azim, knobs["fov"], size)
    images = render_object(mesh, cams)
    depth = render_depth(mesh, depth_cameras(S, knobs["distance"], knobs["fov"], size))
    points = sample_surface(mesh, knobs["num_points"], gen).points
    R = knobs["voxel_size"]
    voxels = inside_convex_union(parts, voxel_centers(R, BOUNDS).reshape(-1, 3)).reshape(R, R, R)
    q = knobs["occupancy_points"]
    uniform = torch.rand(q // 2, 3, generator=gen) * 2 - 1
    near = sample_surface(mesh, q - q // 2, gen).points + 0.05 * torch.randn(q - q // 2, 3, generator=gen)
    occ_points = torch.cat([uniform, near])
    occ = inside_convex_union(parts, occ_points)
    return {"images": (images * 255).round().to(torch.uint8), "elevation": elev, "azimuth": azim,
            "points": points.float(), "voxels": voxels, "occ_points": occ_points.float(), "occ_labels": occ,
            "depth": depth.float(), "verts": mesh.verts, "faces": mesh.faces}


def _check(classes, knobs: Dict) -> None:
    unknown = [c for c in classes if c not in CLASS_NAMES]
    if unknown or not classes:
        raise UserError(f"unknown svr_shapes class {unknown or classes}; known: {', '.join(CLASS_NAMES)}")
    for key in ("n", "views_per_object", "depth_views", "num_points", "occupancy_points"):
        if int(knobs[key]) < 1:
            raise UserError(f"data.{key} must be >= 1, got {knobs[key]}")
    if int(knobs["image_size"]) < 8 or int(knobs["voxel_size"]) < 4:
        raise UserError(f"svr_shapes needs image_size >= 8 and voxel_size >= 4, "
                        f"got {knobs['image_size']}, {knobs['voxel_size']}")
    for key in ("elevation_range", "azimuth_range"):
        if len(knobs[key]) != 2 or not knobs[key][0] <= knobs[key][1]:
            raise UserError(f"data.{key} must be [low, high] with low <= high, got {knobs[key]}")


@DATASETS.register("svr_shapes")
def svr_shapes(classes: Sequence[str] = CLASS_NAMES, train_per_class: int = 60, test_per_class: int = 10,
               views_per_object: int = 2, image_size: int = 32, voxel_size: int = 32, num_points: int = 4096,
               occupancy_points: int = 4096, depth_views: int = 12, distance: float = 2.5, fov: float = 50.0,
               elevation_range: Sequence[float] = (10.0, 40.0), azimuth_range: Sequence[float] = (0.0, 360.0),
               seed: int = 0, cache_dir: str = "outputs/.cache", val_fraction: float = 0.1, val_seed: int = 0,
               device=None) -> SVRData:
    """The built-in SVR dataset (see the module docstring), generated once and cached.

    Sizes: ``train_per_class`` / ``test_per_class`` objects per class per split; images and
    depth maps ``image_size`` pixels square; ``voxel_size`` cells per axis; ``num_points``
    surface samples and ``occupancy_points`` labelled queries per object. The validation
    objects are ``val_fraction`` of the ``train_per_class`` objects of each class (chosen by
    ``val_seed``; :func:`l3d_app.data.val_split.carve_val`); the test objects are never
    touched. ``device`` is accepted for the uniform data-source interface; the data stays
    on the CPU.
    """
    classes = config_words(classes, "data.classes")
    knobs = {"classes": classes, "n": int(train_per_class) + int(test_per_class),
             "views_per_object": int(views_per_object), "image_size": int(image_size),
             "voxel_size": int(voxel_size), "num_points": int(num_points),
             "occupancy_points": int(occupancy_points), "depth_views": int(depth_views),
             "distance": float(distance), "fov": float(fov),
             "elevation_range": [float(x) for x in elevation_range],
             "azimuth_range": [float(x) for x in azimuth_range], "seed": int(seed), "v": VERSION}
    _check(classes, knobs)
    if int(train_per_class) < 1 or int(test_per_class) < 1:
        raise UserError(f"svr_shapes needs train_per_class >= 1 and test_per_class >= 1, "
                        f"got {train_per_class}, {test_per_class}")
    digest = hashlib.sha1(json.dumps(knobs, sort_keys=True).encode()).hexdigest()[:12]
    path = resolve_path(cache_dir) / f"svr_shapes_{digest}.pt"
    if path.exists():
        fields = torch.load(path, map_location="cpu", weights_only=True)
    else:
        fields = _generate(knobs)
        try:
            with atomic_path(path) as tmp:
                torch.save(fields, tmp)
        except OSError as err:  # read-only cache: keep going without it
            print(f"l3d_app: warning: cannot cache svr_shapes in {path.parent}: {err}")
    n = knobs["n"]
    within = torch.arange(len(fields["labels"])) % n
    generated_train = torch.nonzero(within < int(train_per_class))[:, 0]
    keep, held = carve_val(len(generated_train), val_fraction, val_seed, fields["labels"][generated_train])
    return SVRData(images=fields["images"].float() / 255, elevation=fields["elevation"], azimuth=fields["azimuth"],
                   points=fields["points"], voxels=fields["voxels"], occ_points=fields["occ_points"],
                   occ_labels=fields["occ_labels"], depth=fields["depth"].float(), verts=fields["verts"],
                   faces=fields["faces"], vert_counts=fields["vert_counts"], face_counts=fields["face_counts"],
                   labels=fields["labels"], class_names=tuple(CLASS_NAMES),
                   train=generated_train[keep], val=generated_train[held],
                   test=torch.nonzero(within >= int(train_per_class))[:, 0],
                   distance=float(distance), fov=float(fov), source=f"svr_shapes:{path}")


def _generate(knobs: Dict) -> Dict[str, torch.Tensor]:
    """Every object, class by class; stacked fields plus the concatenated meshes."""
    jobs = [(c, i) for c in knobs["classes"] for i in range(knobs["n"])]
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # small tensors: one thread is fastest
    try:
        objs = [generate_object(c, (knobs["seed"], 7919, CLASS_NAMES.index(c), i), knobs)
                for c, i in progress(jobs, desc="svr_shapes")]
    finally:
        torch.set_num_threads(threads)
    out = {k: torch.stack([o[k] for o in objs]) for k in objs[0] if k not in ("verts", "faces")}
    out["verts"] = torch.cat([o["verts"] for o in objs])
    out["faces"] = torch.cat([o["faces"] for o in objs])
    out["vert_counts"] = torch.tensor([o["verts"].shape[0] for o in objs])
    out["face_counts"] = torch.tensor([o["faces"].shape[0] for o in objs])
    out["labels"] = torch.tensor([CLASS_NAMES.index(c) for c, _ in jobs])
    return out
