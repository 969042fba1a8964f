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
