"""CamVid street-scene segmentation (the paper's Cityscapes experiment, on CamVid).

A [`SensorLayer`][] in front of a network (480x360 images, 11 classes + void 11);
its logits are back-warped to 480x360 for the loss and for mIoU (void ignored). θ stays frozen
for the first ``freeze_epochs`` epochs, as in the paper; the uniform layout is the baseline. Two
networks (``--net``):

- ``small`` (the default): a compact PSPNet-style encoder–decoder that trains on a CPU, Adam,
  cosine schedule, horizontal flips.
- ``psp``: the paper's network and protocol, Zhao et al.'s PSPNet on a dilated ResNet-50
  ([`resnets`][layoutwarp.experiments.resnets]) with its auxiliary loss (weight 0.4), SGD with
  momentum 0.9, learning rate 0.01 with poly decay, weight decay 1e-4, batch 4, whole images
  through the sensor with horizontal flips and scale jitter (0.5–2.0; no rotation, as in the
  paper); fewer epochs than the paper's 200 (see [`PSP_CAMVID`][layoutwarp.experiments.protocols.PSP_CAMVID]).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from ..layouts import Layout
from ..sensor import SensorLayer
from .data import CAMVID_CLASSES, VOID, images_to_tensor, load_camvid
from .nets import conv_block, normalise_rgb
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
    "PALETTE",
    "CamVidTask",
    "SegNet",
    "median_frequency_weights",
    "predict_camvid",
]

#: The colour of every class (and of void, last) in figures, RGB.
PALETTE = np.array(
    [
        [128, 128, 128],
        [128, 0, 0],
        [192, 192, 128],
        [128, 64, 128],
        [60, 40, 222],
        [128, 128, 0],
        [192, 128, 128],
        [64, 64, 128],
        [64, 0, 128],
        [64, 64, 0],
        [0, 128, 192],
        [0, 0, 0],
    ],
    np.uint8,
)


class SegNet(nn.Module):
    """Sensor layer + a compact PSPNet-style encoder–decoder (~0.5 M parameters).

    Encoder 32-64-128 channels with two poolings, a pyramid pooling module (bins 1, 2, 4),
    and a decoder with skip connections back to the sensor grid. Returns ``(B, K, h, w)``
    logits on the sensor grid; back-warp them with `layoutwarp.backwarp`.
    """

    def __init__(
        self, layout: str, size: tuple[int, int], classes: int = 11, learn: bool | None = None, **sensor
    ):
        super().__init__()
        self.sensor = SensorLayer(size, layout, learn=learn, **sensor)
        self.enc1, self.enc2, self.enc3 = conv_block(3, 32), conv_block(32, 64), conv_block(64, 128)
        self.bins = (1, 2, 4)
        self.ppm = nn.ModuleList(
            nn.Sequential(nn.Conv2d(128, 32, 1, bias=False), nn.BatchNorm2d(32), nn.ReLU(inplace=True))
            for _ in self.bins
        )
        self.fuse = nn.Sequential(
            nn.Conv2d(128 + 32 * len(self.bins), 128, 1, bias=False),
            nn.BatchNorm2d(128),
            nn.ReLU(inplace=True),
        )
        self.dec2, self.dec1 = conv_block(128 + 64, 64), conv_block(64 + 32, 32)
        self.head = nn.Conv2d(32, classes, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """``(B, 3, H, W)`` images in [0, 1] (or uint8) to sensor-grid logits ``(B, K, h, w)``."""
        s = normalise_rgb(self.sensor(x))
        e1 = self.enc1(s)
        e2 = self.enc2(F.max_pool2d(e1, 2, ceil_mode=True))
        e3 = self.enc3(F.max_pool2d(e2, 2, ceil_mode=True))
        pyr = [e3] + [
            F.interpolate(
                m(F.adaptive_avg_pool2d(e3, b)), e3.shape[-2:], mode="bilinear", align_corners=False
            )
            for b, m in zip(self.bins, self.ppm, strict=True)
        ]
        d = self.fuse(torch.cat(pyr, 1))
        d = self.dec2(
            torch.cat([F.interpolate(d, e2.shape[-2:], mode="bilinear", align_corners=False), e2], 1)
        )
        d = self.dec1(
            torch.cat([F.interpolate(d, e1.shape[-2:], mode="bilinear", align_corners=False), e1], 1)
        )
        return self.head(d)


def median_frequency_weights(labels: np.ndarray, k: int, ignore: int = VOID) -> np.ndarray:
    """Median-frequency class balancing: ``w_c = median(f) / f_c`` (float32, ``(k,)``).

    ``f_c`` is the number of pixels of class ``c`` divided by the number of pixels of the
    images in which ``c`` appears (Eigen & Fergus 2015, as SegNet trains on CamVid); ``ignore``
    is left out, and a class absent from every image gets weight 0.

    Args:
        labels: ``(N, H, W)`` integer label maps.
        k: number of classes.
        ignore: label value that is not a class.
    """
    flat = labels.reshape(len(labels), -1)
    counts = np.stack([np.bincount(row[row != ignore], minlength=k)[:k] for row in flat])  # (N, k)
    valid = (flat != ignore).sum(1)
    present = counts > 0
    denom = (present * valid[:, None]).sum(0)
    freq = np.where(denom > 0, counts.sum(0) / np.maximum(denom, 1), 0.0)
    med = np.median(freq[freq > 0]) if (freq > 0).any() else 1.0
    return np.where(freq > 0, med / np.where(freq > 0, freq, 1.0), 0.0).astype(np.float32)


def predict_camvid(model: nn.Module, images: np.ndarray, batch_size: int = 8) -> torch.Tensor:
    """Back-warped full-resolution class predictions ``(N, H, W)`` int64 of ``(N, H, W, 3)``
    uint8 images ([`predict_labels`][])."""
    return predict_labels(model, images_to_tensor(images), batch_size)


@register_task
class CamVidTask(Task):
    """CamVid (train: ``train/``; report: ``val/``), mIoU, pixel accuracy and per-class IoU."""

    spec = SPECS["camvid"]

    def load(self, folder: Path, limit: int | None = None) -> TaskData:
        train, val = load_camvid(folder, "train", limit), load_camvid(folder, "val", limit)
        return TaskData(train, val, Path(folder), {"train": len(train[0]), "report": len(val[0])})

    def load_split(self, folder: Path, split: str | None) -> Any:
        return load_camvid(folder, split or "val")

    def density_images(self, data: TaskData) -> torch.Tensor:
        return torch.from_numpy(data.train[1]).float()  # label boundaries

    def scene(self, data: TaskData) -> np.ndarray:
        return data.report[0][0] / 255.0

    def network(
        self, layout: str | Layout, size: tuple[int, int], learn: bool | None = None, **sensor: Any
    ) -> nn.Module:
        net = PSPSegNet if self.net == "psp" else SegNet
        return net(layout, size, classes=len(CAMVID_CLASSES), learn=learn, **sensor)

    def batches(
        self, model: nn.Module, train: Any, gen: torch.Generator, options: dict[str, Any]
    ) -> tuple[torch.Tensor, BatchLoss]:
        device = model_device(model)
        x, y = images_to_tensor(train[0]), torch.from_numpy(train[1]).long()
        weight = None
        psp = self.net == "psp"
        if (options.get("class_weights") or ("none" if psp else "median")) == "median":
            weight = torch.from_numpy(median_frequency_weights(train[1], len(CAMVID_CLASSES))).to(device)

        def batch_loss(idx: torch.Tensor, net: nn.Module) -> torch.Tensor:
            xb, yb = x[idx].to(device).float().div_(255), y[idx].to(device)
            return augmented_loss(net, xb, yb, model.sensor.layout, gen, VOID, weight, jitter=psp)

        return torch.arange(len(x)), batch_loss

    def prediction_image(self, model: nn.Module, data: TaskData) -> np.ndarray | None:
        img, lab = data.report[0][0], data.report[1][0]
        pred = predict_camvid(model, img[None])[0].numpy()
        return PALETTE[np.where(lab == VOID, VOID, pred)]

    def legend(self) -> dict[str, tuple[int, int, int]]:
        return class_legend([*CAMVID_CLASSES, "void"], PALETTE)

    def score(self, model: nn.Module, part: Any) -> dict[str, Any]:
        """mIoU and pixel accuracy on ``part`` at full resolution, void ignored."""
        pred = predict_camvid(model, part[0])
        return segmentation_scores(
            confusion(pred, torch.from_numpy(part[1]).long(), len(CAMVID_CLASSES), VOID)
        )
