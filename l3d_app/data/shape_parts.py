"""Built-in procedural part-labelled shapes: chairs, vases and lamps as point clouds.

Every object is assembled from primitive meshes (:mod:`l3d_app.geometry.primitives` plus a
surface of revolution, :func:`lathe`), each primitive tagged with a part, and sampled
uniformly by area with :func:`~l3d_app.geometry.sampling.sample_surface` to P points whose
part is the part of the face they land on. Objects stand on the XZ plane with +Y up and
face +Z; each cloud is then centred (bounding-box centre) and scaled so that its farthest
point is at distance 1.

Variety (per object, from its own seed): chairs have random seat size/height/shape
(square or round), four legs or a pedestal with a star base, a solid, slatted or tilted
back, and arms with probability 0.4; vases have random body profiles (bulge, taper,
waist), a neck with or without a flared lip, and a flat, stepped or conical foot; lamps
have a disc, box or dome base, a straight or bent (desk-lamp) stem, and a conical, drum
or dome shade.

Global part-label space (:data:`PART_NAMES`, the same for every source class)::

    0 chair/seat   1 chair/back   2 chair/legs   3 chair/arms
    4 vase/body    5 vase/neck (with the lip)     6 vase/base
    7 lamp/base    8 lamp/stem    9 lamp/shade

Class labels follow :data:`CLASS_NAMES` = (chair, vase, lamp). The dataset is generated
on first use and cached as ``shape_parts_<hash>.npz`` in ``cache_dir`` (default
``~/.cache/l3d_app``); the hash covers every generation knob. The train/test split is
fixed by ``seed``: object ``i`` of class ``c`` always has the same shape and samples. The
validation split is ``val_fraction`` of the training objects (per class, ``val_seed``).
"""

from __future__ import annotations

import math
from typing import Callable, Dict, List, Optional, Sequence, Tuple

import numpy as np
import torch

from l3d_app.data.point_cache import cached_point_sets, class_block_splits
from l3d_app.data.point_sets import PointCloudData
from l3d_app.errors import UserError
from l3d_app.geometry import primitives as prim
from l3d_app.geometry.mesh import Mesh
from l3d_app.geometry.sampling import sample_surface
from l3d_app.geometry.transforms import axis_rotation
from l3d_app.registry import DATASETS
from l3d_app.runtime.config_values import config_words
from l3d_app.runtime.progress import progress

CLASS_NAMES = ("chair", "vase", "lamp")
PART_NAMES = ("chair/seat", "chair/back", "chair/legs", "chair/arms",
              "vase/body", "vase/neck", "vase/base",
              "lamp/base", "lamp/stem", "lamp/shade")
SEAT, BACK, LEGS, ARMS, BODY, NECK, VBASE, LBASE, STEM, SHADE = range(10)
VERSION = 1  # bump when the generators change (invalidates caches)

Part = Tuple[Mesh, int]


def lathe(radii: Sequence[float], heights: Sequence[float], n: int = 32,
          cap_bottom: bool = False, cap_top: bool = False) -> Mesh:
    """Surface of revolution about +Y: ring ``i`` has radius ``radii[i]`` at ``heights[i]``.

    Args:
        radii, heights: (R,) profile, R >= 2, radii >= 0 (world units).
        n: segments around the axis.
        cap_bottom / cap_top: close the first / last ring with a flat disc.
    Returns:
        Mesh with R * n (+ caps) vertices, 2 n (R - 1) (+ n per cap) faces.
    """
    r = torch.as_tensor(radii, dtype=torch.float64)
    h = torch.as_tensor(heights, dtype=torch.float64)
    rings = r.shape[0]
    phi = torch.arange(n, dtype=torch.float64) * (2 * math.pi / n)
    verts = torch.stack([r[:, None] * phi.sin(), h[:, None].expand(rings, n),
                         r[:, None] * phi.cos()], -1).reshape(-1, 3)
    i = torch.arange(rings - 1)[:, None] * n
    j = torch.arange(n)[None, :]
    a, b = i + j, i + (j + 1) % n
    c, d = a + n, b + n
    faces = [torch.stack([a, c, b], -1).reshape(-1, 3), torch.stack([b, c, d], -1).reshape(-1, 3)]
    extra = []
    for on, ring, y in ((cap_bottom, 0, h[0]), (cap_top, rings - 1, h[-1])):
        if on:
            centre = rings * n + len(extra)
            extra.append(torch.tensor([[0.0, float(y), 0.0]], dtype=torch.float64))
            k = ring * n + torch.arange(n)
            faces.append(torch.stack([torch.full_like(k, centre), k, ring * n + (k + 1 - ring * n) % n], -1))
    verts = torch.cat([verts] + extra)
    return Mesh(verts=verts.float(), faces=torch.cat(faces).long())


def _box(center, size) -> Mesh:
    return prim.box([float(c) for c in center], [float(s) for s in size])


def _cyl(center, radius, height, n: int = 16, rotation=None) -> Mesh:
    mesh = prim.cylinder(float(radius), float(height), n)
    return prim.transformed(mesh, rotation=rotation, translation=[float(c) for c in center])


def arm_rests(rng: np.random.Generator, w: float, d: float, h: float, label: int) -> List[Part]:
    """A chair's arms, each part labelled ``label``: on each side of a ``w`` x ``d`` seat whose top is at
    height ``h``, a rest (height and width drawn from ``rng``) and a support beneath it."""
    ah, aw = rng.uniform(0.2, 0.32), rng.uniform(0.06, 0.1)
    parts: List[Part] = []
    for sx in (-1, 1):
        x = sx * (w / 2 + aw / 2)
        parts.append((_box((x, h + ah, 0.0), (aw, 0.05, d * 0.85)), label))
        parts.append((_box((x, h + ah / 2, d * 0.3), (aw * 0.6, ah, aw * 0.6)), label))
    return parts


def _chair(rng: np.random.Generator) -> List[Part]:
    w, d = rng.uniform(0.8, 1.2), rng.uniform(0.75, 1.15)
    t, h = rng.uniform(0.06, 0.14), rng.uniform(0.7, 1.05)
    parts: List[Part] = []
    round_seat = rng.random() < 0.25
    if round_seat:
        parts.append((_cyl((0, h - t / 2, 0), 0.5 * min(w, d) + 0.05, t, 24), SEAT))
        w = d = min(w, d)
    else:
        parts.append((_box((0, h - t / 2, 0), (w, t, d)), SEAT))
    if rng.random() < 0.75:  # four legs
        lt = rng.uniform(0.05, 0.1)
        inset = rng.uniform(0.0, 0.08)
        for sx in (-1, 1):
            for sz in (-1, 1):
                x, z = sx * (w / 2 - lt / 2 - inset), sz * (d / 2 - lt / 2 - inset)
                if round_seat:
                    x, z = x * 0.7, z * 0.7
                leg = (_cyl((x, (h - t) / 2, z), lt / 2, h - t, 10) if rng.random() < 0.5
                       else _box((x, (h - t) / 2, z), (lt, h - t, lt)))
                parts.append((leg, LEGS))
    else:  # pedestal with a star base
        r = rng.uniform(0.04, 0.08)
        parts.append((_cyl((0, (h - t) / 2, 0), r, h - t - 0.05, 12), LEGS))
        spokes = int(rng.integers(4, 6))
        reach = rng.uniform(0.3, 0.5)
        for k in range(spokes):
            rot = axis_rotation("y", 360.0 * k / spokes + 45.0)
            spoke = prim.transformed(_box((0, 0.03, reach / 2), (0.06, 0.06, reach)), rotation=rot)
            parts.append((spoke, LEGS))
    bh, bt = rng.uniform(0.6, 1.1), rng.uniform(0.05, 0.1)
    tilt = rng.uniform(0.0, 18.0)
    rot = axis_rotation("x", -tilt)
    back_z = -d / 2 + bt / 2
    style = rng.random()
    if style < 0.55:  # solid panel
        pieces = [_box((0, bh / 2, 0), (w, bh, bt))]
    else:  # two posts and slats (horizontal or vertical)
        post = rng.uniform(0.05, 0.09)
        pieces = [_box((sx * (w / 2 - post / 2), bh / 2, 0), (post, bh, bt)) for sx in (-1, 1)]
        slats = int(rng.integers(2, 5))
        if style < 0.8:
            for k in range(slats):
                y = bh * (0.3 + 0.7 * (k + 0.5) / slats)
                pieces.append(_box((0, y, 0), (w - 2 * post, bh * 0.12, bt * 0.8)))
        else:
            pieces.append(_box((0, bh - 0.05, 0), (w - 2 * post, 0.1, bt)))
            for k in range(slats):
                x = (w - 2 * post) * ((k + 0.5) / slats - 0.5)
                pieces.append(_box((x, bh / 2, 0), (0.05, bh, bt * 0.7)))
    for piece in pieces:
        parts.append((prim.transformed(piece, rotation=rot, translation=(0.0, float(h), float(back_z))), BACK))
    if rng.random() < 0.4:  # arms: a rest and a support on each side
        parts += arm_rests(rng, w, d, h, ARMS)
    return parts


def _vase(rng: np.random.Generator) -> List[Part]:
    foot_h = rng.uniform(0.05, 0.15)
    body_h = rng.uniform(0.8, 1.5)
    r0 = rng.uniform(0.25, 0.5)
    bulge, pos = rng.uniform(0.1, 0.7), rng.uniform(0.3, 0.7)
    taper = rng.uniform(-0.3, 0.2)
    s = np.linspace(0.0, 1.0, 12)
    radii = r0 * (1 + bulge * np.sin(np.pi * np.clip(s / pos, 0, 1) / 2 + np.pi * np.clip(s - pos, 0, 1) / (2 * (1 - pos)))
                  + taper * s)
    neck_r = rng.uniform(0.35, 0.7) * radii[-1]
    radii[-1] = max(min(radii[-1], radii[-2]) * 0.8, neck_r * 1.05)
    heights = foot_h + body_h * s
    parts: List[Part] = [(lathe(radii, heights, 28, cap_bottom=True), BODY)]
    neck_h = rng.uniform(0.1, 0.45)
    top = heights[-1]
    neck = [neck_r, neck_r * rng.uniform(0.85, 1.1)]
    neck_y = [top, top + neck_h]
    if rng.random() < 0.6:  # flared lip
        neck.append(neck[-1] * rng.uniform(1.25, 1.6))
        neck_y.append(top + neck_h + rng.uniform(0.04, 0.1))
    parts.append((lathe([radii[-1]] + neck, [top] + neck_y, 28), NECK))
    style = rng.random()
    fr = radii[0] * rng.uniform(0.8, 1.15)
    if style < 0.4:
        foot = lathe([fr, fr, radii[0]], [0.0, foot_h * 0.6, foot_h], 28, cap_bottom=True)
    elif style < 0.7:
        foot = lathe([fr * 1.1, fr * 1.1, fr * 0.7, radii[0]],
                     [0.0, foot_h * 0.4, foot_h * 0.5, foot_h], 28, cap_bottom=True)
    else:
        foot = lathe([fr * 1.2, radii[0] * 0.7, radii[0]], [0.0, foot_h * 0.8, foot_h], 28, cap_bottom=True)
    parts.append((foot, VBASE))
    return parts


def _lamp(rng: np.random.Generator) -> List[Part]:
    parts: List[Part] = []
    style = rng.random()
    bh = rng.uniform(0.05, 0.15)
    br = rng.uniform(0.25, 0.45)
    if style < 0.45:
        parts.append((_cyl((0, bh / 2, 0), br, bh, 24), LBASE))
    elif style < 0.7:
        parts.append((_box((0, bh / 2, 0), (2 * br * 0.9, bh, 2 * br * 0.9)), LBASE))
    else:
        ang = np.linspace(0, np.pi / 2, 7)
        parts.append((lathe(br * np.cos(ang) + 1e-3, bh * 1.5 * np.sin(ang), 24, cap_bottom=True), LBASE))
        bh = bh * 1.5
    stem_h, stem_r = rng.uniform(0.8, 1.7), rng.uniform(0.02, 0.045)
    parts.append((_cyl((0, bh + stem_h / 2, 0), stem_r, stem_h, 10), STEM))
    top = np.array([0.0, bh + stem_h, 0.0])
    shade_rot = None
    if rng.random() < 0.3:  # bent desk-lamp arm, shade tilted
        arm_l, arm_a = rng.uniform(0.4, 0.8), rng.uniform(30.0, 70.0)
        rot = axis_rotation("x", arm_a)
        arm = prim.transformed(_cyl((0, arm_l / 2, 0), stem_r, arm_l, 10), rotation=rot,
                               translation=top.tolist())
        parts.append((arm, STEM))
        top = top + (rot.double() @ torch.tensor([0.0, arm_l, 0.0], dtype=torch.float64)).numpy()
        shade_rot = axis_rotation("x", arm_a + rng.uniform(60.0, 110.0))
    sh = rng.uniform(0.3, 0.6)
    r_top, r_bot = rng.uniform(0.1, 0.25), rng.uniform(0.25, 0.5)
    kind = rng.random()
    if kind < 0.45:    # cone frustum, open
        shade = lathe([r_bot, r_top], [-sh * 0.6, sh * 0.4], 28)
    elif kind < 0.75:  # drum
        shade = lathe([r_bot, r_bot], [-sh * 0.6, sh * 0.4], 28)
    else:              # dome, opening downwards
        ang = np.linspace(0, np.pi / 2, 8)
        shade = lathe(r_bot * np.cos(ang) + 1e-3, -sh * 0.5 + sh * 0.8 * np.sin(ang), 28)
    if shade_rot is not None:
        shade = prim.transformed(shade, rotation=axis_rotation("x", 180.0))
        shade = prim.transformed(shade, rotation=shade_rot, translation=top.tolist())
    else:
        shade = prim.transformed(shade, translation=top.tolist())
    parts.append((shade, SHADE))
    return parts


GENERATORS: Dict[str, Callable[[np.random.Generator], List[Part]]] = {
    "chair": _chair, "vase": _vase, "lamp": _lamp}


def sample_object(parts: List[Part], num_points: int, generator: torch.Generator):
    """Sample ``num_points`` points on the union of ``parts``.

    Returns points (P, 3) float32 (centred, farthest point at distance 1) and the part
    label (P,) int64 of the face each point lies on.
    """
    mesh = prim.join([m for m, _ in parts])
    face_part = torch.cat([torch.full((m.num_faces,), label, dtype=torch.int64) for m, label in parts])
    samples = sample_surface(mesh, num_points, generator)
    pts = samples.points
    lo, hi = pts.min(0).values, pts.max(0).values
    pts = pts - (lo + hi) / 2
    pts = pts / pts.norm(dim=-1).max().clamp_min(1e-12)
    return pts.float(), face_part[samples.face_index]


def generate(classes: Sequence[str], per_class: int, num_points: int, seed: int,
             desc: str = "shape_parts") -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Generate ``per_class`` objects of each class.

    Returns points (C * per_class, P, 3) float32, class labels (C * per_class,) uint8 (the
    index in :data:`CLASS_NAMES`) and part labels (C * per_class, P) uint8; objects are
    ordered class by class, object ``i`` of a class seeded by ``(seed, class, i)``.
    """
    pts = np.empty((len(classes) * per_class, num_points, 3), np.float32)
    parts = np.empty((len(classes) * per_class, num_points), np.uint8)
    labels = np.empty(len(classes) * per_class, np.uint8)
    jobs = [(c, i) for c in classes for i in range(per_class)]
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # tiny tensors: one thread is ~8x faster than several
    try:
        for k, (c, i) in enumerate(progress(jobs, desc=desc)):
            cid = CLASS_NAMES.index(c)
            rng = np.random.default_rng([seed, cid, i])
            gen = torch.Generator().manual_seed(int(rng.integers(2 ** 62)))
            p, lab = sample_object(GENERATORS[c](rng), num_points, gen)
            pts[k], parts[k], labels[k] = p.numpy(), lab.numpy().astype(np.uint8), cid
    finally:
        torch.set_num_threads(threads)
    return pts, labels, parts


@DATASETS.register("shape_parts")
def shape_parts(classes: Sequence[str] = CLASS_NAMES, train_per_class: int = 200,
                test_per_class: int = 50, num_points: int = 10000, seed: int = 0,
                cache_dir: Optional[str] = None, val_fraction: float = 0.1, val_seed: int = 0,
                kind: str = "cls", device=None) -> PointCloudData:
    """The built-in dataset (see module docstring), generated once and cached.

    Args:
        classes: subset of :data:`CLASS_NAMES`; class labels stay the global indices.
        train_per_class / test_per_class: objects per class in each split.
        num_points: P, surface points per object (the course uses 10,000).
        seed: generation seed (fixes shapes, samples and the split).
        cache_dir: cache folder (None: :func:`~l3d_app.data.point_cache.default_cache_dir`).
        val_fraction / val_seed: the validation split carved from the training objects
            (stratified by class; see :meth:`PointCloudData.with_val`).
        kind, device: accepted for a uniform data-source interface; both label kinds are
            always present and data stays on the CPU.
    """
    classes = config_words(classes, "data.classes")
    unknown = [c for c in classes if c not in CLASS_NAMES]
    if unknown or not classes:
        raise UserError(f"unknown shape_parts class {unknown or classes}; known: {', '.join(CLASS_NAMES)}")
    for key, value in (("train_per_class", train_per_class), ("test_per_class", test_per_class),
                       ("num_points", num_points)):
        if int(value) < 1:
            raise UserError(f"data.{key} must be >= 1, got {value}")
    n = int(train_per_class) + int(test_per_class)
    knobs = {"classes": classes, "n": n, "num_points": int(num_points), "seed": int(seed), "v": VERSION}

    def make() -> dict:
        pts, labels, parts = generate(classes, n, int(num_points), int(seed))
        return {"points": pts, "labels": labels, "parts": parts}

    pts, labels, parts, path = cached_point_sets("shape_parts", knobs, cache_dir, make)
    train, test = class_block_splits(pts, labels, parts, n, int(train_per_class))
    return PointCloudData(train, test, list(CLASS_NAMES), list(PART_NAMES),
                          source=f"shape_parts:{path}").with_val(val_fraction, val_seed)
