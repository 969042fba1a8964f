"""Posed multi-view image sets for radiance-field training, and the built-in one.

:class:`MultiViewData` is what every NeRF data source returns (built-in, NeRF-synthetic
``transforms_*.json`` folders in :mod:`l3d_app.data.nerf_formats`, the course truck).

The built-in dataset (``data=nerf_builtin``) is rendered by our own mesh renderer
(:class:`~l3d_app.render.mesh.renderer.MeshRenderer`, Lambert shading under a FIXED
directional light, so appearance does not depend on the viewpoint) from a procedural scene
with textured and thin parts: a checker-textured plinth, four thin coloured poles, a thin
tilted ring and a colour-gradient sphere. Cameras look at the origin from a sphere:
training views on a Fibonacci spiral over elevations [-10, 70] degrees, validation and
test views on separate rings in between. It is generated on first use and cached in
``cache_dir`` (one file per parameter set).
"""

from __future__ import annotations

import hashlib
import json
import math
import sys
from dataclasses import dataclass, replace
from typing import Optional, Sequence, Tuple

import torch

from l3d_app.errors import UserError
from l3d_app.geometry import primitives as P
from l3d_app.geometry.camera_paths import cameras_up
from l3d_app.geometry.cameras import Cameras, look_at_cameras
from l3d_app.geometry.mesh import Mesh
from l3d_app.geometry.transforms import euler_xyz
from l3d_app.registry import DATASETS
from l3d_app.runtime.config_values import config_floats, config_rows
from l3d_app.runtime.files import atomic_path
from l3d_app.runtime.paths import resolve_path

BACKGROUNDS = {"white": (1.0, 1.0, 1.0), "black": (0.0, 0.0, 0.0)}


@dataclass
class MultiViewData:
    """Posed images for a radiance field, and what else the source knows about its scene.

    Tasks read these attributes only (never the data source's name), so every loader
    fills the same fields:

    Attributes:
        images: (N, H, W, 3) float32 in [0, 1] (composited on ``background``).
        cameras: N :class:`Cameras` (internal OpenCV convention).
        train, val, test: (n_split,) long view indices (disjoint; val never from test).
        background: (3,) RGB in [0, 1] behind the scene.
        scene_box: (2, 3) world box (min row, max row) that holds the scene.
        name: where it came from.
        points: (P, 3) float32 initial points in world units (SfM points, a scan) or None.
        point_colors: (P, 3) float32 in [0, 1] matching ``points``, or None.
        mesh: the ground-truth :class:`Mesh` when the source knows it, else None.
        up: (3,) unit world up vector of the scene (orbits and turntables turn about it);
            ``None`` at construction means "the training cameras' mean up vector".
        source_from_world: (4, 4) float64 similarity mapping this dataset's world
            coordinates back to the source file's (identity unless the loader normalised
            the scene): ``x_src = M[:3, :3] @ x + M[:3, 3]``.
        background_known: True when the images were composited on ``background`` (synthetic
            data); False for photographs with a real backdrop, where ``background`` is only
            an initial estimate and a field should learn what lies outside the scene box.
        masks: (N, H, W) float32 coverage in [0, 1] of the scene in each image (the alpha of
            RGBA images), or None when the source has none.
    """

    images: torch.Tensor
    cameras: Cameras
    train: torch.Tensor
    val: torch.Tensor
    test: torch.Tensor
    background: torch.Tensor
    scene_box: torch.Tensor
    name: str = ""
    points: Optional[torch.Tensor] = None
    point_colors: Optional[torch.Tensor] = None
    mesh: Optional[Mesh] = None
    up: Optional[torch.Tensor] = None
    source_from_world: Optional[torch.Tensor] = None
    background_known: bool = True
    masks: Optional[torch.Tensor] = None

    def __post_init__(self):
        if self.up is None:        # from the training cameras: nothing of the scored views
            self.up = cameras_up(self.cameras[self.train] if len(self.train) else self.cameras)
        self.up = torch.nn.functional.normalize(torch.as_tensor(self.up, dtype=torch.float32).reshape(3), dim=0)
        if self.source_from_world is None:
            self.source_from_world = torch.eye(4, dtype=torch.float64)
        for (a, name_a), (b, name_b) in (((self.train, "train"), (self.val, "val")), ((self.train, "train"), (self.test, "test")),
                                         ((self.val, "val"), (self.test, "test"))):
            shared = sorted(set(a.tolist()) & set(b.tolist()))
            if shared:
                raise UserError(f"{self.name or 'the data'}: views {shared[:5]} are in both the {name_a} and the {name_b} "
                                f"split (the splits must be disjoint: the test views only report)")
        if self.points is not None and self.point_colors is not None \
                and self.point_colors.shape != self.points.shape:
            raise ValueError(f"point_colors {tuple(self.point_colors.shape)} must match points "
                             f"{tuple(self.points.shape)}")

    def to(self, device) -> "MultiViewData":
        move = lambda x: None if x is None else x.to(device)  # noqa: E731
        mesh = self.mesh.to(device) if self.mesh is not None and hasattr(self.mesh, "to") else self.mesh
        return replace(self, images=self.images.to(device), cameras=self.cameras.to(device),
                       background=self.background.to(device), scene_box=self.scene_box.to(device),
                       points=move(self.points), point_colors=move(self.point_colors), mesh=mesh,
                       up=self.up.to(device), masks=move(self.masks))

    @property
    def image_size(self) -> Tuple[int, int]:
        """(H, W)."""
        return self.cameras.height, self.cameras.width


def carve_val(train: torch.Tensor, val_every: int) -> Tuple[torch.Tensor, torch.Tensor]:
    """Split training view indices into (train, val): every ``val_every``-th training view
    (positions k-1, 2k-1, ... of ``train``) becomes validation. ``val_every <= 0`` or fewer
    than ``val_every`` training views gives an empty val (training is never emptied)."""
    k = int(val_every)
    if k <= 0 or len(train) < k:
        return train, train[:0]
    pick = torch.zeros(len(train), dtype=torch.bool)
    pick[k - 1::k] = True
    return train[~pick], train[pick]


def disjoint_splits(train: torch.Tensor, val: torch.Tensor, test: torch.Tensor, val_every: int,
                    source: str) -> Tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Split lists read from a file (nerfstudio's ``*_filenames``, the course's ``split``), made
    disjoint: a view in both train and test is refused (the file trains on its test views); val
    loses the views it shares with test (nerfstudio's own files list the same frames as val and
    test) and, when none is left, is carved from train (every ``val_every``-th, :func:`carve_val`),
    with a note on stderr. Returns (train, val, test) index tensors."""
    shared = sorted(set(train.tolist()) & set(test.tolist()))
    if shared:
        raise UserError(f"{source}: views {shared[:5]} are listed for both training and testing "
                        "(the test views only report: list them in one split)")
    test_set = set(test.tolist())
    kept = val[torch.tensor([int(v) not in test_set for v in val.tolist()], dtype=torch.bool)] if len(val) else val
    n_shared = len(val) - len(kept)
    if n_shared:
        if len(kept) == 0:
            train, kept = carve_val(train, val_every)
            how = f"validation carved from the training views instead (every {int(val_every)}th: {len(kept)} views)"
        else:
            how = f"they were dropped from validation ({len(kept)} left)"
        print(f"l3d_app: note: {source}: {n_shared} validation views are also test views; {how}", file=sys.stderr)
    return train, kept, test


def scene_box_tensor(scene_box) -> torch.Tensor:
    """The ``data.scene_box`` knob as a (2, 3) float32 tensor (min row, max row), or :class:`UserError`."""
    return torch.tensor(config_rows(scene_box, "data.scene_box", 2, 3, "[[x, y, z] min, [x, y, z] max]"))


def background_rgb(background) -> torch.Tensor:
    """'white' | 'black' | 3 numbers -> (3,) float tensor."""
    if isinstance(background, str):
        if background not in BACKGROUNDS:
            raise UserError(f"background must be one of {', '.join(BACKGROUNDS)} or 3 numbers, got {background!r}")
        background = BACKGROUNDS[background]
    bg = torch.as_tensor(background, dtype=torch.float32).reshape(-1)
    if bg.numel() != 3:
        raise UserError(f"background must be 3 numbers (RGB), got {background}")
    return bg


# ----------------------------------------------------------- the procedural scene
def checker_box(center: Sequence[float], size: Sequence[float], cells: int,
                colors: Tuple[Sequence[float], Sequence[float]]) -> Mesh:
    """Box with a checkerboard "texture": every face is ``cells x cells`` quads with their own
    vertices (so colours are crisp, normals flat), alternating ``colors``. Faces CCW from outside."""
    c, s = torch.tensor(center, dtype=torch.float64), torch.tensor(size, dtype=torch.float64)
    n = int(cells)
    g = torch.arange(n + 1, dtype=torch.float64) / n
    verts, faces, cols = [], [], []
    col = torch.tensor(colors, dtype=torch.float32)
    i, j = torch.meshgrid(torch.arange(n), torch.arange(n), indexing="ij")
    corners = torch.tensor([[0, 0], [1, 0], [1, 1], [0, 1]])
    for k in range(3):
        for sign in (1.0, -1.0):
            e = torch.eye(3, dtype=torch.float64)
            a, b = e[(k + 1) % 3] * s[(k + 1) % 3], e[(k + 2) % 3] * s[(k + 2) % 3]
            if sign < 0:
                a, b = b, a
            origin = c + sign * 0.5 * s[k] * e[k] - 0.5 * a - 0.5 * b
            ci = (i[..., None] + corners[:, 0]).reshape(-1)          # (n*n*4,)
            cj = (j[..., None] + corners[:, 1]).reshape(-1)
            v = origin + g[ci, None] * a + g[cj, None] * b
            base = sum(x.shape[0] for x in verts)
            q = base + torch.arange(n * n)[:, None] * 4
            faces.append(torch.cat([q + torch.tensor([0, 1, 2]), q + torch.tensor([0, 2, 3])]))
            parity = ((i + j + k) % 2).reshape(-1).repeat_interleave(4)
            cols.append(col[parity])
            verts.append(v)
    return Mesh(verts=torch.cat(verts).float(), faces=torch.cat(faces), vert_colors=torch.cat(cols))


def nerf_scene() -> Mesh:
    """The built-in scene (world units, +Y up, inside [-0.8, 0.8]^3): a checker plinth, four
    thin poles (radius 0.03), a thin tilted ring (tube radius 0.025) and a gradient sphere."""
    plinth = checker_box((0.0, -0.55, 0.0), (1.2, 0.25, 1.2), 6, ((0.92, 0.55, 0.15), (0.95, 0.92, 0.82)))
    poles = [P.transformed(P.cylinder(0.03, 1.0, 12, color=c), translation=(x, -0.0, z))
             for (x, z), c in zip(((0.5, 0.5), (-0.5, 0.5), (-0.5, -0.5), (0.5, -0.5)),
                                  ((0.9, 0.1, 0.1), (0.1, 0.7, 0.2), (0.15, 0.3, 0.95), (0.95, 0.85, 0.1)))]
    ring = P.transformed(P.torus(0.45, 0.025, 48, 8, color=(0.7, 0.2, 0.8)),
                         rotation=euler_xyz((60.0, 0.0, 20.0), dtype=torch.float64), translation=(0.0, 0.2, 0.0))
    sphere = P.icosphere(3, 0.28)
    v = sphere.verts
    sphere = Mesh(verts=v + torch.tensor([0.0, -0.1, 0.0]), faces=sphere.faces,
                  vert_colors=(0.5 + 0.5 * v / 0.28).clamp(0, 1))
    return P.join([plinth] + poles + [ring, sphere])


def builtin_cameras(n_train: int, n_val: int, n_test: int, image_size: int, distance: float, fov: float,
                    elevation_range: Sequence[float] = (-10.0, 70.0)
                    ) -> Tuple[Cameras, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Cameras (train, then val, then test) looking at the origin, and the split indices.

    Train: Fibonacci spiral, elevation uniform in sin over ``elevation_range`` degrees
    (default [-10, 70]: the plinth's underside is never seen), golden-angle azimuths. Val: a
    ring at 45 degrees. Test: a ring at 20 degrees, azimuths offset by half a step from 0.
    """
    e_lo, e_hi = config_floats(elevation_range, "elevation_range", 2)
    if not -90.0 <= e_lo < e_hi <= 90.0:
        raise UserError(f"elevation_range must be [low, high] degrees with -90 <= low < high <= 90, "
                        f"got {list(elevation_range)}")
    k = torch.arange(n_train, dtype=torch.float64)
    lo, hi = math.sin(math.radians(e_lo)), math.sin(math.radians(e_hi))
    elev = torch.rad2deg(torch.asin(lo + (hi - lo) * (k + 0.5) / n_train))
    azim = torch.remainder(k * 137.50776405, 360.0)
    elev = torch.cat([elev, torch.full((n_val,), 45.0, dtype=torch.float64), torch.full((n_test,), 20.0, dtype=torch.float64)])
    azim = torch.cat([azim, torch.arange(n_val) * 360.0 / max(n_val, 1) + 10.0,
                      (torch.arange(n_test) + 0.5) * 360.0 / max(n_test, 1)])
    cams = look_at_cameras(distance, elev.float(), azim.float(), fov, image_size)
    idx = torch.arange(n_train + n_val + n_test)
    return cams, idx[:n_train], idx[n_train:n_train + n_val], idx[n_train + n_val:]


@DATASETS.register("nerf_builtin")
def nerf_builtin(image_size: int = 64, n_train: int = 100, n_val: int = 4, n_test: int = 8,
                 distance: float = 3.2, fov: float = 45.0, background="white", antialias: int = 2,
                 cache_dir: str = "outputs/.cache", scene_box: Sequence[Sequence[float]] = ((-0.75,) * 3, (0.75,) * 3),
                 elevation_range: Sequence[float] = (-10.0, 70.0), device=None) -> MultiViewData:
    """The built-in multi-view dataset (see the module docstring); cached in ``cache_dir``.

    ``image_size`` pixels square (64 default, 128 option); ``distance`` world units;
    ``fov`` degrees; ``antialias`` the mesh renderer's supersampling factor.
    """
    if int(image_size) < 8 or min(int(n_train), int(n_test)) < 1 or int(n_val) < 0:
        raise UserError(f"nerf_builtin needs image_size >= 8, n_train >= 1, n_test >= 1, "
                        f"got {image_size}, {n_train}, {n_test}")
    bg = background_rgb(background)
    box = scene_box_tensor(scene_box)                    # checked before any rendering
    elev = [float(e) for e in elevation_range]
    key = json.dumps([1, int(image_size), int(n_train), int(n_val), int(n_test), float(distance), float(fov),
                      bg.tolist(), int(antialias)] + ([] if elev == [-10.0, 70.0] else [elev]))
    path = resolve_path(cache_dir) / f"nerf_builtin_{hashlib.sha1(key.encode()).hexdigest()[:12]}.pt"
    cams, tr, va, te = builtin_cameras(int(n_train), int(n_val), int(n_test), int(image_size), float(distance),
                                       float(fov), elev)
    if path.exists():
        images = torch.load(path, map_location="cpu", weights_only=True)["images"]
    else:
        from l3d_app.render.mesh.renderer import MeshRenderer

        renderer = MeshRenderer(shading="lambert", background=tuple(bg.tolist()), ambient=0.45, diffuse=0.55,
                                specular=0.0, light_direction=(0.4, 1.0, 0.6), antialias=int(antialias))
        mesh = nerf_scene()
        with torch.no_grad():
            images = torch.cat([renderer(mesh, cams[s:s + 16])["image"] for s in range(0, len(cams), 16)])
        path.parent.mkdir(parents=True, exist_ok=True)
        with atomic_path(path) as tmp:
            torch.save({"images": images.contiguous(), "key": key}, tmp)
    data = MultiViewData(images.float(), cams, tr, va, te, bg, box, name="nerf_builtin", mesh=nerf_scene(),
                         up=torch.tensor([0.0, 1.0, 0.0]))
    return data if device is None else data.to(device)
