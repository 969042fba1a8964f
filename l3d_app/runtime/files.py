"""Atomic file writing: write to a temporary name beside the target, then rename; and reading a user's JSON.

A run that is interrupted or fails never leaves a half-written artefact under the final name.
"""

from __future__ import annotations

import json
import math
import os
import tempfile
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Iterator, Mapping

from l3d_app.errors import UserError


@contextmanager
def atomic_path(path: os.PathLike) -> Iterator[Path]:
    """Yield a temporary path in the same folder (same suffix); renamed onto ``path`` on success."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=path.suffix, dir=path.parent)
    os.close(fd)
    try:
        yield Path(tmp)
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def write_json(path: os.PathLike, data: Mapping[str, Any]) -> Path:
    """Write ``data`` as pretty, strict JSON atomically; returns the path. Tensors and numpy
    values become numbers or lists; a NaN or infinite number becomes ``null`` (JSON has no NaN:
    ``jq`` and JavaScript reject Python's ``NaN``), so a figure that does not exist reads as none."""
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(_json_value(data), indent=2, sort_keys=True, allow_nan=False) + "\n")
    return Path(path)


def read_json(path: os.PathLike) -> Any:
    """The JSON value in the file at ``path``; text that is not JSON is a :class:`UserError`
    ``"{path} is not valid JSON: ..."``."""
    try:
        return json.loads(Path(path).read_text())
    except json.JSONDecodeError as err:
        raise UserError(f"{path} is not valid JSON: {err}") from err


def _json_value(value: Any) -> Any:
    """``value`` as plain JSON types (see :func:`write_json`)."""
    if isinstance(value, Mapping):
        return {str(k): _json_value(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_value(v) for v in value]
    if isinstance(value, (bool, int, str)) or value is None:
        return value
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if hasattr(value, "tolist"):            # tensors, numpy arrays and scalars
        return _json_value(value.tolist())
    return str(value)
