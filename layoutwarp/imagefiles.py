"""Image files as preprocessing reads and writes them: decoded by OpenCV from bytes (so any path
works), a file cut short refused in our words and OpenCV's own lines kept off the terminal
([`read_image`][]); encoded by the destination's suffix ([`encode_image`][])."""

from __future__ import annotations

import contextlib
import os
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import cv2
import numpy as np

__all__ = ["IMAGE_SUFFIXES", "encode_image", "list_images", "read_image", "to_dtype"]

#: The image files preprocessing reads (by suffix, any case).
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp")


def encode_image(path: Path, arr: np.ndarray) -> bytes:
    """``arr`` encoded as the image format of ``path``'s suffix (OpenCV's encoders)."""
    ok, buf = cv2.imencode(path.suffix, arr)
    if not ok:
        raise ValueError(f"OpenCV cannot encode a {arr.dtype} {arr.shape} image as {path.suffix}")
    return buf.tobytes()


def to_dtype(values: np.ndarray, dtype: np.dtype) -> np.ndarray:
    """``values`` in ``dtype``: rounded and clipped to an integer dtype's range."""
    if np.issubdtype(dtype, np.integer):
        info = np.iinfo(dtype)
        return np.clip(np.rint(values), info.min, info.max).astype(dtype)
    return values.astype(dtype)


_CV_SILENT = 0  # cv::utils::logging::LOG_LEVEL_SILENT in every release


def _cv_log() -> Any:
    """OpenCV's log-level functions: in ``cv2.utils.logging`` in newer releases, on ``cv2`` itself in
    older ones (4.8, the oldest pyproject allows)."""
    return getattr(cv2.utils, "logging", cv2)


_QUIET_LOCK = threading.Lock()
_QUIET = {"depth": 0, "level": 0}


@contextlib.contextmanager
def _opencv_quiet() -> Iterator[None]:
    """Within: OpenCV logs nothing (a broken file is reported once, as the run's failure), and as
    it was after the last thread leaves (the level is process-wide; the worker threads decode at
    once)."""
    with _QUIET_LOCK:
        if _QUIET["depth"] == 0:
            _QUIET["level"] = _cv_log().getLogLevel()
            _cv_log().setLogLevel(_CV_SILENT)
        _QUIET["depth"] += 1
    try:
        yield
    finally:
        with _QUIET_LOCK:
            _QUIET["depth"] -= 1
            if _QUIET["depth"] == 0:
                _cv_log().setLogLevel(_QUIET["level"])


def _truncation(data: np.ndarray) -> str | None:
    """Why a PNG or JPEG file's bytes are cut short (its end marker missing), or ``None``. Such a
    file is refused before decoding: OpenCV decodes a truncated JPEG into an image whose lower
    part is grey, and libpng and libjpeg print their own lines about it."""
    raw = data.tobytes()
    if raw.startswith(b"\x89PNG\r\n\x1a\n"):
        if raw.rfind(b"IEND") < raw.rfind(b"IDAT"):  # data may follow IEND (metadata, a trailer)
            return "truncated PNG file (no IEND chunk after its image data)"
    elif raw.startswith(b"\xff\xd8"):
        scan = raw.find(b"\xff\xda")  # the first scan (an EXIF thumbnail's end comes before it)
        if scan < 0 or raw.find(b"\xff\xd9", scan) < 0:  # a video may follow (motion photos)
            return "truncated JPEG file (no end-of-image marker after its scan)"
    return None


def read_image(path: Path, flags: int = cv2.IMREAD_UNCHANGED) -> np.ndarray:
    """An image file as OpenCV decodes it (HW or HWC, its own dtype); ``ValueError`` if unreadable
    or cut short (a PNG or JPEG file without its end marker).

    Read as bytes first, so paths OpenCV's own reader cannot open (non-ASCII names) work too.
    """
    data = np.fromfile(str(path), dtype=np.uint8)
    why = _truncation(data) if data.size else "empty file"
    if why is not None:
        raise ValueError(why)
    with _opencv_quiet():
        img = cv2.imdecode(data, flags)
    if img is None:
        raise ValueError("unreadable or not an image")
    return img


def list_images(src: str | Path, exclude: str | Path | None = None) -> list[Path]:
    """Every image file (by suffix, see [`IMAGE_SUFFIXES`][]) under ``src`` in sorted order,
    leaving out the folder ``exclude`` (e.g. a destination inside the source)."""
    src = Path(src)
    exclude = Path(exclude).resolve() if exclude is not None else None
    files = []
    for root, dirs, names in os.walk(src):
        rootp = Path(root)
        dirs[:] = sorted(d for d in dirs if exclude is None or (rootp / d).resolve() != exclude)
        files += [rootp / n for n in sorted(names) if Path(n).suffix.lower() in IMAGE_SUFFIXES]
    return files
