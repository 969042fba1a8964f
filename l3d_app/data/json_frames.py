"""Checks shared by the loaders of NeRF-style ``transforms*.json`` files (blender, nerfstudio): a value
of the wrong JSON type is one :class:`UserError` naming the file, the frame and the key, never a bare
``ValueError`` from ``float()`` or a ``TypeError`` from ``Path()`` or sorting."""

from __future__ import annotations

from pathlib import Path
from typing import Any, List

from l3d_app.errors import UserError


def json_number(value: Any, where: str) -> float:
    """``value`` as a float; anything ``float()`` refuses (a string, a list, null) is a UserError
    ``"{where} must be a number, got ..."`` (``where``: the file and the key)."""
    try:
        return float(value)
    except (TypeError, ValueError):
        raise UserError(f"{where} must be a number, got {value!r}") from None


def check_frame_entries(frames: Any, path: Path) -> List[dict]:
    """``frames`` (the file's ``frames`` value) as a list of objects, each with a string ``file_path``
    and a ``transform_matrix``; else a UserError naming ``path`` and the frame's index."""
    if not isinstance(frames, list):
        raise UserError(f"{path}: frames must be a list, got {type(frames).__name__}")
    for i, fr in enumerate(frames):
        if not isinstance(fr, dict):
            raise UserError(f"{path}: frame {i} must be an object with file_path and transform_matrix, "
                            f"got {type(fr).__name__}")
        for key in ("file_path", "transform_matrix"):
            if key not in fr:
                raise UserError(f"{path}: frame {i} has no '{key}' key")
        if not isinstance(fr["file_path"], str):
            raise UserError(f"{path}: frame {i} file_path must be a string, got {fr['file_path']!r}")
    return frames
