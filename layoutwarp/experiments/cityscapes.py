"""Cityscapes street-scene segmentation: the paper's headline experiment (its Table 2).

Reads the dataset as it is distributed (Cordts et al., CVPR 2016): images
``leftImg8bit/{train,val}/CITY/NAME_leftImg8bit.png`` (2048x1024 RGB) and fine labels
``gtFine/{train,val}/CITY/NAME_gtFine_labelIds.png`` (8-bit label ids), mapped to the 19
evaluation classes by the official table ([`LABEL_IDS`][]; every other id, void, is
[`IGNORE`][]). Images are read from disk batch by batch (the training split is 18 GB as
arrays).

The paper's protocol is the default: PSPNet on a dilated ResNet-50
([`PSPSegNet`][]), whole images through the sensor, the loss on outputs
back-warped to the labels' 2048x1024, batch 4, 200 epochs with θ frozen for the first 10, and
PSPNet's SGD (momentum 0.9, learning rate 0.01 with poly decay, weight decay 1e-4, auxiliary
loss 0.4) with flips and scale jitter (no rotation); sensors 129x65, 257x129 and 513x257; mIoU
and pixel accuracy on ``val``. Start the backbone from ImageNet weights with
``--backbone-weights FILE`` (nothing downloads at run time).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from ..layouts import Layout
from .protocols import SPECS
from .segmentation import (
    PSPSegNet,
    augmented_loss,
    class_legend,
    confusion,
    predict_labels,
    segmentation_scores,
)
from .tasks import Task, TaskData, register_task
from .training import BatchLoss, model_device

__all__ = [
    "CLASSES",
    "IGNORE",
    "LABEL_IDS",
    "PALETTE",
    "CityscapesTask",
    "find_pairs",
    "read_pairs",
    "train_ids",
]

#: The 19 evaluation classes, in train-id order.
CLASSES = (
    "road",
    "sidewalk",
    "building",
    "wall",
    "fence",
    "pole",
    "traffic light",
    "traffic sign",
    "vegetation",
    "terrain",
    "sky",
    "person",
    "rider",
    "car",
    "truck",
    "bus",
    "train",
    "motorcycle",
    "bicycle",
)
#: Each class's label id in ``*_gtFine_labelIds.png`` (cityscapesScripts' ``labels.py``).
LABEL_IDS = (7, 8, 11, 12, 13, 17, 19, 20, 21, 22, 23, 24, 25, 26, 27, 28, 31, 32, 33)
#: The train id of every other label id (void, and the classes left out of the evaluation).
IGNORE = 255
#: The classes' colours in figures (the official ones), RGB; void black, last.
PALETTE = np.array(
    [
        [128, 64, 128],
        [244, 35, 232],
        [70, 70, 70],
        [102, 102, 156],
        [190, 153, 153],
        [153, 153, 153],
        [250, 170, 30],
        [220, 220, 0],
        [107, 142, 35],
        [152, 251, 152],
        [70, 130, 180],
        [220, 20, 60],
        [255, 0, 0],
        [0, 0, 142],
        [0, 0, 70],
        [0, 60, 100],
        [0, 80, 100],
        [0, 0, 230],
        [119, 11, 32],
        [0, 0, 0],
    ],
    np.uint8,
)

_LUT = np.full(256, IGNORE, np.uint8)
_LUT[list(LABEL_IDS)] = np.arange(len(LABEL_IDS))


def train_ids(label_ids: np.ndarray) -> np.ndarray:
    """Label ids (uint8, any shape) to train ids ``0..18``, [`IGNORE`][] elsewhere."""
    return _LUT[label_ids]


def find_pairs(folder: str | Path, split: str) -> list[tuple[Path, Path]]:
    """Every ``(image, label ids)`` file pair of ``split`` under a Cityscapes folder, sorted.

    Raises:
        FileNotFoundError: no images of ``split``, or an image without its label file (named).
    """
    folder = Path(folder)
    images = sorted((folder / "leftImg8bit" / split).glob("*/*_leftImg8bit.png"))
    if not images:
        raise FileNotFoundError(f"no Cityscapes {split} images under {str(folder / 'leftImg8bit' / split)!r}")
    pairs = []
    for image in images:
        stem = image.name.removesuffix("_leftImg8bit.png")
        label = folder / "gtFine" / split / image.parent.name / f"{stem}_gtFine_labelIds.png"
        if not label.is_file():
            raise FileNotFoundError(f"{str(image)!r} has no label file {str(label)!r}")
        pairs.append((image, label))
    return pairs


def read_pairs(pairs: list[tuple[Path, Path]]) -> tuple[torch.Tensor, torch.Tensor]:
    """Images ``(N, 3, H, W)`` uint8 RGB and train ids ``(N, H, W)`` int64 of file pairs."""
    images, labels = [], []
    for image, label in pairs:
        bgr = cv2.imread(str(image), cv2.IMREAD_COLOR)
        ids = cv2.imread(str(label), cv2.IMREAD_UNCHANGED)
        if bgr is None or ids is None or ids.ndim != 2 or ids.shape != bgr.shape[:2]:
            raise ValueError(
                f"{str(image)!r}: unreadable, or its label file is not a single-channel map of its size"
            )
        images.append(torch.from_numpy(np.ascontiguousarray(bgr[..., ::-1].transpose(2, 0, 1))))
        labels.append(torch.from_numpy(train_ids(ids).astype(np.int64)))
    return torch.stack(images), torch.stack(labels)


@register_task
class CityscapesTask(Task):
    """Cityscapes (train: ``train``; report: ``val``), mIoU and pixel accuracy at 2048x1024."""

    spec = SPECS["cityscapes"]

    def load(self, folder: Path, limit: int | None = None) -> TaskData:
        train, val = find_pairs(folder, "train")[:limit], find_pairs(folder, "val")[:limit]
        return TaskData(train, val, Path(folder), {"train": len(train), "report": len(val)})

    def load_split(self, folder: Path, split: str | None) -> Any:
        return find_pairs(folder, split or "val")

    def density_images(self, data: TaskData) -> torch.Tensor:
        _, labels = read_pairs(data.train[:16])  # label boundaries, at a quarter of the resolution
        return F.interpolate(labels[:, None].float(), scale_factor=0.25, mode="nearest")[:, 0]

    def scene(self, data: TaskData) -> np.ndarray:
        images, _ = read_pairs(data.report[:1])
        return images[0].permute(1, 2, 0).numpy() / 255.0

    def network(
        self, layout: str | Layout, size: tuple[int, int], learn: bool | None = None, **sensor: Any
    ) -> nn.Module:
        return PSPSegNet(layout, size, classes=len(CLASSES), learn=learn, **sensor)

    def batches(
        self, model: nn.Module, train: Any, gen: torch.Generator, options: dict[str, Any]
    ) -> tuple[torch.Tensor, BatchLoss]:
        device = model_device(model)

        def batch_loss(idx: torch.Tensor, net: nn.Module) -> torch.Tensor:
            x, y = read_pairs([train[int(i)] for i in idx])
            xb, yb = x.to(device).float().div_(255), y.to(device)
            return augmented_loss(net, xb, yb, model.sensor.layout, gen, IGNORE)

        return torch.arange(len(train)), batch_loss

    def prediction_image(self, model: nn.Module, data: TaskData) -> np.ndarray | None:
        images, labels = read_pairs(data.report[:1])
        pred = predict_labels(model, images)[0].numpy()
        return PALETTE[np.where(labels[0].numpy() == IGNORE, len(CLASSES), pred)]

    def legend(self) -> dict[str, tuple[int, int, int]]:
        return class_legend([*CLASSES, "void"], PALETTE)

    def score(self, model: nn.Module, part: Any) -> dict[str, Any]:
        """mIoU and pixel accuracy on the file pairs ``part`` at the labels' resolution, void
        ignored (read and scored two images at a time)."""
        total = np.zeros((len(CLASSES), len(CLASSES)), np.int64)
        for k in range(0, len(part), 2):
            images, labels = read_pairs(part[k : k + 2])
            total += confusion(predict_labels(model, images, 2), labels, len(CLASSES), IGNORE)
        return segmentation_scores(total)
