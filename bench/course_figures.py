"""Pictures for docs from finished runs: a run's training loss against step beside frames of its turntable gif.

    python bench/course_figures.py RUN_DIR OUT.png [--gif mesh.gif] [--frames 4] [--title TEXT]

Reads ``train/loss`` from the run's TensorBoard events (:func:`l3d_app.runtime.sweep_pictures.loss_curve`) and
``frames`` evenly spaced frames of ``RUN_DIR/<gif>``; writes one PNG (the loss on a log axis, the frames in a row).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))     # this checkout's l3d_app


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run", type=Path)
    ap.add_argument("out", type=Path)
    ap.add_argument("--gif", default="mesh.gif")
    ap.add_argument("--frames", type=int, default=4)
    ap.add_argument("--title", default="")
    args = ap.parse_args()
    import imageio.v2 as imageio
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from l3d_app.runtime.sweep_pictures import loss_curve

    curve = loss_curve(args.run)
    frames = imageio.mimread(args.run / args.gif)
    pick = np.linspace(0, len(frames) - 1, args.frames + 1)[:-1].round().astype(int)
    fig = plt.figure(figsize=(3 + 2 * args.frames, 2.4), dpi=110)
    grid = fig.add_gridspec(1, args.frames + 2)
    ax = fig.add_subplot(grid[0, :2])
    if curve is not None:
        ax.plot(curve["step"], curve["loss"], lw=1)
        ax.set_yscale("log")
    ax.set_xlabel("step")
    ax.set_ylabel("training loss")
    ax.grid(alpha=0.3)
    for k, i in enumerate(pick):
        sub = fig.add_subplot(grid[0, 2 + k])
        sub.imshow(np.asarray(frames[i])[..., :3])
        sub.set_title(f"frame {i}", fontsize=7)
        sub.axis("off")
    if args.title:
        fig.suptitle(args.title, fontsize=8)
    fig.tight_layout()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out)
    print(args.out)


if __name__ == "__main__":
    main()
