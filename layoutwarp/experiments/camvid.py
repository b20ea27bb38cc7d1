"""CamVid street-scene segmentation (the paper's Cityscapes experiment, on CamVid).

A :class:`~layoutwarp.SensorLayer` in front of a compact PSPNet-style network that trains on
a CPU (480x360, 11 classes + void 11); its logits are back-warped to 480x360 for the loss
and for mIoU (void ignored). θ stays frozen for the first ``freeze_epochs`` epochs, as in
the paper; the uniform layout is the baseline.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from ..backwarp import backwarp, backwarp_cross_entropy
from ..layoutfile import save_layout
from ..sensor import SensorLayer
from .data import CAMVID_CLASSES, VOID, load_camvid
from .training import (
    ExperimentDefaults,
    TaskRun,
    fit,
    layout_name,
    model_device,
    optimizer,
    run_grid,
    save_runs,
    theta_text,
)

__all__ = [
    "DEFAULTS",
    "SegNet",
    "evaluate_camvid",
    "median_frequency_weights",
    "predict_camvid",
    "run_camvid_experiment",
    "segmentation_scores",
    "train_camvid",
]

DEFAULTS = ExperimentDefaults(
    task="camvid",
    shared="camvid",
    sample="camvid",
    families=("uniform", "curv", "rect"),
    sizes=((36, 48), (72, 96)),
    seeds=2,
    epochs=12,
    quick_epochs=1,
    tol=1e-3,
    freeze_epochs=3,
)
RGB_MEAN = torch.tensor([0.45, 0.45, 0.45]).view(1, 3, 1, 1)
RGB_STD = torch.tensor([0.28, 0.28, 0.28]).view(1, 3, 1, 1)


def normalise_rgb(s: torch.Tensor) -> torch.Tensor:
    """Sensor values ``(B, 3, h, w)`` centred and scaled for the networks (on ``s``'s device)."""
    return (s - RGB_MEAN.to(s)) / RGB_STD.to(s)


def to_tensor(imgs: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(imgs).permute(0, 3, 1, 2).contiguous()  # uint8 (N, 3, H, W)


def conv_block(cin: int, cout: int) -> nn.Sequential:
    return nn.Sequential(
        nn.Conv2d(cin, cout, 3, padding=1, bias=False),
        nn.BatchNorm2d(cout),
        nn.ReLU(inplace=True),
        nn.Conv2d(cout, cout, 3, padding=1, bias=False),
        nn.BatchNorm2d(cout),
        nn.ReLU(inplace=True),
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


def train_camvid(
    train: tuple[np.ndarray, np.ndarray],
    val: tuple[np.ndarray, np.ndarray],
    layout: str,
    size: tuple[int, int],
    *,
    seed: int = 0,
    epochs: int = DEFAULTS.epochs,
    freeze_epochs: int = DEFAULTS.freeze_epochs,
    batch_size: int = 8,
    lr: float = 2e-3,
    theta_lr: float = 0.01,
    progress: bool = True,
    sensor: dict | None = None,
    class_weights: str = "median",
    device: str | torch.device = "cpu",
    amp: bool = False,
) -> tuple[TaskRun, SegNet]:
    """Train sensor + SegNet on CamVid ``train`` and score it on ``val`` (back-warped to full size).

    ``class_weights``: ``"none"`` (plain cross-entropy) or ``"median"``
    (:func:`median_frequency_weights` of the training labels).
    """
    if class_weights not in ("none", "median"):
        raise ValueError(f"class_weights must be 'none' or 'median', got {class_weights!r}")
    torch.manual_seed(seed)
    gen = torch.Generator().manual_seed(seed)
    model = SegNet(layout, size, learn=layout != "uniform", **(sensor or DEFAULTS.sensor())).to(device)
    opt = optimizer(model, lr, theta_lr)
    x, y = to_tensor(train[0]), torch.from_numpy(train[1]).long()
    weight = None
    if class_weights == "median":
        weight = torch.from_numpy(median_frequency_weights(train[1], len(CAMVID_CLASSES))).to(device)

    def batch_loss(idx: torch.Tensor, net: nn.Module) -> torch.Tensor:
        xb, yb = x[idx].to(device).float().div_(255), y[idx].to(device)
        if bool(torch.rand((), generator=gen) < 0.5):  # horizontal flip
            xb, yb = xb.flip(-1), yb.flip(-1)
        return backwarp_cross_entropy(net(xb), yb, model.sensor.layout, ignore_index=VOID, weight=weight)

    t0 = time.perf_counter()
    history = fit(
        model,
        torch.arange(len(x)),
        batch_loss,
        opt,
        gen,
        epochs=epochs,
        batch_size=batch_size,
        freeze_epochs=freeze_epochs,
        sched=torch.optim.lr_scheduler.CosineAnnealingLR(opt, max(epochs, 1)),
        desc=f"camvid {layout_name(layout)} {size[1]}x{size[0]} seed {seed}",
        progress=progress,
        amp=amp,
    )
    scores = evaluate_camvid(model, val)
    run = TaskRun(
        "camvid", layout_name(layout), list(size), seed, scores, model.sensor.theta.detach().tolist(), history
    )
    run.seconds = time.perf_counter() - t0
    return run, model


@torch.no_grad()
def predict_camvid(model: SegNet, images: np.ndarray, batch_size: int = 8) -> torch.Tensor:
    """Back-warped full-resolution class predictions ``(N, H, W)`` int64."""
    model.eval()
    x = to_tensor(images)
    out = []
    for k in range(0, len(x), batch_size):
        logits = model(x[k : k + batch_size].to(model_device(model)).float().div(255))
        out.append(backwarp(logits.argmax(1), model.sensor.layout, tuple(x.shape[-2:])).cpu())
    return torch.cat(out)


def evaluate_camvid(model: SegNet, val: tuple[np.ndarray, np.ndarray]) -> dict:
    """mIoU and pixel accuracy on ``val`` at full resolution, void ignored."""
    pred = predict_camvid(model, val[0])
    return segmentation_scores(_confusion(pred, torch.from_numpy(val[1]).long(), len(CAMVID_CLASSES), VOID))


def run_camvid_experiment(
    data_dir: str | Path,
    out: str | Path,
    families: tuple[str, ...] = DEFAULTS.families,
    sizes: tuple[tuple[int, int], ...] = DEFAULTS.sizes,
    seeds: tuple[int, ...] = tuple(range(DEFAULTS.seeds)),
    epochs: int = DEFAULTS.epochs,
    freeze_epochs: int = DEFAULTS.freeze_epochs,
    limit: int | None = None,
    progress: bool = True,
    sensor: dict | None = None,
    class_weights: str = "median",
    device: str | torch.device = "cpu",
    amp: bool = False,
) -> dict:
    """Every family × sensor size × seed on CamVid; writes results.json, layouts and figures."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    sensor = sensor or DEFAULTS.sensor()
    train, val = load_camvid(data_dir, "train", limit), load_camvid(data_dir, "val", limit)
    configs = [(f, tuple(size), seed) for size in sizes for f in families for seed in seeds]
    models = run_grid(
        "camvid",
        out,
        configs,
        lambda layout, size, seed: train_camvid(
            train,
            val,
            layout,
            size,
            seed=seed,
            epochs=epochs,
            freeze_epochs=min(freeze_epochs, max(epochs - 1, 0)),
            progress=progress,
            sensor=sensor,
            class_weights=class_weights,
            device=device,
            amp=amp,
        ),
        sensor=sensor,
        training={"epochs": epochs, "class_weights": class_weights},
        describe=lambda run: (
            f"mIoU {run.scores['miou']:5.2f}%  pixel acc {run.scores['pixel_accuracy']:5.2f}%"
        ),
        save=lambda runs: save_runs(
            out,
            "camvid",
            data_dir,
            len(train[0]),
            len(val[0]),
            epochs,
            runs,
            ("miou", "pixel_accuracy"),
            sensor,
            class_weights=class_weights,
        ),
    )
    for (layout, size), model in models.items():
        save_layout(
            model.sensor.layout,
            out / f"layout_{layout}_{size[1]}x{size[0]}.json",
            size=size,
            experiment="camvid",
        )
    _camvid_figures(val, models, out)
    return json.loads((out / "results.json").read_text())


def _camvid_figures(val, models: dict, out: Path) -> None:
    """Fig. 5 analogue (layouts over a street scene) and back-warped example predictions."""
    from .plots import draw_layout, figure, save_figure

    models = {key: model.cpu() for key, model in models.items()}  # figures are drawn on the CPU

    img, lab = val[0][0], val[1][0]
    palette = np.array(
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
    keys = list(models)
    fig, axes = figure(3, len(keys), figsize=(3.6 * len(keys), 8.2), squeeze=False)
    for k, (layout, size) in enumerate(keys):
        model = models[(layout, size)]
        draw_layout(axes[0, k], model.sensor.layout, size, image=img / 255.0, max_lines=32, lw=0.5)
        axes[0, k].set_title(f"{layout} {size[1]}x{size[0]} {theta_text(model)}", fontsize=8)
        with torch.no_grad():
            s = (
                model.sensor(torch.from_numpy(img).permute(2, 0, 1)[None].float() / 255)[0]
                .permute(1, 2, 0)
                .numpy()
            )
        axes[1, k].imshow(np.clip(s, 0, 1), interpolation="nearest")
        axes[1, k].set_title("sensor image", fontsize=8)
        pred = predict_camvid(model, img[None])[0].numpy()
        axes[2, k].imshow(palette[np.where(lab == VOID, VOID, pred)])
        axes[2, k].set_title("back-warped prediction", fontsize=8)
        for ax in axes[1:, k]:
            ax.set_xticks([])
            ax.set_yticks([])
    save_figure(fig, out / "camvid_layouts.png", dpi=100)
