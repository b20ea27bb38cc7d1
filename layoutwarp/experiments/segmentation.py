"""What the segmentation tasks (CamVid, Cityscapes) share: the paper's PSPNet behind a sensor,
its loss on back-warped outputs, PSPNet's scale jitter for whole images and a training batch's
augmented loss, predictions at the labels' resolution, the scores (mIoU, pixel accuracy) and the
classes' legend.

Shapes: images ``(B, 3, H, W)`` in [0, 1] (uint8 for [`predict_labels`][]), label maps
``(B, H, W)`` int64 with one ``ignore`` value, logits ``(B, K, h, w)`` on the sensor grid.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from ..backwarp import backwarp, backwarp_cross_entropy
from ..layouts import Layout
from ..sensor import SensorLayer
from .resnets import AUX_WEIGHT, IMAGENET_MEAN, IMAGENET_STD, PSPNet, load_backbone
from .training import model_device

__all__ = [
    "PSPSegNet",
    "augmented_loss",
    "class_legend",
    "confusion",
    "predict_labels",
    "scale_jitter",
    "segmentation_loss",
    "segmentation_scores",
]


class PSPSegNet(nn.Module):
    """Sensor layer + PSPNet on a dilated ResNet-50 ([`PSPNet`][]): ``(B, 3, H, W)``
    images in [0, 1] to sensor-grid logits ``(B, K, h, w)``; in training mode ``(logits,
    aux_logits)``. The sensor's values are scaled by ImageNet's statistics, as a pretrained
    backbone expects ([`load_backbone`][])."""

    def __init__(
        self,
        layout: str | Layout,
        size: tuple[int, int],
        classes: int = 11,
        learn: bool | None = None,
        **sensor,
    ):
        super().__init__()
        self.sensor = SensorLayer(size, layout, learn=learn, **sensor)
        self.psp = PSPNet(classes)
        self.register_buffer("mean", torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(IMAGENET_STD).view(1, 3, 1, 1), persistent=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor | tuple[torch.Tensor, torch.Tensor]:
        return self.psp((self.sensor(x) - self.mean) / self.std)

    def load_backbone(self, path: str | Path) -> None:
        """Start the ResNet-50 from a torchvision-format state dict ([`load_backbone`][])."""
        load_backbone(self.psp.backbone, path)


def scale_jitter(
    x: torch.Tensor,
    y: torch.Tensor,
    gen: torch.Generator,
    lo: float = 0.5,
    hi: float = 2.0,
    ignore: int = 255,
) -> tuple[torch.Tensor, torch.Tensor]:
    """PSPNet's random scaling for whole images: images ``(B, 3, H, W)`` and labels ``(B, H, W)``
    scaled by one factor drawn uniformly from ``[lo, hi]`` (bilinear; labels nearest), then cut
    back to ``H x W`` at a random place where larger, or padded where smaller (images with
    [`IMAGENET_MEAN`][], labels with ``ignore``), so the sensor always sees a whole frame."""
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


def confusion(pred: torch.Tensor, labels: torch.Tensor, k: int, ignore: int) -> np.ndarray:
    keep = labels != ignore
    idx = labels[keep].long() * k + pred[keep].long()
    return torch.bincount(idx, minlength=k * k).reshape(k, k).numpy()


def segmentation_loss(
    out: torch.Tensor | tuple[torch.Tensor, torch.Tensor],
    labels: torch.Tensor,
    layout: Layout,
    ignore: int,
    weight: torch.Tensor | None = None,
) -> torch.Tensor:
    """Cross-entropy of sensor-grid logits back-warped to the labels' resolution (the paper's
    loss), ``ignore`` left out; with ``out`` a training-mode [`PSPSegNet`][]'s ``(logits,
    aux_logits)``, plus [`AUX_WEIGHT`][layoutwarp.experiments.resnets.AUX_WEIGHT] times the auxiliary
    head's."""
    logits, aux = out if isinstance(out, tuple) else (out, None)
    loss = backwarp_cross_entropy(logits, labels, layout, ignore_index=ignore, weight=weight)
    if aux is not None:
        loss = loss + AUX_WEIGHT * backwarp_cross_entropy(
            aux, labels, layout, ignore_index=ignore, weight=weight
        )
    return loss


def augmented_loss(
    net: nn.Module,
    x: torch.Tensor,
    y: torch.Tensor,
    layout: Layout,
    gen: torch.Generator,
    ignore: int,
    weight: torch.Tensor | None = None,
    jitter: bool = True,
) -> torch.Tensor:
    """A training batch's [`segmentation_loss`][]: images ``x`` (float, in ``[0, 1]``) and
    labels ``y`` flipped left to right with probability 1/2 and, with ``jitter``, scaled by
    [`scale_jitter`][] (padding labels with ``ignore``), both drawn from ``gen``."""
    if bool(torch.rand((), generator=gen) < 0.5):  # horizontal flip
        x, y = x.flip(-1), y.flip(-1)
    if jitter:
        x, y = scale_jitter(x, y, gen, ignore=ignore)
    return segmentation_loss(net(x), y, layout, ignore, weight)


def class_legend(names: Sequence[str], palette: np.ndarray) -> dict[str, tuple[int, int, int]]:
    """Each class's colour in figures, by name (``names`` and ``palette``'s rows in step)."""
    return {n: tuple(int(v) for v in c) for n, c in zip(names, palette, strict=True)}


@torch.no_grad()
def predict_labels(model: nn.Module, images: torch.Tensor, batch_size: int = 8) -> torch.Tensor:
    """Class predictions ``(N, H, W)`` int64 at the images' resolution: ``model`` (in eval mode)
    on uint8 ``images`` ``(N, 3, H, W)``, its sensor-grid argmax back-warped."""
    model.eval()
    out = []
    for k in range(0, len(images), batch_size):
        logits = model(images[k : k + batch_size].to(model_device(model)).float().div(255))
        out.append(backwarp(logits.argmax(1), model.sensor.layout, tuple(images.shape[-2:])).cpu())
    return torch.cat(out)
