"""CamVid street-scene segmentation (the paper's Cityscapes experiment, on CamVid).

A :class:`~layoutwarp.SensorLayer` in front of a network (480x360 images, 11 classes + void 11);
its logits are back-warped to 480x360 for the loss and for mIoU (void ignored). θ stays frozen
for the first ``freeze_epochs`` epochs, as in the paper; the uniform layout is the baseline. Two
networks (``--net``):

- ``small`` (the default): a compact PSPNet-style encoder–decoder that trains on a CPU, Adam,
  cosine schedule, horizontal flips.
- ``psp``: the paper's network and protocol, Zhao et al.'s PSPNet on a dilated ResNet-50
  (:mod:`~layoutwarp.experiments.resnets`) with its auxiliary loss (weight 0.4), SGD with
  momentum 0.9, learning rate 0.01 with poly decay, weight decay 1e-4, batch 4, whole images
  through the sensor with horizontal flips and scale jitter (0.5–2.0; no rotation, as in the
  paper); fewer epochs than the paper's 200 (see :data:`PSP_DEFAULTS`).
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from ..backwarp import backwarp, backwarp_cross_entropy
from ..layouts import Layout
from ..sensor import SensorLayer
from .data import CAMVID_CLASSES, VOID, images_to_tensor, load_camvid
from .nets import conv_block, normalise_rgb
from .resnets import AUX_WEIGHT, PSPNet, load_backbone
from .tasks import StudyPlan, Task, TaskData, TaskDefaults, register_task
from .training import BatchLoss, model_device

__all__ = [
    "IMAGENET_MEAN",
    "IMAGENET_STD",
    "PALETTE",
    "PSP_DEFAULTS",
    "CamVidTask",
    "PSPSegNet",
    "SegNet",
    "median_frequency_weights",
    "predict_camvid",
    "scale_jitter",
    "segmentation_scores",
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
    logits on the sensor grid; back-warp them with :func:`layoutwarp.backwarp`.
    """

    def __init__(self, layout: str, size: tuple[int, int], classes: int = 11, learn: bool = True, **sensor):
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


#: ImageNet's channel means and deviations, which a pretrained ResNet expects its inputs scaled by.
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


class PSPSegNet(nn.Module):
    """Sensor layer + PSPNet on a dilated ResNet-50 (:class:`~.resnets.PSPNet`): ``(B, 3, H, W)``
    images in [0, 1] to sensor-grid logits ``(B, K, h, w)``; in training mode ``(logits,
    aux_logits)``. The sensor's values are scaled by ImageNet's statistics, as a pretrained
    backbone expects (:meth:`load_backbone`)."""

    def __init__(
        self, layout: str | Layout, size: tuple[int, int], classes: int = 11, learn: bool = True, **sensor
    ):
        super().__init__()
        self.sensor = SensorLayer(size, layout, learn=learn, **sensor)
        self.psp = PSPNet(classes)
        self.register_buffer("mean", torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(IMAGENET_STD).view(1, 3, 1, 1), persistent=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor | tuple[torch.Tensor, torch.Tensor]:
        return self.psp((self.sensor(x) - self.mean) / self.std)

    def load_backbone(self, path: str | Path) -> None:
        """Start the ResNet-50 from a torchvision-format state dict (:func:`~.resnets.load_backbone`)."""
        load_backbone(self.psp.backbone, path)


def scale_jitter(
    x: torch.Tensor,
    y: torch.Tensor,
    gen: torch.Generator,
    lo: float = 0.5,
    hi: float = 2.0,
    ignore: int = VOID,
) -> tuple[torch.Tensor, torch.Tensor]:
    """PSPNet's random scaling for whole images: images ``(B, 3, H, W)`` and labels ``(B, H, W)``
    scaled by one factor drawn uniformly from ``[lo, hi]`` (bilinear; labels nearest), then cut
    back to ``H x W`` at a random place where larger, or padded where smaller (images with
    :data:`IMAGENET_MEAN`, labels with ``ignore``), so the sensor always sees a whole frame."""
    h, w = x.shape[-2:]
    s = lo + (hi - lo) * float(torch.rand((), generator=gen))
    sh, sw = max(1, round(h * s)), max(1, round(w * s))
    xs = F.interpolate(x, (sh, sw), mode="bilinear", align_corners=False)
    ys = F.interpolate(y[:, None].float(), (sh, sw), mode="nearest")[:, 0].to(y.dtype)
    ox = int(torch.randint(0, abs(sw - w) + 1, (), generator=gen))
    oy = int(torch.randint(0, abs(sh - h) + 1, (), generator=gen))
    if s >= 1:
        return xs[..., oy : oy + h, ox : ox + w], ys[..., oy : oy + h, ox : ox + w]
    xo = (
        torch.tensor(IMAGENET_MEAN, dtype=x.dtype, device=x.device)
        .view(1, 3, 1, 1)
        .expand(len(x), 3, h, w)
        .clone()
    )
    yo = torch.full((len(y), h, w), ignore, dtype=y.dtype, device=y.device)
    xo[..., oy : oy + sh, ox : ox + sw], yo[..., oy : oy + sh, ox : ox + sw] = xs, ys
    return xo, yo


def segmentation_scores(confusion: np.ndarray) -> dict:
    """mIoU, pixel accuracy and per-class IoU (percent) from a ``(K, K)`` confusion matrix.

    Rows are ground truth, columns predictions; classes absent from both are left out of
    the mean.
    """
    tp = np.diag(confusion).astype(np.float64)
    denom = confusion.sum(0) + confusion.sum(1) - tp
    iou = np.where(denom > 0, tp / np.maximum(denom, 1), np.nan)
    return {
        "miou": float(np.nanmean(iou) * 100),
        "pixel_accuracy": float(tp.sum() / max(confusion.sum(), 1) * 100),
        "iou": [None if np.isnan(v) else float(v * 100) for v in iou],
    }


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


def _confusion(pred: torch.Tensor, labels: torch.Tensor, k: int, ignore: int) -> np.ndarray:
    keep = labels != ignore
    idx = labels[keep].long() * k + pred[keep].long()
    return torch.bincount(idx, minlength=k * k).reshape(k, k).numpy()


@torch.no_grad()
def predict_camvid(model: SegNet, images: np.ndarray, batch_size: int = 8) -> torch.Tensor:
    """Back-warped full-resolution class predictions ``(N, H, W)`` int64."""
    model.eval()
    x = images_to_tensor(images)
    out = []
    for k in range(0, len(x), batch_size):
        logits = model(x[k : k + batch_size].to(model_device(model)).float().div(255))
        out.append(backwarp(logits.argmax(1), model.sensor.layout, tuple(x.shape[-2:])).cpu())
    return torch.cat(out)


#: The PSP protocol on CamVid (``--net psp``): the paper's optimiser, schedule and batch, and
#: its θ frozen for the first 5 % of the epochs (10 of 200); 20 epochs, about an hour a run on
#: 2 CPU cores at 96x72 (a training epoch 2–4 minutes), where the paper trains 200 on
#: Cityscapes. No class weights unless asked.
PSP_DEFAULTS = TaskDefaults(
    families=("uniform", "rect", "curv"),
    sizes=((72, 96),),
    seeds=3,
    epochs=20,
    batch_size=4,
    lr=0.01,
    theta_lr=0.01,
    tol=1e-3,
    freeze_epochs=1,
    schedule="poly",
    optimizer="sgd",
    weight_decay=1e-4,
)


@register_task
class CamVidTask(Task):
    """CamVid (train: ``train/``; report: ``val/``), mIoU, pixel accuracy and per-class IoU."""

    name = "camvid"
    folder = "camvid"
    description = "CamVid street-scene segmentation, back-warped to full resolution"
    metrics = ("miou", "pixel_accuracy")
    metric_label = "val mIoU (%)"
    image_size = (360, 480)
    report_split = "val"
    defaults = TaskDefaults(
        families=("uniform", "curv", "rect"),
        sizes=((36, 48), (72, 96)),
        seeds=2,
        epochs=12,
        batch_size=8,
        lr=2e-3,
        theta_lr=0.01,
        tol=1e-3,
        freeze_epochs=3,
        schedule="cosine",
    )
    quick: ClassVar[dict[str, Any]] = {"epochs": 1}
    study = StudyPlan(
        ((18, 24), (27, 36), (36, 48), (54, 72), (72, 96), (90, 120)),
        ((36, 48), (72, 96)),
    )
    nets: ClassVar[dict[str, dict[str, Any]]] = {
        "small": {},
        "psp": {
            "defaults": PSP_DEFAULTS,
            "study": StudyPlan(((72, 96),), ((72, 96),), families=("rect", "curv")),
            "quick": {"epochs": 1},
        },
    }

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
        self, layout: str | Layout, size: tuple[int, int], learn: bool = True, **sensor: Any
    ) -> nn.Module:
        net = PSPSegNet if self.net == "psp" else SegNet
        return net(layout, size, classes=len(CAMVID_CLASSES), learn=learn, **sensor)

    def add_arguments(self, parser: argparse.ArgumentParser) -> None:
        parser.add_argument(
            "--class-weights",
            choices=["none", "median"],
            help="loss class weights: none or median-frequency balancing (default: median with the small "
            "network, none with psp, as PSPNet trains)",
        )

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
            if bool(torch.rand((), generator=gen) < 0.5):  # horizontal flip
                xb, yb = xb.flip(-1), yb.flip(-1)
            if psp:
                xb, yb = scale_jitter(xb, yb, gen)
            out = net(xb)
            logits, aux = out if isinstance(out, tuple) else (out, None)
            layout = model.sensor.layout
            loss = backwarp_cross_entropy(logits, yb, layout, ignore_index=VOID, weight=weight)
            if aux is not None:
                loss = loss + AUX_WEIGHT * backwarp_cross_entropy(
                    aux, yb, layout, ignore_index=VOID, weight=weight
                )
            return loss

        return torch.arange(len(x)), batch_loss

    def prediction_image(self, model: nn.Module, data: TaskData) -> np.ndarray | None:
        img, lab = data.report[0][0], data.report[1][0]
        pred = predict_camvid(model, img[None])[0].numpy()
        return PALETTE[np.where(lab == VOID, VOID, pred)]

    def legend(self) -> dict[str, tuple[int, int, int]]:
        names = [*CAMVID_CLASSES, "void"]
        return {n: tuple(int(v) for v in c) for n, c in zip(names, PALETTE, strict=True)}

    def score(self, model: nn.Module, part: Any) -> dict[str, Any]:
        """mIoU and pixel accuracy on ``part`` at full resolution, void ignored."""
        pred = predict_camvid(model, part[0])
        return segmentation_scores(
            _confusion(pred, torch.from_numpy(part[1]).long(), len(CAMVID_CLASSES), VOID)
        )
