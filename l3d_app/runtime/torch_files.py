"""Reading ``torch.save`` files the user points at (checkpoints, exported models)."""

from __future__ import annotations

import os
from typing import Any

import torch

from l3d_app.errors import UserError


def read_torch_file(path: os.PathLike, what: str, weights_only: bool = False) -> Any:
    """``torch.load(path)`` on the CPU; a file that is not a readable torch file (empty,
    truncated, text, another format) is a :class:`UserError` naming ``what`` it should be."""
    try:
        return torch.load(path, map_location="cpu", weights_only=weights_only)
    except Exception as err:  # noqa: BLE001 -- pickle, zip and torch raise many types for a bad file
        raise UserError(f"{path} is not a readable {what} ({type(err).__name__}: {' '.join(str(err).split())})"
                        ) from err
