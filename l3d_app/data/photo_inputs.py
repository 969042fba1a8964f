"""Photos and video frames as structure-from-motion sees them: found, decoded, upright, shrunk.

* :func:`photo_files`: the JPEG / PNG files of a folder (any names, sorted; other files ignored).
* :func:`read_photo`: one photo as (H, W, 3) uint8, its EXIF orientation applied; a file that
  does not decode is a one-line :class:`~l3d_app.errors.UserError` naming it.
* :func:`video_frames`: ``frames`` frames of a video, one per equal stretch of its length, each
  the sharpest of its stretch (:func:`sharpness`), the blurry ones dropped.
* :func:`shrink`: the long side down to ``max_size`` pixels (area averaging).
"""

from __future__ import annotations

from pathlib import Path
from typing import Iterator, List, Tuple

import numpy as np

from l3d_app.errors import UserError
from l3d_app.runtime.progress import progress

PHOTO_SUFFIXES = (".jpg", ".jpeg", ".png")


def photo_files(folder: Path) -> List[Path]:
    """JPEG / PNG files directly in ``folder`` (case-insensitive suffix, hidden files skipped), sorted by name."""
    if not folder.is_dir():
        raise UserError(f"photo folder not found: {folder}")
    return sorted(p for p in folder.iterdir()
                  if p.is_file() and p.suffix.lower() in PHOTO_SUFFIXES and not p.name.startswith("."))


def read_photo(path: Path) -> np.ndarray:
    """(H, W, 3) uint8 RGB of ``path`` turned upright by its EXIF orientation tag."""
    from PIL import Image, ImageOps

    try:
        with Image.open(path) as im:
            im.load()
            im = ImageOps.exif_transpose(im)
            return np.asarray(im.convert("RGB"))
    except Exception as err:      # PIL raises many kinds for a broken file
        raise UserError(f"{path}: cannot be read as an image ({type(err).__name__}: {str(err)[:80]}); "
                        "remove or replace the file") from None


def shrink(img: np.ndarray, max_size: int) -> np.ndarray:
    """``img`` (H, W, 3) uint8 with its long side at most ``max_size`` px (0: unchanged)."""
    h, w = img.shape[:2]
    if int(max_size) <= 0 or max(h, w) <= int(max_size):
        return img
    from PIL import Image

    s = int(max_size) / float(max(h, w))
    return np.asarray(Image.fromarray(img).resize((max(1, round(w * s)), max(1, round(h * s))), Image.BOX))


def sharpness(img: np.ndarray) -> float:
    """Variance of the 4-neighbour Laplacian of the grey image (uint8 scale): low for blurred frames."""
    g = img.astype(np.float32).mean(-1)
    lap = g[1:-1, :-2] + g[1:-1, 2:] + g[:-2, 1:-1] + g[2:, 1:-1] - 4.0 * g[1:-1, 1:-1]
    return float(lap.var())


def _decode(path: Path) -> Tuple[Iterator[np.ndarray], int]:
    """A frame iterator over ``path`` and its frame count; a UserError when ffmpeg cannot read it."""
    import imageio_ffmpeg

    try:
        n, _ = imageio_ffmpeg.count_frames_and_secs(str(path))
        reader = imageio_ffmpeg.read_frames(str(path))
        meta = next(reader)
    except Exception as err:
        msg = " ".join(str(err).split())[-100:]
        raise UserError(f"{path}: cannot be decoded as a video ({msg})") from None
    w, h = meta["size"]

    def frames():
        try:
            for buf in reader:
                yield np.frombuffer(buf, np.uint8).reshape(h, w, 3)
        except Exception as err:
            raise UserError(f"{path}: the video breaks off while decoding ({' '.join(str(err).split())[-80:]})") from None
        finally:
            reader.close()

    return frames(), int(n)


def video_frames(path: Path, frames: int, min_sharpness: float, max_size: int) -> Tuple[List[np.ndarray], dict]:
    """``frames`` frames of the video at ``path``, shrunk to ``max_size``, in time order.

    The video's length is cut into ``frames`` equal stretches; from each the sharpest frame
    (:func:`sharpness`, measured after shrinking) is kept, then every kept frame sharper than
    ``min_sharpness`` x the median of the kept ones stays (the rest are blurred by motion).
    Returns the frames and a note: ``{"decoded": total frames, "kept": n, "blurry": dropped}``.
    """
    if not path.is_file():
        raise UserError(f"video not found: {path}")
    it, n = _decode(path)
    if n < 1:
        raise UserError(f"{path}: the video holds no frames")
    k = max(1, min(int(frames), n))
    stretch = np.minimum((np.arange(n) * k) // n, k - 1)        # frame index -> its stretch
    best: List[Tuple[float, np.ndarray]] = [(-1.0, None)] * k
    seen = 0
    for i, img in enumerate(progress(it, desc="video: frames", total=n)):
        if i >= n:
            break
        small = shrink(img, max_size)
        s = sharpness(small)
        j = int(stretch[i])
        if s > best[j][0]:
            best[j] = (s, small.copy())
        seen += 1
    kept = [(s, f) for s, f in best if f is not None]
    if not kept:
        raise UserError(f"{path}: no frame could be decoded")
    med = float(np.median([s for s, _ in kept]))
    sharp = [f for s, f in kept if s >= float(min_sharpness) * med]
    return sharp, {"decoded": seen, "kept": len(sharp), "blurry": len(kept) - len(sharp)}
