"""A solved capture written once, atomically, keyed by what went in, and reused.

:func:`solved_capture` returns a folder ``<cache>/<label>-<key>/`` holding ``images/``,
``sparse/`` and ``sfm.json`` (:mod:`l3d_app.data.sfm`). The key hashes the inputs' bytes
and every setting that changes the result, so edited photos or another setting solve
again, and the same capture is solved once. The folder is built under a hidden temporary
name beside it and renamed into place only when SfM succeeded: a failed, refused or
interrupted run leaves nothing a later run would take for a finished model (the temporary
folder is removed; one left by a killed process is hidden and never read).
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import sys
import uuid
from pathlib import Path
from typing import Callable, Dict, List, Sequence, Tuple

import numpy as np

from l3d_app.data.sfm import SfmReport, read_report, solve_cameras
from l3d_app.errors import UserError
from l3d_app.runtime.progress import progress

KEY_VERSION = 1


def content_key(files: Sequence[Path], settings: Dict) -> str:
    """sha1 (hex) of each file's name and bytes plus ``settings`` (JSON)."""
    h = hashlib.sha1(json.dumps([KEY_VERSION, settings], sort_keys=True).encode())
    for f in files:
        h.update(Path(f).name.encode() + b"\0")
        with open(f, "rb") as fh:
            for block in iter(lambda: fh.read(1 << 20), b""):
                h.update(block)
    return h.hexdigest()


def staged_names(files: Sequence[Path]) -> List[str]:
    """PNG names for ``files`` in the same sorted order: ``stem.png``, or ``name.png`` where stems collide."""
    stems = [Path(f).stem for f in files]
    return [f"{s}.png" if stems.count(s) == 1 else f"{Path(f).name}.png" for s, f in zip(stems, files)]


def solved_capture(cache: Path, label: str, key: str, frames: Callable[[], Tuple[List[str], Callable[[int], np.ndarray]]],
                   solve: Dict) -> Tuple[Path, SfmReport, bool]:
    """The finished model folder for ``key``: reused when present, else solved now.

    Args:
        cache: the cache root (created). label: readable prefix of the folder name.
        key: :func:`content_key` of the inputs and settings.
        frames: called only when solving: returns (names, image_of) where ``image_of(i)`` is the
            i-th image as (H, W, 3) uint8, already upright and shrunk.
        solve: keyword arguments of :func:`~l3d_app.data.sfm.solve_cameras` (matcher, ...).
    Returns:
        (folder, report, reused).
    """
    final = cache / f"{label}-{key[:16]}"
    if (final / "sfm.json").is_file():
        return final, read_report(final), True
    from PIL import Image

    cache.mkdir(parents=True, exist_ok=True)
    tmp = cache / f".{final.name}.tmp-{os.getpid()}-{uuid.uuid4().hex[:8]}"
    try:
        names, image_of = frames()
        staged = tmp / "input"
        staged.mkdir(parents=True)
        first = None
        for i, name in enumerate(progress(names, desc="sfm: staging images")):
            img = image_of(i)
            first = first or (name, img.shape[:2])
            if img.shape[:2] != first[1]:
                raise UserError(f"{name} is {img.shape[1]}x{img.shape[0]} px but {first[0]} is {first[1][1]}x{first[1][0]}: "
                                "one camera, one image size per capture (the same zoom and orientation throughout)")
            Image.fromarray(img).save(staged / name, compress_level=1)
        report = solve_cameras(staged, names, tmp, **solve)
        for scratch in ("input", "mapping", "database.db", "stereo", "run-colmap-geometric.sh",
                        "run-colmap-photometric.sh"):
            p = tmp / scratch
            shutil.rmtree(p) if p.is_dir() else p.unlink(missing_ok=True)
        try:
            os.rename(tmp, final)
        except OSError:                 # another run finished the same capture first: keep its folder
            if not (final / "sfm.json").is_file():
                raise
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
    print(f"l3d_app: note: cameras solved by structure-from-motion: {report.line()}; model cached at {final}",
          file=sys.stderr)
    return final, report, False
