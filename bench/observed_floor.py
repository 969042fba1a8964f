"""The observed-truth floor of the benchmark's surface scores: what a perfect mesh that leaves
unseen space empty scores on each scene.

    python bench/observed_floor.py [--root outputs/.cache/bench_scenes] [--scenes dev ground ...] [--threads 2]

Each scene's TRUE mesh is cut to the faces some training camera sees
(:func:`l3d_app.render.mesh.visibility.cull_unseen_faces`, the culling volsdf applies to its own meshes
with ``mesh_cull=true``, here at the surface metrics' depth tolerance 0.01) and scored as a method's mesh
is (``bench_scenes.scores_of_mesh``); printed: the true area cut (%), whole-surface chamfer (% of the diagonal),
F1@0.05 whole, F1@0.02 observed, phantom area (%). The observed scores are ~perfect by construction; the
whole-surface chamfer is what the unseen truth (a plate's underside, a tray's outer bottom) costs a
mesh that does not guess it, so no such mesh scores below it. Reads the truth and the cameras only:
no method runs and nothing is tuned by it (a property of the scene and the metric, as the tables'
observed fraction is).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))  # run from a checkout without installing
sys.path.insert(0, str(REPO / "bench"))  # its sibling bench_scenes, also when loaded as a module by the tests

from bench_scenes import DEFAULT_SCENES, scores_of_mesh  # noqa: E402


TOLERANCE = 0.01
"""World units: the surface metrics' own depth tolerance (``surface_scores``), not tuned."""


def observed_truth(truth, cameras):
    """``truth`` (a Mesh) without the faces none of ``cameras`` sees, and the share of its area cut (0..1)."""
    from l3d_app.render.mesh.visibility import cull_unseen_faces

    return cull_unseen_faces(truth, cameras, tolerance=TOLERANCE)


def floor_row(scene: Path) -> dict:
    """The scores of ``scene``'s observed true faces, the area share cut and the seconds taken."""
    from l3d_app.data.nerf_formats import blender
    from l3d_app.geometry.mesh_io import load_mesh

    t0 = time.perf_counter()
    truth = load_mesh(str(scene / "mesh.ply"))
    data = blender(root=str(scene), background="white")
    seen, cut = observed_truth(truth, data.cameras[data.train])
    return {"scene": scene.name, "cut_pct": 100 * cut, **scores_of_mesh(seen, scene),
            "seconds": time.perf_counter() - t0}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--root", type=Path, default=DEFAULT_SCENES)
    ap.add_argument("--scenes", nargs="+", default=None, help="scene folder names (default: all under --root)")
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()
    import torch

    torch.set_num_threads(args.threads)
    found = sorted(p.name for p in args.root.iterdir() if (p / "scene.json").is_file()) if args.root.is_dir() else []
    names = args.scenes or found
    missing = [n for n in names if not (args.root / n / "mesh.ply").is_file()]
    if missing or not names:      # one line, exit 2, as main.py's usage errors
        print(f"observed_floor: no scene {', '.join(missing) or 'at all'} under {args.root}: run python "
              f"bench/make_scenes.py first", file=sys.stderr)
        sys.exit(2)
    print("| scene | true area cut (unseen) % | chamfer % whole | F1@0.05 whole | F1@0.02 obs | phantom % | s |")
    print("|---|---|---|---|---|---|---|")
    for name in names:
        r = floor_row(args.root / name)
        print(f"| {name} | {r['cut_pct']:.1f} | {r['chamfer_pct']:.3f} | {r['f1_05']:.3f} | {r['f1_02_obs']:.3f} | "
              f"{r['phantom_pct']:.2f} | {r['seconds']:.0f} |", flush=True)


if __name__ == "__main__":
    main()
