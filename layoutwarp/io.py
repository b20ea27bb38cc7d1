"""Saved layouts (JSON) and dataset readers."""

from __future__ import annotations

import gzip
import json
import os
import tempfile
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from .layouts import Layout, make_layout

__all__ = ["atomic_write", "load_layout", "load_mnist", "read_idx", "save_layout"]

FORMAT = "layoutwarp.layout/1"
_UMASK = os.umask(0)
os.umask(_UMASK)
FILE_MODE = 0o666 & ~_UMASK  # what open() gives a new file (mkstemp gives 0o600)


def atomic_write(path: str | Path, content: bytes | str | Callable[[str], object]) -> Path:
    """Write ``path`` so that no reader ever sees it half-written, even if the process dies.

    The content goes to a temporary file in the same folder (named ``.<name>.<random><suffix>``,
    so writers that pick a format from the suffix still work), which is then renamed over
    ``path``; on any error the temporary file is removed and ``path`` is left as it was.

    Args:
        path: the file to write (its folder is created).
        content: bytes or text, or a function that writes the file at the path it is given.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=path.suffix, dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            if isinstance(content, (bytes, str)):
                f.write(content.encode() if isinstance(content, str) else content)
        if callable(content):
            content(tmp)
        os.chmod(tmp, FILE_MODE)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def save_layout(layout: Layout, path: str | Path, size: tuple[int, int] | None = None, **extra) -> Path:
    """Write ``layout`` (family, θ, bound, optional sensor size ``(H, W)``) to a JSON file.

    The file is written atomically (a temporary file renamed into place). Extra keyword
    values (JSON-serialisable) are stored under ``"extra"``.
    """
    from . import __version__

    data = {
        "format": FORMAT,
        "family": layout.family,
        "theta": [float(v) for v in layout.theta.detach().double()],
        "bound": layout.bound,
        "size_hw": list(size) if size is not None else None,
        "version": __version__,
        "extra": extra,
    }
    return atomic_write(path, json.dumps(data, indent=2))


def load_layout(
    path: str | Path, *, learn: bool = False, dtype: torch.dtype | None = None
) -> tuple[Layout, dict]:
    """Read a layout JSON written by :func:`save_layout`.

    Returns:
        ``(layout, info)`` where ``info`` holds the rest of the file (``size_hw``, ``version``,
        ``extra``).

    Raises:
        ValueError: malformed file or unknown family (naming the file and the problem).
    """
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise ValueError(f"{path}: not a readable layout JSON ({exc})") from exc
    if not isinstance(data, dict) or data.get("format") != FORMAT:
        raise ValueError(f"{path}: not a layoutwarp layout file (expected format {FORMAT!r})")
    family = data.get("family")
    theta = data.get("theta")
    if family not in ("uniform", "rect", "curv"):
        raise ValueError(f"{path}: unknown layout family {family!r}; expected 'uniform', 'rect' or 'curv'")
    if not isinstance(theta, list) or not all(isinstance(v, (int, float)) for v in theta):
        raise ValueError(f"{path}: 'theta' must be a list of numbers, got {theta!r}")
    kwargs = (
        {"dtype": dtype}
        if family == "uniform"
        else {"bound": float(data.get("bound", 1.0)), "learn": learn, "dtype": dtype}
    )
    layout = make_layout(family, theta if family != "uniform" else None, **kwargs)
    return layout, {k: data.get(k) for k in ("size_hw", "version", "extra")}


def read_idx(path: str | Path) -> np.ndarray:
    """Read an IDX file (MNIST format), gzip-compressed or not, into a numpy array."""
    path = Path(path)
    raw = path.read_bytes()
    if raw[:2] == b"\x1f\x8b":
        raw = gzip.decompress(raw)
    if len(raw) < 4 or raw[0] != 0 or raw[1] != 0:
        raise ValueError(f"{path}: not an IDX file")
    dtypes = {0x08: np.uint8, 0x09: np.int8, 0x0B: ">i2", 0x0C: ">i4", 0x0D: ">f4", 0x0E: ">f8"}
    if raw[2] not in dtypes:
        raise ValueError(f"{path}: unknown IDX data type 0x{raw[2]:02x}")
    ndim = raw[3]
    dims = [int.from_bytes(raw[4 + 4 * i : 8 + 4 * i], "big") for i in range(ndim)]
    data = np.frombuffer(raw, dtype=dtypes[raw[2]], offset=4 + 4 * ndim)
    if data.size != int(np.prod(dims)):
        raise ValueError(f"{path}: IDX header says {dims}, file holds {data.size} values")
    return data.reshape(dims).copy()  # writable, independent of the file buffer


def load_mnist(folder: str | Path) -> dict[str, np.ndarray]:
    """MNIST from a folder with the standard IDX names (``.gz`` or not).

    Returns ``{"train_images", "train_labels", "test_images", "test_labels"}`` (uint8).
    """
    folder = Path(folder)
    out = {}
    for split, prefix in (("train", "train"), ("test", "t10k")):
        for kind, stem in (("images", "images-idx3-ubyte"), ("labels", "labels-idx1-ubyte")):
            cands = [folder / f"{prefix}-{stem}.gz", folder / f"{prefix}-{stem}"]
            found = next((c for c in cands if c.exists()), None)
            if found is None:
                raise FileNotFoundError(f"MNIST file {prefix}-{stem}[.gz] not found in {folder}")
            out[f"{split}_{kind}"] = read_idx(found)
    return out
