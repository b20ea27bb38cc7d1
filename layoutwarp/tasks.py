"""Dense and multi-label tasks (paper §5 substitutes): CamVid segmentation, UTKFace attributes.

Both put a :class:`~layoutwarp.SensorLayer` in front of a compact network that trains on a
CPU and compare a uniform sensor (θ frozen at 0) with learned layouts.

* CamVid (480x360, 11 classes + void 11): a small PSPNet-style encoder–decoder on the sensor
  grid; its logits are back-warped to 480x360 for the loss and for mIoU (void ignored).
  θ stays frozen for the first ``freeze_epochs`` epochs, as in the paper.
* UTKFace (200x200 faces): gender (2 classes), age group (:data:`AGE_GROUPS`) and race (5)
  from an 8x8 or 16x16 sensor, one head each; accuracies per attribute and their mean.
"""

from __future__ import annotations

import csv
import json
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import ClassVar

import cv2
import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from .backwarp import backwarp, backwarp_cross_entropy
from .io import atomic_write, save_layout
from .sensor import SensorLayer
from .train import fit

__all__ = [
    "AGE_GROUPS",
    "CAMVID_CLASSES",
    "FaceNet",
    "SegNet",
    "load_camvid",
    "load_faces",
    "median_frequency_weights",
    "run_camvid_experiment",
    "run_faces_experiment",
    "segmentation_scores",
]

CAMVID_CLASSES = "Sky Building Pole Road Pavement Tree SignSymbol Fence Car Pedestrian Bicyclist".split()
VOID = 11
AGE_GROUPS = ((0, 14), (15, 29), (30, 44), (45, 59), (60, 200))
RGB_MEAN = torch.tensor([0.45, 0.45, 0.45]).view(1, 3, 1, 1)
RGB_STD = torch.tensor([0.28, 0.28, 0.28]).view(1, 3, 1, 1)


# ----------------------------------------------------------------------------------------
# Data
# ----------------------------------------------------------------------------------------
def _read_rgb(path: Path) -> np.ndarray:
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
        raise FileNotFoundError(f"no CamVid images in {root / split}")
    imgs = np.stack([_read_rgb(f) for f in files])
    labels = []
    for f in files:
        lab = cv2.imread(str(root / f"{split}annot" / f.name), cv2.IMREAD_UNCHANGED)
        if lab is None:
            raise FileNotFoundError(f"missing label map {root / f'{split}annot' / f.name}")
        labels.append(lab)
    return imgs, np.stack(labels)


def age_group(age: np.ndarray) -> np.ndarray:
    """Index into :data:`AGE_GROUPS` for ages in years."""
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
    imgs = np.stack([_read_rgb(root / r["file"]) for r in rows])
    age = np.array([int(r["age"]) for r in rows])
    return {
        "images": imgs,
        "gender": np.array([int(r["gender"]) for r in rows]),
        "age_group": age_group(age),
        "race": np.array([int(r["race"]) for r in rows]),
    }


def _to_tensor(imgs: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(imgs).permute(0, 3, 1, 2).contiguous()  # uint8 (N, 3, H, W)


# ----------------------------------------------------------------------------------------
# Networks
# ----------------------------------------------------------------------------------------
def _block(cin: int, cout: int) -> nn.Sequential:
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
        self.enc1, self.enc2, self.enc3 = _block(3, 32), _block(32, 64), _block(64, 128)
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
        self.dec2, self.dec1 = _block(128 + 64, 64), _block(64 + 32, 32)
        self.head = nn.Conv2d(32, classes, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """``(B, 3, H, W)`` images in [0, 1] (or uint8) to sensor-grid logits ``(B, K, h, w)``."""
        s = (self.sensor(x) - RGB_MEAN) / RGB_STD
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


class FaceNet(nn.Module):
    """Sensor layer + a small CNN with one head per attribute (gender, age group, race)."""

    HEADS: ClassVar[dict[str, int]] = {"gender": 2, "age_group": len(AGE_GROUPS), "race": 5}

    def __init__(self, layout: str, size: tuple[int, int], learn: bool = True, **sensor):
        super().__init__()
        self.sensor = SensorLayer(size, layout, learn=learn, **sensor)
        self.body = nn.Sequential(_block(3, 32), nn.MaxPool2d(2, ceil_mode=True), _block(32, 64))
        self.pool = nn.AdaptiveAvgPool2d(2)
        self.fc = nn.Sequential(nn.Flatten(), nn.Linear(64 * 4, 128), nn.ReLU(inplace=True), nn.Dropout(0.3))
        self.heads = nn.ModuleDict({k: nn.Linear(128, n) for k, n in self.HEADS.items()})

    def forward(self, x: torch.Tensor) -> dict[str, torch.Tensor]:
        s = (self.sensor(x) - RGB_MEAN) / RGB_STD
        z = self.fc(self.pool(self.body(s)))
        return {k: head(z) for k, head in self.heads.items()}


# ----------------------------------------------------------------------------------------
# Metrics
# ----------------------------------------------------------------------------------------
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


# ----------------------------------------------------------------------------------------
# Training
# ----------------------------------------------------------------------------------------
@dataclass
class TaskRun:
    """One training run of a task."""

    task: str
    layout: str
    size_hw: list[int]
    seed: int
    scores: dict
    theta: list[float]
    theta_history: list[list[float]] = field(default_factory=list)
    seconds: float = 0.0


def _optimizer(model: nn.Module, lr: float, theta_lr: float) -> torch.optim.Optimizer:
    sensor = [p for p in model.sensor.parameters() if p.requires_grad]
    rest = [p for n, p in model.named_parameters() if not n.startswith("sensor.")]
    groups = [{"params": rest, "lr": lr}] + ([{"params": sensor, "lr": theta_lr}] if sensor else [])
    return torch.optim.Adam(groups)


def train_camvid(
    train: tuple[np.ndarray, np.ndarray],
    val: tuple[np.ndarray, np.ndarray],
    layout: str,
    size: tuple[int, int],
    *,
    seed: int = 0,
    epochs: int = 12,
    freeze_epochs: int = 3,
    batch_size: int = 8,
    lr: float = 2e-3,
    theta_lr: float = 0.01,
    progress: bool = True,
    sensor: dict | None = None,
    class_weights: str = "median",
) -> tuple[TaskRun, SegNet]:
    """Train sensor + SegNet on CamVid ``train`` and score it on ``val`` (back-warped to full size).

    ``class_weights``: ``"none"`` (plain cross-entropy) or ``"median"``
    (:func:`median_frequency_weights` of the training labels).
    """
    if class_weights not in ("none", "median"):
        raise ValueError(f"class_weights must be 'none' or 'median', got {class_weights!r}")
    torch.manual_seed(seed)
    gen = torch.Generator().manual_seed(seed)
    learn = layout != "uniform"
    model = SegNet(layout, size, learn=learn, **(sensor or {}))
    opt = _optimizer(model, lr, theta_lr)
    x, y = _to_tensor(train[0]), torch.from_numpy(train[1]).long()
    weight = None
    if class_weights == "median":
        weight = torch.from_numpy(median_frequency_weights(train[1], len(CAMVID_CLASSES)))

    def batch_loss(idx: torch.Tensor) -> torch.Tensor:
        xb, yb = x[idx].float().div_(255), y[idx]
        if bool(torch.rand((), generator=gen) < 0.5):  # horizontal flip
            xb, yb = xb.flip(-1), yb.flip(-1)
        return backwarp_cross_entropy(model(xb), yb, model.sensor.layout, ignore_index=VOID, weight=weight)

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
        desc=f"camvid {layout} {size[1]}x{size[0]} seed {seed}",
        progress=progress,
    )
    scores = evaluate_camvid(model, val)
    run = TaskRun("camvid", layout, list(size), seed, scores, model.sensor.theta.detach().tolist(), history)
    run.seconds = time.perf_counter() - t0
    return run, model


@torch.no_grad()
def predict_camvid(model: SegNet, images: np.ndarray, batch_size: int = 8) -> torch.Tensor:
    """Back-warped full-resolution class predictions ``(N, H, W)`` int64."""
    model.eval()
    x = _to_tensor(images)
    out = []
    for k in range(0, len(x), batch_size):
        logits = model(x[k : k + batch_size].float().div(255))
        out.append(backwarp(logits.argmax(1), model.sensor.layout, tuple(x.shape[-2:])))
    return torch.cat(out)


def evaluate_camvid(model: SegNet, val: tuple[np.ndarray, np.ndarray]) -> dict:
    """mIoU and pixel accuracy on ``val`` at full resolution, void ignored."""
    pred = predict_camvid(model, val[0])
    return segmentation_scores(_confusion(pred, torch.from_numpy(val[1]).long(), len(CAMVID_CLASSES), VOID))


def train_faces(
    data: dict[str, np.ndarray],
    train_idx: np.ndarray,
    test_idx: np.ndarray,
    layout: str,
    size: tuple[int, int],
    *,
    seed: int = 0,
    epochs: int = 30,
    freeze_epochs: int = 0,
    batch_size: int = 64,
    lr: float = 2e-3,
    theta_lr: float = 0.01,
    progress: bool = True,
    sensor: dict | None = None,
) -> tuple[TaskRun, FaceNet]:
    """Train sensor + FaceNet on the ``train_idx`` faces; accuracies on ``test_idx``."""
    torch.manual_seed(seed)
    gen = torch.Generator().manual_seed(seed)
    family, learn = ("rect", False) if layout == "uniform" else (layout, True)
    model = FaceNet(family, size, learn=learn, **(sensor or {}))
    opt = _optimizer(model, lr, theta_lr)
    x = _to_tensor(data["images"])
    targets = {k: torch.from_numpy(data[k]).long() for k in FaceNet.HEADS}

    def batch_loss(idx: torch.Tensor) -> torch.Tensor:
        xb = x[idx].float().div_(255)
        if bool(torch.rand((), generator=gen) < 0.5):  # horizontal flip
            xb = xb.flip(-1)
        out = model(xb)
        return sum(F.cross_entropy(out[key], targets[key][idx]) for key in out)

    t0 = time.perf_counter()
    history = fit(
        model,
        torch.from_numpy(train_idx),
        batch_loss,
        opt,
        gen,
        epochs=epochs,
        batch_size=batch_size,
        freeze_epochs=freeze_epochs,
        sched=torch.optim.lr_scheduler.CosineAnnealingLR(opt, max(epochs, 1)),
        desc=f"faces {layout} {size[1]}x{size[0]} seed {seed}",
        progress=progress,
    )
    scores = evaluate_faces(
        model, x[torch.from_numpy(test_idx)], {k: v[torch.from_numpy(test_idx)] for k, v in targets.items()}
    )
    run = TaskRun("faces", layout, list(size), seed, scores, model.sensor.theta.detach().tolist(), history)
    run.seconds = time.perf_counter() - t0
    return run, model


@torch.no_grad()
def evaluate_faces(
    model: FaceNet, x: torch.Tensor, targets: dict[str, torch.Tensor], batch_size: int = 256
) -> dict:
    """Accuracy (percent) per attribute and their mean."""
    model.eval()
    correct = dict.fromkeys(targets, 0)
    for k in range(0, len(x), batch_size):
        out = model(x[k : k + batch_size].float().div(255))
        for key in targets:
            correct[key] += int((out[key].argmax(1) == targets[key][k : k + batch_size]).sum())
    acc = {key: 100.0 * c / len(x) for key, c in correct.items()}
    return {**acc, "mean": float(np.mean(list(acc.values())))}


# ----------------------------------------------------------------------------------------
# Experiments
# ----------------------------------------------------------------------------------------
def _summarise(runs: list[TaskRun], metrics: tuple[str, ...]) -> dict:
    summary: dict = {}
    for run in runs:
        key = f"{run.layout} {run.size_hw[1]}x{run.size_hw[0]}"
        summary.setdefault(key, {"layout": run.layout, "size_hw": run.size_hw, "runs": []})["runs"].append(
            run
        )
    for s in summary.values():
        rs = s.pop("runs")
        for m in metrics:
            v = np.array([r.scores[m] for r in rs])
            s[m] = {"mean": float(v.mean()), "std": float(v.std(ddof=1)) if len(v) > 1 else 0.0}
        s["theta_mean"] = np.mean([r.theta for r in rs], 0).tolist()
        s["n"] = len(rs)
    return summary


def run_camvid_experiment(
    data_dir: str | Path,
    out: str | Path,
    layouts: tuple[str, ...] = ("uniform", "curv", "rect"),
    sizes: tuple[tuple[int, int], ...] = ((36, 48), (72, 96)),
    seeds: tuple[int, ...] = (0, 1),
    epochs: int = 12,
    freeze_epochs: int = 3,
    limit: int | None = None,
    progress: bool = True,
    sensor: dict | None = None,
    class_weights: str = "median",
) -> dict:
    """Every layout × sensor size × seed on CamVid; writes results.json, layouts and figures."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    train, val = load_camvid(data_dir, "train", limit), load_camvid(data_dir, "val", limit)
    runs, models = [], {}
    for size in sizes:
        for layout in layouts:
            for seed in seeds:
                run, model = train_camvid(
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
                )
                runs.append(run)
                models.setdefault((layout, tuple(size)), model)
                th = ", ".join(f"{v:+.3f}" for v in run.theta)
                print(
                    f"  camvid {layout:8s} {size[1]}x{size[0]} seed {seed}: mIoU {run.scores['miou']:5.2f}%  "
                    f"pixel acc {run.scores['pixel_accuracy']:5.2f}%  θ = ({th})  [{run.seconds:.0f} s]",
                    flush=True,
                )
                _save_runs(
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


def _save_runs(
    out: Path, task: str, data_dir, n_train: int, n_test: int, epochs: int, runs, metrics, sensor, **options
) -> None:
    result = {
        "task": task,
        "data": str(data_dir),
        "train_size": n_train,
        "test_size": n_test,
        "epochs": epochs,
        **options,
        "sensor": sensor or {"method": "exact"},
        "summary": _summarise(runs, metrics),
        "runs": [asdict(r) for r in runs],
    }
    atomic_write(out / "results.json", json.dumps(result, indent=2))


def run_faces_experiment(
    data_dir: str | Path,
    out: str | Path,
    layouts: tuple[str, ...] = ("uniform", "rect"),
    sizes: tuple[tuple[int, int], ...] = ((8, 8), (16, 16)),
    seeds: tuple[int, ...] = (0, 1, 2),
    epochs: int = 30,
    limit: int | None = None,
    test_fraction: float = 0.2,
    progress: bool = True,
    sensor: dict | None = None,
) -> dict:
    """Every layout × sensor size × seed on UTKFace attributes; writes results.json and figures."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    data = load_faces(data_dir, limit)
    n = len(data["images"])
    order = np.random.default_rng(1234).permutation(n)  # one fixed split for every run
    n_test = max(1, round(n * test_fraction))
    test_idx, train_idx = np.sort(order[:n_test]), np.sort(order[n_test:])
    runs, models = [], {}
    metrics = (*FaceNet.HEADS, "mean")
    for size in sizes:
        for layout in layouts:
            for seed in seeds:
                run, model = train_faces(
                    data,
                    train_idx,
                    test_idx,
                    layout,
                    size,
                    seed=seed,
                    epochs=epochs,
                    progress=progress,
                    sensor=sensor,
                )
                runs.append(run)
                models.setdefault((layout, tuple(size)), model)
                accs = "  ".join(f"{k} {run.scores[k]:5.1f}" for k in metrics)
                th = ", ".join(f"{v:+.3f}" for v in run.theta)
                print(
                    f"  faces {layout:8s} {size[1]}x{size[0]} seed {seed}: {accs}  "
                    f"θ = ({th})  [{run.seconds:.0f} s]",
                    flush=True,
                )
                _save_runs(
                    out, "faces", data_dir, len(train_idx), len(test_idx), epochs, runs, metrics, sensor
                )
    for (layout, size), model in models.items():
        save_layout(
            model.sensor.layout,
            out / f"layout_{layout}_{size[1]}x{size[0]}.json",
            size=size,
            experiment="faces",
        )
    _faces_figure(data["images"][test_idx[:1]], models, out)
    return json.loads((out / "results.json").read_text())


def _theta_text(model: nn.Module) -> str:
    th = model.sensor.theta.detach().tolist()
    return "θ=(" + ", ".join(f"{v:.2f}" for v in th) + ")" if th else "θ=()"


def _camvid_figures(val, models: dict, out: Path) -> None:
    """Fig. 5 analogue (layouts over a street scene) and back-warped example predictions."""
    from .plots import _plt, draw_layout, save_figure

    plt = _plt()
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
    fig, axes = plt.subplots(3, len(keys), figsize=(3.6 * len(keys), 8.2), squeeze=False)
    for k, (layout, size) in enumerate(keys):
        model = models[(layout, size)]
        draw_layout(axes[0, k], model.sensor.layout, size, image=img / 255.0, max_lines=32, lw=0.5)
        axes[0, k].set_title(f"{layout} {size[1]}x{size[0]} {_theta_text(model)}", fontsize=8)
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


def _faces_figure(images: np.ndarray, models: dict, out: Path) -> None:
    from .plots import _plt, draw_layout, save_figure

    plt = _plt()
    keys = list(models)
    fig, axes = plt.subplots(2, len(keys), figsize=(3 * len(keys), 6), squeeze=False)
    for k, (layout, size) in enumerate(keys):
        model = models[(layout, size)]
        draw_layout(axes[0, k], model.sensor.layout, size, image=images[0] / 255.0, lw=0.8)
        axes[0, k].set_title(f"{layout} {size[1]}x{size[0]} {_theta_text(model)}", fontsize=8)
        with torch.no_grad():
            s = model.sensor(torch.from_numpy(images[0]).permute(2, 0, 1)[None].float() / 255)[0]
        axes[1, k].imshow(np.clip(s.permute(1, 2, 0).numpy(), 0, 1), interpolation="nearest")
        axes[1, k].set_xticks([])
        axes[1, k].set_yticks([])
    save_figure(fig, out / "faces_layouts.png", dpi=100)
