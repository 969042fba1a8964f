"""Benchmark: hard rasteriser + Phong + UV texture on the course cow, turntable views.

    python bench/bench_mesh_render.py [--sizes 256 512] [--views 30] [--threads 2]

Prints frames/s and the per-frame split (transform, rasterise, shade) per image size.
Falls back to an icosphere of similar face count when the cow is absent.
Reference point: PyTorch3D's compiled CPU renderer takes ~1.06 s/frame for this scene.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run from a checkout

from l3d_app.geometry.cameras import Cameras, look_at
from l3d_app.geometry.mesh import Mesh
from l3d_app.render.mesh.renderer import MeshRenderer

COW = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "cow" / "cow.obj"


def load_scene() -> tuple:
    """(mesh, description): the textured cow, or a grey icosphere when it is absent."""
    if COW.exists():
        try:
            from l3d_app.geometry.mesh_io import load_mesh
            mesh = load_mesh(COW)
        except ImportError:  # mesh_io not available: trimesh directly (UVs per vertex)
            import trimesh
            tm = trimesh.load(COW, process=False, maintain_order=True, force="mesh")
            faces = torch.as_tensor(tm.faces, dtype=torch.long)
            image = np.asarray(tm.visual.material.image.convert("RGB"))
            tex = torch.as_tensor(image, dtype=torch.float32) / 255
            mesh = Mesh(torch.as_tensor(tm.vertices, dtype=torch.float32), faces,
                        verts_uvs=torch.as_tensor(tm.visual.uv, dtype=torch.float32),
                        faces_uvs=faces, texture=tex)
        return mesh, (f"cow ({mesh.num_verts} verts, {mesh.num_faces} faces, "
                      f"texture {tuple(mesh.texture.shape)})")
    mesh = _icosphere(4)  # 5120 faces, about the cow's 5856
    return mesh, f"icosphere fallback ({mesh.num_verts} verts, {mesh.num_faces} faces)"


def _icosphere(level: int) -> Mesh:
    t = (1 + 5 ** 0.5) / 2
    v = torch.tensor([[-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0], [0, -1, t], [0, 1, t],
                      [0, -1, -t], [0, 1, -t], [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1]])
    f = torch.tensor([[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9],
                      [5, 11, 4], [11, 10, 2], [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2],
                      [3, 2, 6], [3, 6, 8], [3, 8, 9], [4, 9, 5], [2, 4, 11], [6, 2, 10],
                      [8, 6, 7], [9, 8, 1]])
    v = torch.nn.functional.normalize(v.float(), dim=-1)
    for _ in range(level):
        e = torch.cat([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]).sort(dim=1).values
        uniq, inv = torch.unique(e, dim=0, return_inverse=True)
        mid = torch.nn.functional.normalize(v[uniq].mean(1), dim=-1)
        m = inv.reshape(3, -1).T + v.shape[0]
        v = torch.cat([v, mid])
        f = torch.cat([torch.stack([f[:, 0], m[:, 0], m[:, 2]], 1),
                       torch.stack([f[:, 1], m[:, 1], m[:, 0]], 1),
                       torch.stack([f[:, 2], m[:, 2], m[:, 1]], 1), m])
    return Mesh(v, f)


def turntable(n: int, size: int) -> Cameras:
    azim = torch.arange(n, dtype=torch.float32) * (360.0 / n)
    R, t = look_at(2.7, 15.0, azim)
    return Cameras.from_fov(R, t, 50.0, size, size)


def bench(renderer, mesh, cams, reps: int, batch: int = 1) -> dict:
    """Render every view once per repetition, ``batch`` views per call; the figures of the
    median repetition (frames/s) and of the best one."""
    n = len(cams)
    for i in range(0, min(n, 5 * batch), batch):  # warm-up
        renderer(mesh, cams[i:i + batch])
    fps, splits = [], []
    for _ in range(reps):
        acc = {"transform": 0.0, "rasterize": 0.0, "shade": 0.0}
        start = time.perf_counter()
        for i in range(0, n, batch):
            out = renderer(mesh, cams[i:i + batch], return_timings=True)
            for k, v in out["timings"].items():
                acc[k] += v / n
        fps.append(n / (time.perf_counter() - start))
        splits.append(acc)
    best = max(range(reps), key=lambda r: fps[r])
    med = sorted(range(reps), key=lambda r: fps[r])[reps // 2]
    return {"fps_median": fps[med], "fps_best": fps[best], "split": splits[med],
            "coverage": float(out["alpha"].mean())}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[256, 512])
    ap.add_argument("--views", type=int, default=30)
    ap.add_argument("--reps", type=int, default=5)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--shading", default="phong")
    ap.add_argument("--antialias", type=int, default=1)
    ap.add_argument("--batch", type=int, default=1, help="views per renderer call")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    mesh, what = load_scene()
    renderer = MeshRenderer(shading=args.shading, antialias=args.antialias)
    print(f"scene: {what}; shading={args.shading}, antialias={args.antialias}, "
          f"batch={args.batch}, threads={torch.get_num_threads()}, torch {torch.__version__}")
    with torch.inference_mode():
        for size in args.sizes:
            r = bench(renderer, mesh, turntable(args.views, size), args.reps, args.batch)
            split = ", ".join(f"{k} {v * 1e3:.2f} ms" for k, v in r["split"].items())
            print(f"{size}x{size}: {r['fps_median']:.1f} frames/s median ({r['fps_best']:.1f} best "
                  f"of {args.reps} x {args.views} views); per frame: {split}; "
                  f"coverage {r['coverage']:.3f}")


if __name__ == "__main__":
    main()
