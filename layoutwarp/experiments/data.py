"""Where the experiments' data lives, and its readers: MNIST (IDX files), CamVid and UTKFace.

A *data root* is a folder with one subfolder per task, laid out as each task expects::

    ROOT/mnist/                    train-images-idx3-ubyte[.gz], train-labels-idx1-ubyte[.gz],
                                   t10k-images-idx3-ubyte[.gz], t10k-labels-idx1-ubyte[.gz]
    ROOT/camvid/                   train/, trainannot/, val/, valannot/ (PNG images and
                                   same-named 8-bit class-index maps, 11 = void)
    ROOT/faces/utkface_subset/     labels.csv (file, age, gender, race) and the images it lists

The bundled samples ([`samples_dir`][], a few MB that ship with the package) are such a
root (``--quick``); the full data sets are another, named by the environment variable
``LAYOUTWARP_DATA`` ([`data_root`][]), or a task's own folder is given with ``--data DIR``.
Sources and licences: the samples' README. Nothing is downloaded.
"""

from __future__ import annotations

import csv
import gzip
import os
import zlib
from pathlib import Path

import cv2
import numpy as np
import torch

__all__ = [
    "AGE_GROUPS",
    "CAMVID_CLASSES",
    "DATA_ENV",
    "VOID",
    "age_group",
    "data_root",
    "images_to_tensor",
    "load_camvid",
    "load_faces",
    "load_mnist",
    "load_mnist_split",
    "read_idx",
    "read_rgb",
    "samples_dir",
]

#: The environment variable naming the data root of the full data sets.
DATA_ENV = "LAYOUTWARP_DATA"

CAMVID_CLASSES = "Sky Building Pole Road Pavement Tree SignSymbol Fence Car Pedestrian Bicyclist".split()
VOID = 11
AGE_GROUPS = ((0, 14), (15, 29), (30, 44), (45, 59), (60, 200))


def samples_dir() -> Path:
    """The bundled samples: ``layoutwarp/data_samples`` in an installed package, the checkout's
    ``data_samples/`` when running from a source tree.

    Raises:
        FileNotFoundError: neither is there (a broken installation).
    """
    package = Path(__file__).resolve().parents[1]
    for cand in (package / "data_samples", package.parent / "data_samples"):
        if (cand / "mnist").is_dir():
            return cand
    raise FileNotFoundError(f"the bundled data samples are missing (looked in {package} and beside it)")


def data_root(root: str | Path | None = None, quick: bool = False) -> Path | None:
    """The data root: ``root`` when given, the bundled samples with ``quick``, else the folder
    the environment variable [`DATA_ENV`][] names, else ``None`` (no full data here)."""
    if root is not None:
        return Path(root)
    if quick:
        return samples_dir()
    env = os.environ.get(DATA_ENV)
    return Path(env) if env else None


def images_to_tensor(images: np.ndarray) -> torch.Tensor:
    """uint8 images ``(N, H, W, 3)`` as a contiguous uint8 tensor ``(N, 3, H, W)``."""
    return torch.from_numpy(images).permute(0, 3, 1, 2).contiguous()


def read_idx(path: str | Path) -> np.ndarray:
    """Read an IDX file (MNIST format), gzip-compressed or not, into a numpy array."""
    path = Path(path)
    raw = path.read_bytes()
    if raw[:2] == b"\x1f\x8b":
        try:
            raw = gzip.decompress(raw)
        except (EOFError, OSError, zlib.error) as exc:  # cut short, or not gzip after all
            raise ValueError(f"{path}: a damaged gzip file ({exc})") from None
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


def load_mnist_split(folder: str | Path, split: str = "test") -> tuple[np.ndarray, np.ndarray]:
    """One MNIST split (``"train"`` or ``"test"``, the ``t10k-*`` files): uint8 images and labels."""
    if split not in ("train", "test"):
        raise ValueError(f"split must be 'train' or 'test' for MNIST, got {split!r}")
    folder = Path(folder)
    prefix = "train" if split == "train" else "t10k"
    out = []
    for stem in ("images-idx3-ubyte", "labels-idx1-ubyte"):
        cands = [folder / f"{prefix}-{stem}.gz", folder / f"{prefix}-{stem}"]
        found = next((c for c in cands if c.exists()), None)
        if found is None:
            raise FileNotFoundError(f"MNIST file {prefix}-{stem}[.gz] not found in {folder}")
        out.append(read_idx(found))
    images, labels = out
    if images.ndim != 3 or labels.ndim != 1 or len(images) != len(labels):
        raise ValueError(
            f"MNIST {split} files in {folder} do not match: images {images.shape}, labels {labels.shape} "
            "(one label per image expected)"
        )
    return images, labels


def load_mnist(folder: str | Path) -> dict[str, np.ndarray]:
    """MNIST from a folder with the standard IDX names (``.gz`` or not).

    Returns ``{"train_images", "train_labels", "test_images", "test_labels"}`` (uint8).
    """
    out = {}
    for split in ("train", "test"):
        out[f"{split}_images"], out[f"{split}_labels"] = load_mnist_split(folder, split)
    return out


def read_rgb(path: Path) -> np.ndarray:
    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if bgr is None:
        raise ValueError(f"cannot read image {path}")
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


def load_camvid(root: str | Path, split: str, limit: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """CamVid ``split`` ("train"/"val"): uint8 RGB ``(N, 360, 480, 3)`` and labels ``(N, 360, 480)``.

    Reads ``root/<split>/*.png`` and the same names in ``root/<split>annot/``.
    """
    root = Path(root)
    files = sorted((root / split).glob("*.png"))[:limit]
    if not files:
        raise FileNotFoundError(f"no CamVid images in {root / split} (split {split!r})")
    imgs = np.stack([read_rgb(f) for f in files])
    labels = []
    for f in files:
        lab = cv2.imread(str(root / f"{split}annot" / f.name), cv2.IMREAD_UNCHANGED)
        if lab is None:
            raise FileNotFoundError(f"missing label map {root / f'{split}annot' / f.name}")
        labels.append(lab)
    return imgs, np.stack(labels)


def age_group(age: np.ndarray) -> np.ndarray:
    """Index into [`AGE_GROUPS`][] for ages in years."""
    edges = np.array([lo for lo, _ in AGE_GROUPS[1:]])
    return np.searchsorted(edges, age, side="right")


def load_faces(root: str | Path, limit: int | None = None) -> dict[str, np.ndarray]:
    """UTKFace subset: ``images`` uint8 ``(N, H, W, 3)``, ``gender``, ``age_group``, ``race``.

    Reads ``root/labels.csv`` (``file, age, gender, race``; files relative to ``root``).
    """
    root = Path(root)
    with open(root / "labels.csv", newline="") as f:
        rows = list(csv.DictReader(f))[:limit]
    if not rows:
        raise FileNotFoundError(f"no faces listed in {root / 'labels.csv'}")
    imgs = np.stack([read_rgb(root / r["file"]) for r in rows])
    age = np.array([int(r["age"]) for r in rows])
    return {
        "images": imgs,
        "gender": np.array([int(r["gender"]) for r in rows]),
        "age_group": age_group(age),
        "race": np.array([int(r["race"]) for r in rows]),
    }
