"""Photo captures that look like a person's: rendered by a renderer this project did not write (Mitsuba 3).

    pip install -e ".[bench]"                        # mitsuba (CPU variant scalar_rgb)
    python bench/make_capture.py [--out DIR] [--only NAME ...] [--spp 12] [--views 56]

Each scene is a room (textured floor, four textured walls, no ceiling: sky light and a sun
come in from above) with a table in the middle and objects on it. The camera is held at a
person's eye height (1.40-1.65 m) by someone walking once around the table at 1.2-1.6 m from
its centre, aiming at the objects with a hand's wobble (the aim point, the height and the
distance jitter per photo; a little roll). Images are JPEG (quality 95), 640 x 480, with no
alpha, no masks and no camera poses beside them: ``DIR/<name>/images/``. The true cameras go
to ``DIR/<name>/truth.json`` (OpenGL camera-to-world, +Z up, metres) for diagnosis only;
the app never reads them.

==========  =============================================================  ============
name        on the table                                                   role
==========  =============================================================  ============
desk        a banded vase, a book, a ball and a mug                        DEVELOPMENT
shelf       a torus knot on a stand, stacked boxes, a cone and a bowl      held out
==========  =============================================================  ============

Only ``desk`` may be looked at to choose a setting (SfM thresholds, training knobs).
``shelf`` is read once, for the figures in ``docs/measured/capture.md``.
The default folder is ``outputs/.cache/captures`` (outside git); existing scenes are kept
unless ``--force``.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path
from typing import Dict, List

import numpy as np

BENCH = Path(__file__).resolve().parent
sys.path.insert(0, str(BENCH))
from make_scenes import (_bands, _checks, _colour, _fine, _mitsuba, _place, _revolve, _solid, _stripes,  # noqa: E402
                         _trimesh, _tube, look_at_c2w_opengl, sensor_dict, write_float_colour_ply)

REPO = BENCH.parent
DEFAULT_OUT = REPO / "outputs" / ".cache" / "captures"
WIDTH, HEIGHT, FOV_X_DEG = 640, 480, 62.0
TABLE_TOP = 0.75


# ----------------------------------------------------------------------------- textures
def _noise(rng: np.random.Generator, h: int, w: int, octaves: int = 5) -> np.ndarray:
    """(h, w) smooth value noise in [0, 1] (sum of upsampled random grids)."""
    out = np.zeros((h, w))
    for o in range(octaves):
        n = 4 * 2 ** o
        g = rng.random((n + 1, n + 1))
        y, x = np.linspace(0, n, h, endpoint=False), np.linspace(0, n, w, endpoint=False)
        y0, x0 = y.astype(int), x.astype(int)
        fy, fx = (y - y0)[:, None], (x - x0)[None, :]
        v = (g[y0][:, x0] * (1 - fy) * (1 - fx) + g[y0 + 1][:, x0] * fy * (1 - fx)
             + g[y0][:, x0 + 1] * (1 - fy) * fx + g[y0 + 1][:, x0 + 1] * fy * fx)
        out += v / 2 ** o
    return (out - out.min()) / (out.max() - out.min() + 1e-9)


def texture_floor(rng, size: int = 1024) -> np.ndarray:
    """Wooden planks: stripes of varying tone with grain noise and dark seams (sRGB uint8)."""
    planks = 10
    tone = rng.uniform(0.55, 1.0, planks)[(np.arange(size) * planks // size)]
    grain = _noise(rng, size, size, 6)
    base = np.array([0.55, 0.36, 0.2])
    img = base[None, None] * (0.6 + 0.4 * grain[..., None]) * tone[None, :, None]
    seam = (np.arange(size) % (size // planks)) < 3
    img[:, seam] *= 0.35
    offs = rng.integers(0, size, planks)            # plank ends at staggered places
    for p in range(planks):
        cols = slice(p * size // planks, (p + 1) * size // planks)
        for k in range(2):
            r = (offs[p] + k * size // 2) % size
            img[max(r - 2, 0):r + 2, cols] *= 0.35
    return (np.clip(img, 0, 1) * 255).astype(np.uint8)


def texture_wall(rng, size: int = 1024) -> np.ndarray:
    """Wallpaper: a pale base with a repeating motif, blotches, and a few framed pictures."""
    y, x = np.mgrid[0:size, 0:size] / size
    base = np.array(rng.uniform(0.6, 0.85, 3))
    motif = 0.5 + 0.5 * np.sin(2 * math.pi * 14 * x) * np.sin(2 * math.pi * 9 * y + 2 * np.sin(2 * math.pi * 5 * x))
    img = base[None, None] * (0.8 + 0.2 * motif[..., None]) * (0.85 + 0.15 * _noise(rng, size, size)[..., None])
    for _ in range(4):                           # pictures: noisy colour fields in a dark frame
        w, h = rng.uniform(0.12, 0.25), rng.uniform(0.1, 0.2)
        x0, y0 = rng.uniform(0.05, 0.9 - w), rng.uniform(0.15, 0.5)
        a, b = (int(x0 * size), int((x0 + w) * size)), (int(y0 * size), int((y0 + h) * size))
        img[b[0]:b[1], a[0]:a[1]] = 0.1
        pic = _noise(rng, b[1] - b[0] - 12, a[1] - a[0] - 12, 4)[..., None] * rng.uniform(0.2, 1.0, 3) \
            + (1 - _noise(rng, b[1] - b[0] - 12, a[1] - a[0] - 12, 3)[..., None]) * rng.uniform(0.2, 1.0, 3)
        img[b[0] + 6:b[1] - 6, a[0] + 6:a[1] - 6] = np.clip(pic * 0.7, 0, 1)
    img[int(0.9 * size):] *= 0.5                 # a skirting board at the bottom
    return (np.clip(img, 0, 1) * 255).astype(np.uint8)


def texture_table(rng, size: int = 512) -> np.ndarray:
    """A table cloth: a two-colour check with woven noise (sRGB uint8)."""
    y, x = np.mgrid[0:size, 0:size] / size
    c1, c2 = rng.uniform(0.3, 0.9, 3), rng.uniform(0.3, 0.9, 3)
    check = ((np.floor(x * 12) + np.floor(y * 8)) % 2)[..., None]
    img = c1 * check + c2 * (1 - check)
    img = img * (0.75 + 0.25 * _noise(rng, size, size, 6)[..., None])
    return (np.clip(img, 0, 1) * 255).astype(np.uint8)


def texture_label(rng, size: int = 256) -> np.ndarray:
    """A book cover / box label: blocks of colour and stripes."""
    img = np.ones((size, size, 3)) * rng.uniform(0.2, 0.9, 3)
    for _ in range(8):
        a, b = sorted(rng.integers(0, size, 2)), sorted(rng.integers(0, size, 2))
        img[a[0]:a[1] + 4, b[0]:b[1] + 4] = rng.uniform(0.05, 1.0, 3)
    img *= 0.8 + 0.2 * _noise(rng, size, size, 4)[..., None]
    return (np.clip(img, 0, 1) * 255).astype(np.uint8)


# ----------------------------------------------------------------------------- scenes
def _room_parts(rng) -> List[dict]:
    """Floor (6 x 6 m), four walls 2.6 m high, the table (top 1.2 x 0.8 m at 0.75 m, four legs)."""
    return [
        {"kind": "rect", "tex": texture_floor(rng), "to_world": _rect(6.0, 6.0, (0, 0, 0), "z"), "name": "floor"},
        *[{"kind": "rect", "tex": texture_wall(rng), "to_world": _rect(6.0, 2.6, c, axis), "name": f"wall{k}"}
          for k, (c, axis) in enumerate((((0, 3, 1.3), "-y"), ((0, -3, 1.3), "+y"), ((3, 0, 1.3), "-x"),
                                          ((-3, 0, 1.3), "+x")))],
        {"kind": "cube", "tex": texture_table(rng), "to_world": _box((0, 0, TABLE_TOP - 0.02), (1.2, 0.8, 0.04)),
         "name": "tabletop"},
        *[{"kind": "cube", "rgb": (0.25, 0.15, 0.08), "to_world": _box((sx * 0.55, sy * 0.35, (TABLE_TOP - 0.04) / 2),
                                                                         (0.05, 0.05, TABLE_TOP - 0.04)), "name": f"leg{k}"}
          for k, (sx, sy) in enumerate(((1, 1), (1, -1), (-1, 1), (-1, -1)))],
    ]


def _rect(width: float, height: float, centre, facing: str) -> np.ndarray:
    """4x4 to_world of Mitsuba's rectangle ([-1, 1]^2 in z=0, normal +z) scaled and turned to face ``facing``."""
    S = np.diag([width / 2, height / 2, 1.0, 1.0])
    turn = {"z": np.eye(3),
            "-y": np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0]], float),     # local +y -> world +z, normal -> -y
            "+y": np.array([[-1, 0, 0], [0, 0, 1], [0, 1, 0]], float),
            "-x": np.array([[0, 0, -1], [-1, 0, 0], [0, 1, 0]], float),
            "+x": np.array([[0, 0, 1], [1, 0, 0], [0, 1, 0]], float)}[facing]
    M = np.eye(4)
    M[:3, :3] = turn
    M[:3, 3] = centre
    return M @ S


def _box(centre, size) -> np.ndarray:
    """4x4 to_world of Mitsuba's cube ([-1, 1]^3) with side lengths ``size`` at ``centre``."""
    M = np.diag([size[0] / 2, size[1] / 2, size[2] / 2, 1.0])
    M[:3, 3] = centre
    return M


def _on_table(mesh, xy, lift: float = 0.0):
    """Place a trimesh (its lowest point) on the table top at (x, y)."""
    z0 = float(mesh.bounds[0][2])
    return _place(mesh, (xy[0], xy[1], TABLE_TOP - z0 + lift))


def scene_desk(rng) -> List[dict]:
    t = _trimesh().creation
    prof = np.array([[0.0, 0.0], [0.07, 0.0], [0.09, 0.06], [0.06, 0.16], [0.035, 0.22], [0.05, 0.27], [0.0, 0.27]])
    vase = _colour(_on_table(_fine(_revolve(prof, 64), 0.01), (-0.25, 0.08)),
                   _bands((0.8, 0.2, 0.15), (0.95, 0.85, 0.3), (0.15, 0.35, 0.75)))
    ball = _colour(_on_table(t.icosphere(4, radius=0.08), (0.22, 0.18)),
                   _checks(0.04, (0.9, 0.9, 0.85), (0.1, 0.45, 0.2)))
    mug = _revolve(np.array([[0.05, 0.0], [0.055, 0.0], [0.055, 0.11], [0.05, 0.11], [0.05, 0.0]]), 64)
    mug = _colour(_on_table(_fine(mug, 0.01), (0.05, -0.2)), _stripes(2, 0.03, (0.9, 0.6, 0.1), (0.95, 0.95, 0.95)))
    handle = _colour(_fine(_tube(np.stack([0.105 + 0.035 * np.cos(a := np.linspace(0, 2 * np.pi, 32, endpoint=False)),
                                           np.zeros(32) - 0.2, TABLE_TOP + 0.055 + 0.035 * np.sin(a)], 1), 0.008, 10),
                           0.01), _solid((0.9, 0.6, 0.1)))
    return [*_room_parts(rng),
            {"kind": "cube", "tex": texture_label(rng), "to_world": _box((0.3, -0.12, TABLE_TOP + 0.025), (0.22, 0.3, 0.05)),
             "name": "book"},
            {"kind": "mesh", "mesh": vase, "glossy": True, "name": "vase"},
            {"kind": "mesh", "mesh": ball, "name": "ball"},
            {"kind": "mesh", "mesh": mug, "name": "mug"},
            {"kind": "mesh", "mesh": handle, "name": "handle"}]


def scene_shelf(rng) -> List[dict]:
    t = _trimesh().creation
    s = np.linspace(0, 2 * np.pi, 240, endpoint=False)
    knot = np.stack([(2 + np.cos(3 * s)) * np.cos(2 * s), (2 + np.cos(3 * s)) * np.sin(2 * s), np.sin(3 * s)], 1) * 0.045
    knot = _colour(_fine(_tube(knot, 0.018, 12), 0.01), _bands((0.2, 0.6, 0.85), (0.95, 0.3, 0.4), (0.95, 0.9, 0.3)))
    knot = _on_table(knot, (-0.2, 0.05), lift=0.12)
    stand = _colour(_on_table(_fine(t.cylinder(0.012, 0.13, sections=16), 0.01), (-0.2, 0.05)), _solid((0.3, 0.3, 0.3)))
    base = _colour(_on_table(_fine(t.cylinder(0.07, 0.015, sections=48), 0.01), (-0.2, 0.05)), _solid((0.15, 0.15, 0.15)))
    cone = _colour(_on_table(_fine(t.cone(0.07, 0.2, sections=48), 0.01), (0.3, 0.2)),
                   _stripes(2, 0.025, (0.95, 0.5, 0.1), (0.2, 0.2, 0.25)))
    bowl = _revolve(np.array([[0.0, 0.0], [0.05, 0.0], [0.1, 0.06], [0.095, 0.062], [0.045, 0.008], [0.0, 0.008]]), 64)
    bowl = _colour(_on_table(_fine(bowl, 0.01), (0.12, -0.22)), _checks(0.03, (0.85, 0.85, 0.9), (0.55, 0.2, 0.6)))
    return [*_room_parts(rng),
            {"kind": "cube", "tex": texture_label(rng), "to_world": _box((0.3, -0.05, TABLE_TOP + 0.04), (0.18, 0.14, 0.08)),
             "name": "box1"},
            {"kind": "cube", "tex": texture_label(rng), "to_world": _box((0.31, -0.06, TABLE_TOP + 0.115), (0.12, 0.1, 0.07)),
             "name": "box2"},
            {"kind": "mesh", "mesh": knot, "glossy": True, "name": "knot"},
            {"kind": "mesh", "mesh": stand, "name": "stand"},
            {"kind": "mesh", "mesh": base, "name": "base"},
            {"kind": "mesh", "mesh": cone, "name": "cone"},
            {"kind": "mesh", "mesh": bowl, "name": "bowl"}]


SCENES = {"desk": {"build": scene_desk, "role": "DEVELOPMENT", "seed": 11, "target": (0.0, 0.0, TABLE_TOP + 0.1)},
          "shelf": {"build": scene_shelf, "role": "held out", "seed": 23, "target": (0.0, 0.0, TABLE_TOP + 0.1)}}


# ----------------------------------------------------------------------------- cameras and rendering
def walk_cameras(n: int, rng, target) -> np.ndarray:
    """(n, 4, 4) OpenGL camera-to-world: one loop around the table at eye height, hand-held wobble."""
    az = np.linspace(0, 2 * np.pi, n, endpoint=False) + rng.uniform(-0.03, 0.03, n)
    dist = 1.4 + rng.uniform(-0.2, 0.2, n)
    height = rng.uniform(1.40, 1.65, n)
    out = []
    for a, d, h in zip(az, dist, height):
        eye = np.array([d * np.cos(a), d * np.sin(a), h])
        aim = np.asarray(target) + rng.normal(0.0, 0.06, 3)
        c2w = look_at_c2w_opengl(eye, aim)
        roll = math.radians(rng.normal(0.0, 2.0))
        R = np.array([[math.cos(roll), -math.sin(roll), 0], [math.sin(roll), math.cos(roll), 0], [0, 0, 1]])
        c2w[:3, :3] = c2w[:3, :3] @ R
        out.append(c2w)
    return np.stack(out)


def build_scene_dict(mi, parts: List[dict], folder: Path) -> dict:
    import imageio.v2 as imageio

    scene = {"type": "scene",
             "integrator": {"type": "path", "max_depth": 3},
             "sky": {"type": "constant", "radiance": {"type": "rgb", "value": 0.9}},
             "sun": {"type": "directional", "direction": [-0.3, 0.45, -1.0], "irradiance": {"type": "rgb", "value": 2.5}}}
    for i, p in enumerate(parts):
        if "tex" in p:
            tex_path = folder / f"{p['name']}.png"
            imageio.imwrite(tex_path, p["tex"])
            refl = {"type": "bitmap", "filename": str(tex_path), "filter_type": "bilinear"}
        elif "rgb" in p:
            refl = {"type": "rgb", "value": list(p["rgb"])}
        else:
            refl = {"type": "mesh_attribute", "name": "vertex_color"}
        bsdf = {"type": "diffuse", "reflectance": refl}
        if p.get("glossy"):
            bsdf = {"type": "blendbsdf", "weight": 0.15, "bsdf_0": bsdf,
                    "bsdf_1": {"type": "roughconductor", "material": "none", "alpha": 0.15}}
        bsdf = {"type": "twosided", "bsdf": bsdf}
        if p["kind"] == "mesh":
            path = folder / f"{p['name']}.ply"
            m = p["mesh"]
            write_float_colour_ply(path, m.vertices, m.faces, m.metadata["rgb"])
            scene[p["name"]] = {"type": "ply", "filename": str(path), "face_normals": True, "bsdf": bsdf}
        else:
            scene[p["name"]] = {"type": "rectangle" if p["kind"] == "rect" else "cube",
                                "to_world": mi.ScalarTransform4f(p["to_world"].tolist()), "bsdf": bsdf}
    return scene


def sensor(mi, c2w_gl: np.ndarray, spp: int) -> dict:
    """The capture's camera: WIDTH x HEIGHT RGB film, Gaussian pixel filter, multi-jittered samples."""
    return sensor_dict(mi, c2w_gl, WIDTH, spp, height=HEIGHT, fov_x_deg=FOV_X_DEG, pixel_format="rgb",
                       rfilter="gaussian", sampler="multijitter")


def to_srgb8(img: np.ndarray, exposure: float) -> np.ndarray:
    rgb = np.clip(img[..., :3] * exposure, 0.0, 1.0)
    srgb = np.where(rgb <= 0.0031308, 12.92 * rgb, 1.055 * np.power(rgb, 1 / 2.4) - 0.055)
    return np.round(srgb * 255.0).astype(np.uint8)


def make_capture(name: str, out: Path, spp: int, views: int) -> Path:
    import imageio.v2 as imageio

    mi = _mitsuba("make_capture")
    spec = SCENES[name]
    rng = np.random.default_rng(spec["seed"])
    folder = out / name
    assets = folder / "assets"
    (folder / "images").mkdir(parents=True, exist_ok=True)
    assets.mkdir(exist_ok=True)
    scene_dict = build_scene_dict(mi, spec["build"](rng), assets)
    c2ws = walk_cameras(views, rng, spec["target"])
    t0 = time.perf_counter()
    scene = mi.load_dict(scene_dict)
    exposure = None
    for k, c2w in enumerate(c2ws):
        img = np.array(mi.render(scene, sensor=mi.load_dict(sensor(mi, c2w, spp)), seed=k), dtype=np.float32)
        if exposure is None:          # one exposure for the whole capture (a phone's locked exposure)
            exposure = 0.8 / max(float(np.percentile(img, 99)), 1e-6)
        imageio.imwrite(folder / "images" / f"IMG_{1000 + k:04d}.jpg", to_srgb8(img, exposure), quality=95)
        print(f"{name}: view {k + 1}/{views} ({time.perf_counter() - t0:.0f} s)", flush=True)
    info = {"name": name, "role": spec["role"], "views": views, "width": WIDTH, "height": HEIGHT,
            "fov_x_deg": FOV_X_DEG, "spp": spp, "exposure": exposure, "up": [0.0, 0.0, 1.0],
            "mitsuba": mi.__version__, "variant": "scalar_rgb", "render_seconds": round(time.perf_counter() - t0, 1),
            "camera_to_world_opengl": [c.tolist() for c in c2ws],
            "names": [f"IMG_{1000 + k:04d}.jpg" for k in range(views)]}
    (folder / "truth.json").write_text(json.dumps(info, indent=1))
    return folder


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT)
    ap.add_argument("--only", nargs="*", default=None, help=f"scene names (default: all of {', '.join(SCENES)})")
    ap.add_argument("--spp", type=int, default=12, help="samples per pixel")
    ap.add_argument("--views", type=int, default=56, help="photos per capture (40-80)")
    ap.add_argument("--force", action="store_true", help="re-render existing captures")
    args = ap.parse_args()
    for name in args.only or list(SCENES):
        if name not in SCENES:
            raise SystemExit(f"unknown capture '{name}'; known: {', '.join(SCENES)}")
        folder = args.out / name
        if args.force or not (folder / "truth.json").is_file():
            t0 = time.perf_counter()
            make_capture(name, args.out, args.spp, args.views)
            print(f"{name}: rendered in {time.perf_counter() - t0:.0f} s -> {folder / 'images'}", flush=True)
        else:
            print(f"{name}: cached at {folder / 'images'}")


if __name__ == "__main__":
    main()
