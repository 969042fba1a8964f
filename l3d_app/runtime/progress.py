"""Progress bars for every long loop (tqdm), quiet when ``L3D_NO_PROGRESS=1``."""

from __future__ import annotations

import os
from typing import Iterable, Optional

from tqdm.auto import tqdm


def progress(iterable: Optional[Iterable] = None, desc: str = "", total: Optional[int] = None, **kwargs):
    """A tqdm bar over ``iterable`` (or a manual bar with ``total``)."""
    disable = os.environ.get("L3D_NO_PROGRESS", "0") == "1"
    return tqdm(iterable, desc=desc, total=total, disable=disable, dynamic_ncols=True,
                leave=False, **kwargs)
