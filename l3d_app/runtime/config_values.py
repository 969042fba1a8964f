"""Config values read as the numbers or names a library function needs, and checked.

A knob such as ``background``, ``up`` or ``data.scene_box`` arrives as a list (an OmegaConf
``ListConfig`` is a sequence); a wrong length, a word among numbers, or a bare number where a
list is due is one :class:`~l3d_app.errors.UserError` that names the knob, never Python's own
"not enough values to unpack". One bare name where a list of names is due is a list of one.
The ``require_*`` checks name the first of a mapping's keys whose value is out of range.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, List, Optional

from l3d_app.errors import UserError


def shown(value: Any) -> str:
    """A value as the user typed it: ``true`` / ``false`` for bools, ``repr`` otherwise."""
    return str(value).lower() if isinstance(value, bool) else repr(value)


def _items(value: Any) -> Any:
    """A config sequence (list, tuple, ListConfig) as a plain list, nested rows too; anything else as it is."""
    if isinstance(value, Sequence) and not isinstance(value, str):
        return [_items(v) for v in value]
    return value


def is_number_list(value: Any, allow_empty: bool = False) -> bool:
    """A list (or tuple) whose every entry is an int or a float (not a bool); non-empty unless
    ``allow_empty``."""
    return isinstance(value, (list, tuple)) and (allow_empty or len(value) > 0) and all(
        isinstance(v, (int, float)) and not isinstance(v, bool) for v in value)


def config_floats(value: Any, key: str, length: Optional[int] = None) -> List[float]:
    """A config list of numbers as floats, or :class:`UserError` naming ``key``.

    Args: value: the config value (a list, a ListConfig or a tuple); key: its name in the
        message; length: the required number of entries (None: any).
    """
    items = _items(value)
    shape = f"a list of {length} numbers" if length is not None else "a list of numbers"
    if not is_number_list(items, allow_empty=True) or (length is not None and len(items) != length):
        raise UserError(f"{key} must be {shape}, got {shown(items)}")
    return [float(v) for v in items]


def config_rows(value: Any, key: str, rows: Optional[int], cols: int, what: Optional[str] = None
                ) -> List[List[float]]:
    """A config list of ``rows`` lists of ``cols`` numbers each (``rows`` None: any count), as
    floats, or :class:`UserError` naming ``key`` and ``what`` it must be (default: the shape
    in words) (a scene box, point-light positions)."""
    items = _items(value)
    shape = f"a list of {rows if rows is not None else 'any number of'} lists of {cols} numbers"
    if not isinstance(items, list) or (rows is not None and len(items) != rows) or not all(
            is_number_list(row) and len(row) == cols for row in items):
        raise UserError(f"{key} must be {what or shape}, got {shown(items)}")
    return [[float(v) for v in row] for row in items]


def config_words(value: Any, key: str) -> List[str]:
    """A config list of names (formats, panels, classes) as strings; one bare name is a list of
    one (``mesh_formats=ply``), never its letters; numbers or nested lists are a :class:`UserError`."""
    items = _items(value)
    if isinstance(items, str):
        return [items]
    if not isinstance(items, list) or not all(isinstance(v, str) for v in items):
        raise UserError(f"{key} must be a name or a list of names, got {shown(items)}")
    return items


def require_positive(cfg, *keys: str) -> None:
    """UserError naming the first of ``keys`` whose config value is not > 0."""
    for key in keys:
        value = cfg.get(key)
        if value is None or isinstance(value, bool) or not isinstance(value, (int, float)) or value <= 0:
            raise UserError(f"{key} must be a positive number, got {value!r}")


def require_fraction(cfg, *keys: str) -> None:
    """UserError naming the first of ``keys`` whose config value is not a number in [0, 1]
    (a probability, a decay)."""
    for key in keys:
        value = cfg.get(key)
        if value is None or isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 <= value <= 1:
            raise UserError(f"{key} must be a number in [0, 1], got {value!r}")


def require_nonnegative(cfg, *keys: str) -> None:
    """UserError naming the first of ``keys`` whose config value is not a number >= 0."""
    for key in keys:
        value = cfg.get(key)
        if value is None or isinstance(value, bool) or not isinstance(value, (int, float)) or value < 0:
            raise UserError(f"{key} must be a number >= 0, got {value!r}")
