"""CelebA face attributes: the paper's multi-label experiment (its Table 3).

Reads the dataset as it is distributed (Liu et al., ICCV 2015): the aligned faces
``img_align_celeba/NNNNNN.jpg`` (178x218), ``list_attr_celeba.txt`` (the count, the 40
attribute names, then a file name and 40 values ±1 a line) and ``list_eval_partition.txt`` (a
file name and 0 train, 1 val, 2 test a line). Images are read from disk batch by batch.

The paper's protocol is the default: ResNet-18 ([`SensorResNet`][], 40 outputs, a
binary cross-entropy each) behind 8x8 and 16x16 sensors, Adam with learning rate 1e-3, batch
64, 15 epochs, the rect layout against uniform; the score is the mean accuracy over the 40
attributes on ``test``. The paper fine-tunes from ImageNet weights: pass them with
``--backbone-weights FILE`` (nothing downloads at run time).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from ..layouts import Layout
from .faces import SensorResNet
from .protocols import SPECS
from .tasks import Task, TaskData, register_task
from .training import BatchLoss, model_device

__all__ = ["PARTITIONS", "CelebAPart", "CelebATask", "read_attributes", "read_celeba", "read_partition"]

#: ``list_eval_partition.txt``'s codes.
PARTITIONS = {"train": 0, "val": 1, "test": 2}


def read_attributes(path: str | Path) -> tuple[list[str], list[str], np.ndarray]:
    """``list_attr_celeba.txt``: the attribute names, the file names and their values as 0/1
    ``(N, A)`` uint8 (the file's ±1; its first line's count is not checked against the rows, so
    a file cut short still reads).

    Raises:
        ValueError: a row with another number of values than names, or a value not ±1 (named).
    """
    path = Path(path)
    lines = path.read_text().splitlines()
    if len(lines) < 2:
        raise ValueError(f"{str(path)!r}: not a CelebA attribute file (no count and names lines)")
    names = lines[1].split()
    files, rows = [], []
    for number, line in enumerate(lines[2:], start=3):
        parts = line.split()
        if not parts:
            continue
        if len(parts) != len(names) + 1 or any(v not in ("1", "-1") for v in parts[1:]):
            raise ValueError(f"{path!s}:{number}: expected a file name and {len(names)} values of ±1")
        files.append(parts[0])
        rows.append([v == "1" for v in parts[1:]])
    return names, files, np.array(rows, np.uint8).reshape(len(files), len(names))


def read_partition(path: str | Path) -> dict[str, int]:
    """``list_eval_partition.txt``: each file name's partition (0 train, 1 val, 2 test)."""
    out = {}
    for number, line in enumerate(Path(path).read_text().splitlines(), start=1):
        parts = line.split()
        if not parts:
            continue
        if len(parts) != 2 or parts[1] not in ("0", "1", "2"):
            raise ValueError(f"{path}:{number}: expected a file name and 0, 1 or 2")
        out[parts[0]] = int(parts[1])
    return out


@dataclass
class CelebAPart:
    """One partition: image files and their attributes ``(N, 40)`` 0/1."""

    files: list[Path]
    attributes: np.ndarray
    names: list[str]

    def __len__(self) -> int:
        return len(self.files)

    def images(self, index: slice | list[int]) -> torch.Tensor:
        """The images at ``index`` as ``(n, 3, 218, 178)`` uint8 RGB, read from disk."""
        files = self.files[index] if isinstance(index, slice) else [self.files[i] for i in index]
        out = []
        for f in files:
            bgr = cv2.imread(str(f), cv2.IMREAD_COLOR)
            if bgr is None:
                raise ValueError(f"{str(f)!r}: not a readable image")
            out.append(torch.from_numpy(np.ascontiguousarray(bgr[..., ::-1].transpose(2, 0, 1))))
        return torch.stack(out)


def read_celeba(folder: str | Path, split: str, limit: int | None = None) -> CelebAPart:
    """The faces of partition ``split`` (``train``, ``val`` or ``test``) of a CelebA folder.

    Raises:
        FileNotFoundError: a list file, or an image it names, is missing.
        ValueError: ``split`` is not a partition.
    """
    if split not in PARTITIONS:
        raise ValueError(f"split must be one of {', '.join(PARTITIONS)}; got {split!r}")
    folder = Path(folder)
    for name in ("list_attr_celeba.txt", "list_eval_partition.txt", "img_align_celeba"):
        if not (folder / name).exists():
            raise FileNotFoundError(
                f"no {name} in {str(folder)!r} (a CelebA folder holds img_align_celeba/ and the two lists)"
            )
    names, files, values = read_attributes(folder / "list_attr_celeba.txt")
    partition = read_partition(folder / "list_eval_partition.txt")
    keep = [i for i, f in enumerate(files) if partition.get(f) == PARTITIONS[split]][:limit]
    paths = [folder / "img_align_celeba" / files[i] for i in keep]
    missing = next((p for p in paths if not p.is_file()), None)
    if missing is not None:
        raise FileNotFoundError(f"{str(missing)!r} is listed but missing")
    return CelebAPart(paths, values[keep], names)


@register_task
class CelebATask(Task):
    """CelebA (train: ``train``; report: ``test``), mean accuracy over the 40 attributes."""

    spec = SPECS["celeba"]

    def load(self, folder: Path, limit: int | None = None) -> TaskData:
        train, test = read_celeba(folder, "train", limit), read_celeba(folder, "test", limit)
        return TaskData(train, test, Path(folder), {"train": len(train), "report": len(test)})

    def load_split(self, folder: Path, split: str | None) -> Any:
        return read_celeba(folder, split or "test")

    def density_images(self, data: TaskData) -> torch.Tensor:
        return data.train.images(slice(0, 500)).float()

    def scene(self, data: TaskData) -> np.ndarray:
        return data.train.images(slice(0, 200)).float().mean(0).permute(1, 2, 0).numpy() / 255.0

    def network(
        self, layout: str | Layout, size: tuple[int, int], learn: bool | None = None, **sensor: Any
    ) -> nn.Module:
        return SensorResNet(layout, size, 40, learn=learn, **sensor)

    def batches(
        self, model: nn.Module, train: Any, gen: torch.Generator, options: dict[str, Any]
    ) -> tuple[torch.Tensor, BatchLoss]:
        device = model_device(model)
        targets = torch.from_numpy(train.attributes).float()

        def batch_loss(idx: torch.Tensor, net: nn.Module) -> torch.Tensor:
            xb = train.images(idx.tolist()).to(device).float().div_(255)
            if bool(torch.rand((), generator=gen) < 0.5):  # horizontal flip
                xb = xb.flip(-1)
            return F.binary_cross_entropy_with_logits(net(xb), targets[idx].to(device))

        return torch.arange(len(train)), batch_loss

    @torch.no_grad()
    def score(self, model: nn.Module, part: Any, batch_size: int = 256) -> dict[str, Any]:
        """Accuracy (percent) per attribute and their mean (``mean``)."""
        model.eval()
        correct = np.zeros(len(part.names))
        for k in range(0, len(part), batch_size):
            logits = model(part.images(slice(k, k + batch_size)).to(model_device(model)).float().div(255))
            truth = torch.from_numpy(part.attributes[k : k + batch_size]).bool()
            correct += ((logits.cpu() > 0) == truth).sum(0).numpy()
        acc = 100.0 * correct / max(len(part), 1)
        return {"mean": float(acc.mean()), **{n: float(a) for n, a in zip(part.names, acc, strict=True)}}
