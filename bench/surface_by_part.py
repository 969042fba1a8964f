"""Where a reconstructed surface is wrong, per object of a bench scene: the benchmark's surface
figures split by the scene's true parts (``parts/*.ply``, written by ``bench/make_scenes.py``).

    python bench/surface_by_part.py MESH --scene outputs/.cache/bench_scenes/SCENE [--samples 20000] [--seed 0]

``MESH``: a run's extracted surface (``mesh.ply`` of a volsdf run, ``mesh*.ply`` of train_nerf's).
``--samples`` area-uniform samples are drawn on the true mesh and on ``MESH``; each is assigned to the
true part nearest it (exact point-to-mesh distances, :func:`nearest_part`).
Per part (world units):

- ``truth_to_mesh``: the mean distance from the part's true samples to ``MESH`` (completeness);
- ``truth_far``: the share of the part's true samples farther than ``--near`` (0.02) from ``MESH``;
- ``mesh_share``: the share of ``MESH``'s area whose nearest true part is this one;
- ``mesh_to_truth``: the mean distance from those samples to the true mesh (accuracy);
- ``phantom``: the share of those samples farther than ``--far`` (0.05) from the true mesh.

Whole-surface figures are over all samples (not per-part means). A diagnosis aid: it chooses nothing.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Dict, List, Sequence

import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))  # run from a checkout without installing


def scores_by_part(pred, truth, parts: Sequence, samples: int = 20000, seed: int = 0,
                   near: float = 0.02, far: float = 0.05) -> List[Dict[str, float]]:
    """One dict per entry of ``parts`` (loaded ``Mesh`` objects whose union is ``truth``), then one
    for the whole surface (``part`` = "all"), with the keys of the module docstring. ``pred`` and
    ``truth`` are ``Mesh`` objects; ``samples`` area-uniform samples of each (one generator seeded
    with ``seed``). A part with no samples of one kind gets NaN for that kind's figures."""
    from l3d_app.geometry.point_mesh_distance import point_mesh_distance
    from l3d_app.geometry.sampling import sample_surface

    pred, truth = pred.to("cpu"), truth.to("cpu")
    gen = torch.Generator().manual_seed(int(seed))
    g = sample_surface(truth, int(samples), generator=gen).points.double()
    p = sample_surface(pred, int(samples), generator=gen).points.double()
    comp = point_mesh_distance(g, pred).distance       # (S,) true sample -> predicted mesh
    acc = point_mesh_distance(p, truth).distance       # (S,) predicted sample -> true mesh
    g_part, p_part = nearest_part(g, parts), nearest_part(p, parts)
    rows = [_row(str(k), comp[g_part == k], acc[p_part == k], len(p), near, far) for k in range(len(parts))]
    return rows + [_row("all", comp, acc, len(p), near, far)]


def nearest_part(points: torch.Tensor, parts: Sequence) -> torch.Tensor:
    """(N,) index into ``parts`` (loaded ``Mesh`` objects) of the part nearest each of the (N, 3)
    ``points`` (exact point-to-mesh distances, in chunks of 200k points)."""
    from l3d_app.geometry.point_mesh_distance import point_mesh_distance

    return torch.stack([torch.cat([point_mesh_distance(h, m).distance for h in points.split(200000)])
                        for m in parts], 1).argmin(1)


def _row(name: str, comp: torch.Tensor, acc: torch.Tensor, n_pred: int, near: float, far: float) -> Dict[str, float]:
    nan = float("nan")
    return {"part": name, "true_samples": int(comp.numel()), "mesh_samples": int(acc.numel()),
            "truth_to_mesh": float(comp.mean()) if comp.numel() else nan,
            "truth_far": float((comp > near).double().mean()) if comp.numel() else nan,
            "mesh_share": acc.numel() / n_pred,
            "mesh_to_truth": float(acc.mean()) if acc.numel() else nan,
            "phantom": float((acc > far).double().mean()) if acc.numel() else nan}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("mesh", type=Path)
    ap.add_argument("--scene", type=Path, required=True, help="a bench scene's folder (mesh.ply, parts/*.ply)")
    ap.add_argument("--samples", type=int, default=20000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--near", type=float, default=0.02)
    ap.add_argument("--far", type=float, default=0.05)
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args(argv)
    from l3d_app.geometry.mesh_io import load_mesh

    torch.set_num_threads(args.threads)
    part_files = sorted((args.scene / "parts").glob("*.ply"))
    for f in (args.mesh, args.scene / "mesh.ply"):
        if not f.is_file():
            raise SystemExit(f"surface_by_part: no file {f}")
    if not part_files:
        raise SystemExit(f"surface_by_part: {args.scene} has no parts/*.ply (render it with bench/make_scenes.py)")
    rows = scores_by_part(load_mesh(str(args.mesh)), load_mesh(str(args.scene / "mesh.ply")),
                          [load_mesh(str(f)) for f in part_files], args.samples, args.seed, args.near, args.far)
    names = [f.stem for f in part_files] + ["all"]
    print(f"{args.mesh} against {args.scene.name} ({args.samples} samples each, seed {args.seed}):")
    print(f"| part | truth -> mesh | truth > {args.near} | mesh share | mesh -> truth | phantom > {args.far} |")
    print("|---|---:|---:|---:|---:|---:|")
    for name, r in zip(names, rows):
        print(f"| {name} | {r['truth_to_mesh']:.4f} | {100 * r['truth_far']:.1f}% | {100 * r['mesh_share']:.1f}% "
              f"| {r['mesh_to_truth']:.4f} | {100 * r['phantom']:.1f}% |")


if __name__ == "__main__":
    main()
