"""Reading ``.npy`` / ``.npz`` files the user brings: one :class:`UserError` naming the file for
anything numpy cannot read (missing, empty, truncated, pickled where pickles are refused, not
numpy at all), never an ``EOFError`` traceback."""

from __future__ import annotations

import zipfile
from pathlib import Path

import numpy as np

from l3d_app.errors import UserError


def load_array_file(path: Path, **kwargs):
    """``np.load(path, **kwargs)`` (an ndarray, or an ``NpzFile`` for ``.npz``); a file numpy
    cannot read is a :class:`UserError` naming it."""
    try:
        return np.load(path, **kwargs)
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as err:
        raise UserError(f"cannot read {path}: {type(err).__name__}: {err}") from None


def numeric_array(array, where: str, dtype=np.float32) -> np.ndarray:
    """``array`` as a new ``dtype`` ndarray (a copy: never a view of a memory-mapped file); one
    that holds no numbers (strings, objects) is a
    :class:`UserError` naming ``where`` (the file, and the key inside it)."""
    array = np.asarray(array)
    if array.dtype.kind not in "biuf":
        raise UserError(f"{where} must hold numbers, got an array of dtype {array.dtype}")
    return np.array(array, dtype=dtype)
