"""How far a run's mesh lies inside or outside `dev`'s curved and flat surfaces (VolSDF's grazing-ray shrink).

    python bench/diagnose_shrink.py MESH.ply [MESH.ply ...] [--samples 50000]

For meshes of the development scene ``dev`` (its primitives' positions are written in, as
``bench/make_scenes.py`` builds them): area-uniform samples of the mesh, then the median signed
offset (world units; < 0: inside, the surface shrunk) of the samples near the sphere (radius 0.45,
radial offset), near the cylinder's side (radius 0.2) and near the box's x-facing sides (0.3 from its
centre). A diagnosis aid; it chooses nothing.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

SPHERE, SPHERE_R = np.array([-0.45, -0.3, 0.0]), 0.45
CYLINDER, CYLINDER_R = np.array([0.45, -0.55, 0.0]), 0.2
BOX, BOX_HALF = np.array([0.5, 0.35, -0.15]), 0.3


def offsets(points: np.ndarray) -> dict:
    """Median signed offsets (world units) of (N, 3) surface samples from dev's sphere, cylinder, box sides."""
    r = np.linalg.norm(points - SPHERE, axis=1)
    sphere = r[(r > SPHERE_R - 0.1) & (r < SPHERE_R + 0.1)] - SPHERE_R
    c = points - CYLINDER
    rc = np.hypot(c[:, 0], c[:, 1])
    cyl = rc[(np.abs(c[:, 2]) < 0.3) & (rc > CYLINDER_R - 0.1) & (rc < CYLINDER_R + 0.1)] - CYLINDER_R
    q = points - BOX
    side = (np.abs(q[:, 1]) < 0.2) & (np.abs(q[:, 2]) < 0.2) & (np.abs(np.abs(q[:, 0]) - BOX_HALF) < 0.06)
    box = np.abs(q[side, 0]) - BOX_HALF
    return {name: (float(np.median(v)) if len(v) else float("nan"), len(v))
            for name, v in (("sphere", sphere), ("cylinder", cyl), ("box sides", box))}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("meshes", type=Path, nargs="+")
    ap.add_argument("--samples", type=int, default=50000)
    args = ap.parse_args()
    import trimesh

    for path in args.meshes:
        if not path.is_file():
            raise SystemExit(f"{path}: no such mesh")
        mesh = trimesh.load(path, process=False)
        points, _ = trimesh.sample.sample_surface(mesh, args.samples, seed=0)
        got = offsets(np.asarray(points))
        print(f"{path}: " + "; ".join(f"{k} {v:+.4f} ({n} samples)" for k, (v, n) in got.items()))


if __name__ == "__main__":
    main()
