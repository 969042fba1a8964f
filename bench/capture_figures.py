"""The capture figures of docs/measured/capture.md, read from the runs' metrics.json.

    python bench/make_capture.py                                   # desk (development), shelf (held out)
    python main.py task=process_images data=images data.root=outputs/.cache/captures/NAME/images threads=2 \\
        hydra.run.dir=outputs/capture_runs/sfm_NAME
    python main.py task=gs_train data=images data.root=outputs/.cache/captures/NAME/images threads=2 \\
        hydra.run.dir=outputs/capture_runs/gs_NAME                 # and task=train_nerf ... nerf_NAME
    python bench/capture_figures.py [--runs outputs/capture_runs]

Prints one markdown table of SfM figures and one of training figures (test PSNR / SSIM on the
held-out images, scored with the recovered cameras; seconds of the whole task).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path


def _load(path: Path) -> dict:
    return json.loads(path.read_text()) if path.is_file() else {}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=Path, default=Path("outputs/capture_runs"))
    ap.add_argument("--scenes", nargs="*", default=["desk", "shelf"])
    args = ap.parse_args()
    print("| capture | registered | mean reprojection error (px) | sparse points | SfM seconds (features / matching / mapping / undistortion) |")
    print("|---|---|---|---|---|")
    for name in args.scenes:
        m = _load(args.runs / f"sfm_{name}" / "metrics.json")
        if not m:
            continue
        s = m["sfm_seconds"]
        print(f"| {name} | {m['registered']} of {m['given']} ({100 * m['registered'] / m['given']:.0f}%) | "
              f"{m['reprojection_error']:.3f} | {m['points']} | {s.get('total', 0):.0f} ({s.get('features', 0):.0f} / "
              f"{s.get('matching', 0):.0f} / {s.get('mapping', 0):.0f} / {s.get('undistortion', 0):.0f}) |")
    print()
    print("| capture | task | test PSNR (dB) | test SSIM | val PSNR (dB) | steps | seconds |")
    print("|---|---|---|---|---|---|---|")
    for name in args.scenes:
        for task, prefix in (("gs_train", "gs"), ("train_nerf", "nerf")):
            m = _load(args.runs / f"{prefix}_{name}" / "metrics.json")
            if m:
                print(f"| {name} | {task} | {m['psnr']:.2f} | {m['ssim']:.3f} | {m.get('val_psnr', float('nan')):.2f} | "
                      f"{m.get('iters', '')} | {m['seconds']:.0f} |")


if __name__ == "__main__":
    main()
