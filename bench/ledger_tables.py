"""Write each measured page's held-out table from the benchmark's ledger (``docs/benchmark_scenes*.json``,
written by ``bench/bench_scenes.py``). Runs nothing:

    python bench/ledger_tables.py            # every marked block under docs/

A page marks its block with ``<!-- ledger_table method=volsdf ledger=docs/benchmark_scenes.json -->``
and ``<!-- ledger_table end -->``; the text between them is replaced by one method's rows of that
ledger: scene, role, the figures, seconds, size, commit, machine and the targets each row misses,
under the command that reproduces a row.
"""

from __future__ import annotations

import json
import re
import sys
from pathlib import Path
from typing import Dict, List

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_scenes import DENSITY_NAMES, EXTRA, REPO, role_of  # noqa: E402

START = re.compile(r"<!-- ledger_table method=(\S+) ledger=(\S+) -->")
END = "<!-- ledger_table end -->"
# The held-out targets (bench_scenes.TARGETS in words): key, comparison, bound, name, format.
CHECKS = {"train_nerf": [("psnr", ">=", 32.0, "PSNR", ".2f")],
          "gs_train": [("psnr", ">=", 33.0, "PSNR", ".2f")],
          "volsdf": [("psnr", ">=", 28.0, "PSNR", ".2f"), ("chamfer_pct", "<=", 1.0, "chamfer", ".3f"),
                     ("f1_02_obs", ">=", 0.8, "F1@0.02", ".3f"), ("phantom_pct", "<", 5.0, "phantom", ".1f")],
          "surfels": [("psnr", ">=", 30.0, "PSNR", ".2f"), ("chamfer_obs_pct", "<=", 0.5, "observed chamfer", ".3f"),
                      ("f1_02_obs", ">=", 0.85, "F1@0.02", ".3f"), ("phantom_pct", "<", 5.0, "phantom", ".1f")]}


def missed(row: dict) -> str:
    """The row's targets not met, with their figures ('all met' when none; '' without targets)."""
    checks = CHECKS.get(row["method"], [])
    if not checks:
        return ""
    ok = {">=": lambda v, b: v >= b, "<=": lambda v, b: v <= b, "<": lambda v, b: v < b}
    out = [f"{name} {row[key]:{spec}}" for key, op, bound, name, spec in checks
           if row.get(key) is not None and not ok[op](row[key], bound)]
    return "not met: " + ", ".join(out) if out else "all met"


def fmt(v, spec: str) -> str:
    return "" if v is None else format(v, spec)


def method_table(rows: List[dict], method: str, ledger: str) -> str:
    """The block for ``method``: the command, then one line per scene."""
    extra = " ".join(EXTRA.get(method, []) + (["time_budget=590"] if method == "nerf_baseline" else []))
    cmd = (f"`python bench/bench_scenes.py --methods {method} --scenes SCENE` (one run: `python main.py task={method} "
           f"data=blender data.root=outputs/.cache/bench_scenes/SCENE data.mesh_path=mesh.ply threads=2"
           f"{' ' + extra if extra else ''}`)")
    lines = [f"Each row: {cmd}; the rows are the ledger `{ledger}`, this table `python bench/ledger_tables.py`.", ""]
    surface = any(r.get("chamfer_pct") is not None for r in rows if r["method"] == method)
    head = "| scene | role | test PSNR / SSIM |"
    head += " chamfer % diag whole / observed | F1@0.02 obs | phantom % |" if surface else ""
    head += " size | seconds | commit | machine |" + (" targets |" if method in CHECKS else "")
    lines += [head, "|" + "---|" * (head.count("|") - 1)]
    for r in rows:
        if r["method"] != method:
            continue
        label = r["scene"] + (f" ({DENSITY_NAMES.get(r['density'], r['density'])})" if r.get("density") else "")
        cells = [label, role_of(r), f"{fmt(r.get('psnr'), '.2f')} / {fmt(r.get('ssim'), '.3f')}"]
        if surface:
            cham = "" if r.get("chamfer_pct") is None else f"{r['chamfer_pct']:.2f} / {r['chamfer_obs_pct']:.2f}"
            cells += [cham, fmt(r.get("f1_02_obs"), ".3f"), fmt(r.get("phantom_pct"), ".1f")]
        size = r.get("n_gaussians") or r.get("n_params") or ""
        cells += [str(size), fmt(r.get("seconds"), ".0f"), r.get("commit", "?"),
                  r.get("machine", "machine not recorded")] + ([missed(r)] if method in CHECKS else [])
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def render(doc: Path) -> bool:
    """Rewrite every marked block of ``doc``; True when the file changed."""
    text = doc.read_text()
    out, pos = [], 0
    for m in START.finditer(text):
        end = text.index(END, m.end())
        rows = json.loads((REPO / m.group(2)).read_text())
        out += [text[pos:m.end()], "\n", method_table(rows, m.group(1), m.group(2)), "\n"]
        pos = end
    new = "".join(out) + text[pos:]
    if new != text:
        doc.write_text(new)
    return new != text


def main() -> None:
    changed = [p for p in sorted((REPO / "docs").rglob("*.md")) if START.search(p.read_text()) and render(p)]
    for p in changed:
        print(f"wrote {p.relative_to(REPO)}")


if __name__ == "__main__":
    main()
