"""Small line plots written to PNG (matplotlib, Agg backend): measured points beside reference curves."""

from __future__ import annotations

import os
from typing import Mapping, Optional, Sequence, Tuple

from l3d_app.runtime.files import atomic_path

Series = Tuple[Sequence[float], Sequence[float]]


def line_plot(path: os.PathLike, curves: Mapping[str, Series], points: Optional[Mapping[str, Series]] = None,
              xlabel: str = "", ylabel: str = "", title: str = "", logx: bool = False,
              logy: bool = False) -> None:
    """Draw ``curves`` (label -> (xs, ys)) as lines and ``points`` (label -> (xs, ys)) as markers
    in matching colours (a point series takes the colour of the curve with the same label
    prefix before ' (' when there is one); write a PNG at ``path`` atomically."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4), dpi=120)
    colours = {}
    for i, (label, (xs, ys)) in enumerate(curves.items()):
        line, = ax.plot(list(xs), list(ys), "-", label=label, color=f"C{i % 10}")
        colours[label.split(" (")[0]] = line.get_color()
    for j, (label, (xs, ys)) in enumerate((points or {}).items()):
        colour = colours.get(label.split(" (")[0], f"C{(len(curves) + j) % 10}")
        ax.plot(list(xs), list(ys), "o", label=label, color=colour, markersize=4)
    ax.set_xscale("log" if logx else "linear")
    ax.set_yscale("log" if logy else "linear")
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    if title:
        ax.set_title(title)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)
