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

__all__ = [
    "IMAGE_SUFFIXES",
    "JPEG_CHANNELS",
    "KEEPS",
    "encode_image",
    "list_images",
    "read_image",
    "read_label",
    "to_dtype",
]

#: The image files preprocessing reads (by suffix, any case).
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp")

#: The dtypes the format of each suffix keeps (OpenCV's encoders; TIFF, not listed, keeps every
#: dtype an image file holds). OpenCV writes any other as 8-bit, with a line on the terminal.
KEEPS = {".png": ("uint8", "uint16"), ".jpg": ("uint8",), ".jpeg": ("uint8",), ".bmp": ("uint8",)}
#: The channel counts a JPEG keeps (OpenCV drops an alpha channel without a word).
JPEG_CHANNELS = (1, 3)


def encode_image(path: Path, arr: np.ndarray) -> bytes:
    """``arr`` encoded as the image format of ``path``'s suffix (OpenCV's encoders); ``ValueError``
    for a dtype that format does not keep ([`KEEPS`][]: a 16-bit image in a file named ``.jpg``,
    say), which OpenCV would write as 8-bit, saturated, for an alpha channel a JPEG would drop
    ([`JPEG_CHANNELS`][]), and for what OpenCV cannot encode."""
    keeps = KEEPS.get(path.suffix.lower())
    if keeps is not None and arr.dtype.name not in keeps:
        raise ValueError(
            f"{_a(arr.dtype.name)} {arr.dtype} image cannot be written as {path.suffix}, which keeps "
            f"{' or '.join(keeps)} "
            "only: give the source file a suffix of its format (.tif keeps every dtype)"
        )
    channels = 1 if arr.ndim == 2 else arr.shape[2]
    if path.suffix.lower() in (".jpg", ".jpeg") and channels not in JPEG_CHANNELS:
        raise ValueError(
            f"an image of {channels} channels cannot be written as {path.suffix}, which keeps 1 or 3 "
            "(its alpha would be dropped): give the source file a suffix of its format"
        )
    try:
        ok, buf = cv2.imencode(path.suffix, arr)
    except cv2.error:  # a channel count the format has no place for: OpenCV's lines, in one
        ok = False
    if not ok:
        raise ValueError(f"OpenCV cannot encode a {arr.dtype} {arr.shape} image as {path.suffix}")
    return buf.tobytes()


def _a(word: str) -> str:
    """The article before ``word``."""
    return "an" if word[:1] in "aeio" else "a"  # "an int16", "a uint16"


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
    or cut short (a PNG or JPEG file without its end marker). A JPEG file is turned as its EXIF
    orientation says (as viewers show it, and as ``cv2.imread`` reads it by default), with the
    default ``flags``.

    Read as bytes first, so paths OpenCV's own reader cannot open (non-ASCII names) work too.
    """
    return _decode(_file_bytes(path), flags)


def _decode(data: np.ndarray, flags: int = cv2.IMREAD_UNCHANGED) -> np.ndarray:
    """A file's bytes ``data`` decoded as [`read_image`][] decodes them."""
    if flags == cv2.IMREAD_UNCHANGED and data[:2].tobytes() == b"\xff\xd8":  # no alpha in a JPEG
        flags = cv2.IMREAD_ANYDEPTH | cv2.IMREAD_ANYCOLOR  # UNCHANGED ignores the orientation
    with _opencv_quiet():
        img = cv2.imdecode(data, flags)
    if img is None:
        raise ValueError("unreadable or not an image")
    return img


def read_label(path: Path) -> np.ndarray:
    """A label map file's class indices, HW (HWC where the file holds colours): as
    [`read_image`][] reads it, except that a palette PNG (Pascal VOC's) gives the indices its pixels
    hold, not the palette's colours."""
    data = _file_bytes(path)
    # a PNG's IHDR chunk comes first: its colour type (3: palette) is byte 25 of the file
    if data[:8].tobytes() == b"\x89PNG\r\n\x1a\n" and data.size > 25 and data[25] == 3:
        import io

        from PIL import Image  # Pillow comes with scikit-image

        with Image.open(io.BytesIO(data.tobytes())) as im:
            return np.array(im)  # writable, as OpenCV gives them
    return _decode(data)


def _file_bytes(path: Path) -> np.ndarray:
    """A file's bytes; ``ValueError`` for an empty file or a PNG or JPEG cut short."""
    if not path.is_file():  # not opened: a pipe would wait for a writer
        raise ValueError("not a file (a broken link, a pipe or a device)")
    data = np.fromfile(str(path), dtype=np.uint8)
    why = _truncation(data) if data.size else "empty file"
    if why is not None:
        raise ValueError(why)
    return data


def list_images(src: str | Path, exclude: str | Path | None = None) -> list[Path]:
    """Every image file (by suffix, see [`IMAGE_SUFFIXES`][]) under ``src`` in sorted order,
    leaving out the folder ``exclude`` (e.g. a destination inside the source). Links to folders
    are followed, each folder walked once; a link to ``src`` or a folder above it is not (it
    would bring in src's siblings); an entry with an image suffix that is no file (a broken link,
    a pipe) is listed too, for its reader to refuse."""
    src = Path(src)
    exclude = Path(exclude).resolve() if exclude is not None else None
    top = src.resolve()
    files, walked = [], {top, exclude}
    for root, dirs, names in os.walk(src, followlinks=True):
        rootp, kept = Path(root), []
        for d in sorted(dirs):  # a folder reached twice (by a link) is walked once, and a link
            real = (rootp / d).resolve()  # up to a folder holding src, never (src's siblings)
            if real not in walked and not top.is_relative_to(real):
                walked.add(real)
                kept.append(d)
        dirs[:] = kept
        files += [rootp / n for n in sorted(names) if Path(n).suffix.lower() in IMAGE_SUFFIXES]
    return files
