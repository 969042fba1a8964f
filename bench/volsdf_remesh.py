"""A finished volsdf run's mesh re-extracted at other marching-cubes resolutions and scored like the benchmark.

    python bench/volsdf_remesh.py RUN_DIR SCENE_DIR [--resolutions 128 192 256]

For each resolution: marching cubes of the run's SDF (its checkpoint) over the scene box, culled to
what the training cameras see (as volsdf does), written to ``RUN_DIR/remesh/mesh<R>.ply`` and scored
against ``SCENE_DIR/mesh.ply`` with ``bench_scenes.mesh_scores`` (chamfer whole / observed, % of the
diagonal; F1@0.02 / 0.05 observed; phantom %), with the seconds of extraction + culling. Use on
development scenes: it tells whether the mesh's resolution or the field limits the surface scores.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

from volsdf_run import load_sdf_field, run_scene_parser

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))  # run from a checkout without installing


def main() -> None:
    ap = run_scene_parser(__doc__)
    ap.add_argument("--resolutions", type=int, nargs="+", default=[128, 192, 256])
    args = ap.parse_args()
    import torch
    from bench_scenes import mesh_scores
    from l3d_app.render.field_mesh import extract_mesh, save_field_mesh
    from l3d_app.tasks.field_common import cull_to_training_views

    torch.set_num_threads(args.threads)
    _, data, model = load_sdf_field(args.run, args.scene)
    box = data.scene_box.tolist()
    out = args.run / "remesh"
    out.mkdir(exist_ok=True)
    for res in args.resolutions:
        t0 = time.perf_counter()
        with torch.no_grad():
            mesh = extract_mesh(model.sdf, box, res, 0.0, device="cpu")
            if mesh is None:
                raise SystemExit(f"{args.run}: the SDF has no zero level set in the box")
            mesh, _ = cull_to_training_views(mesh, data, box, res)
        seconds = time.perf_counter() - t0
        save_field_mesh(mesh, out / f"mesh{res}", ["ply"])
        s = mesh_scores(out / f"mesh{res}.ply", args.scene)
        print(f"{args.run.name} at {res}: chamfer {s['chamfer_pct']:.3f}% (observed {s['chamfer_obs_pct']:.3f}%), "
              f"F1@0.02 obs {s['f1_02_obs']:.3f}, F1@0.05 obs {s['f1_05_obs']:.3f}, phantom {s['phantom_pct']:.2f}%, "
              f"{seconds:.1f} s, {mesh.num_faces} faces", flush=True)


if __name__ == "__main__":
    main()
