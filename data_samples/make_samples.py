"""Rebuild data_samples/ from a full copy of the data (kept for provenance).

Usage: python data_samples/make_samples.py /path/to/shared/data

Takes, in their original order: the first 4000 MNIST training and 1000 test digits
(re-written as gzip IDX files), the first 6 CamVid train and 3 val image/annotation
pairs, the first 64 UTKFace faces of labels.csv, and the Kodak photos kodim03 and kodim20.
"""

from __future__ import annotations

import csv
import gzip
import shutil
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent


def _idx_head(src: Path, dst: Path, count: int) -> None:
    data = gzip.open(src, "rb").read()
    ndim = data[3]
    dims = [int.from_bytes(data[4 + 4 * i : 8 + 4 * i], "big") for i in range(ndim)]
    item = 1
    for d in dims[1:]:
        item *= d
    header = bytearray(data[: 4 + 4 * ndim])
    header[4:8] = count.to_bytes(4, "big")
    body = data[4 + 4 * ndim : 4 + 4 * ndim + count * item]
    with gzip.GzipFile(dst, "wb", mtime=0) as f:
        f.write(bytes(header) + body)


def main(root: Path) -> None:
    (HERE / "mnist").mkdir(exist_ok=True)
    for split, n in (("train", 4000), ("t10k", 1000)):
        for kind in ("images-idx3", "labels-idx1"):
            name = f"{split}-{kind}-ubyte.gz"
            _idx_head(root / "mnist" / name, HERE / "mnist" / name, n)
    for split, n in (("train", 6), ("val", 3)):
        for sub in (split, split + "annot"):
            (HERE / "camvid" / sub).mkdir(parents=True, exist_ok=True)
        for name in sorted((root / "camvid" / split).iterdir())[:n]:
            shutil.copy(name, HERE / "camvid" / split / name.name)
            shutil.copy(
                root / "camvid" / (split + "annot") / name.name,
                HERE / "camvid" / (split + "annot") / name.name,
            )
    shutil.copy(root / "camvid" / "CLASSES.txt", HERE / "camvid" / "CLASSES.txt")
    faces = HERE / "faces" / "utkface_subset"
    (faces / "images").mkdir(parents=True, exist_ok=True)
    rows = list(csv.DictReader(open(root / "faces" / "utkface_subset" / "labels.csv")))[:64]
    for r in rows:
        shutil.copy(root / "faces" / "utkface_subset" / r["file"], faces / r["file"])
    with open(faces / "labels.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    (HERE / "photos").mkdir(exist_ok=True)
    for name in ("kodim03.png", "kodim20.png"):
        shutil.copy(root / "photos" / "kodak24" / name, HERE / "photos" / name)


if __name__ == "__main__":
    main(Path(sys.argv[1]))
