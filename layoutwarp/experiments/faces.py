"""UTKFace attributes (the paper's CelebA experiment, on UTKFace).

Gender (2 classes), age group (:data:`~layoutwarp.experiments.data.AGE_GROUPS`) and race (5)
from an 8x8 or 16x16 sensor, one head each; accuracies per attribute and their mean. The
uniform layout is the baseline.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import ClassVar

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from ..layoutfile import save_layout
from ..sensor import SensorLayer
from .camvid import conv_block, normalise_rgb, to_tensor
from .data import AGE_GROUPS, load_faces
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

__all__ = ["DEFAULTS", "FaceNet", "evaluate_faces", "run_faces_experiment", "train_faces"]

DEFAULTS = ExperimentDefaults(
    task="faces",
    shared="faces/utkface_subset",
    sample="faces/utkface",
    families=("uniform", "rect"),
    sizes=((8, 8), (16, 16)),
    seeds=3,
    epochs=30,
    quick_epochs=2,
    tol=1e-3,
)


class FaceNet(nn.Module):
    """Sensor layer + a small CNN with one head per attribute (gender, age group, race)."""

    HEADS: ClassVar[dict[str, int]] = {"gender": 2, "age_group": len(AGE_GROUPS), "race": 5}

    def __init__(self, layout: str, size: tuple[int, int], learn: bool = True, **sensor):
        super().__init__()
        self.sensor = SensorLayer(size, layout, learn=learn, **sensor)
        self.body = nn.Sequential(conv_block(3, 32), nn.MaxPool2d(2, ceil_mode=True), conv_block(32, 64))
        self.pool = nn.AdaptiveAvgPool2d(2)
        self.fc = nn.Sequential(nn.Flatten(), nn.Linear(64 * 4, 128), nn.ReLU(inplace=True), nn.Dropout(0.3))
        self.heads = nn.ModuleDict({k: nn.Linear(128, n) for k, n in self.HEADS.items()})

    def forward(self, x: torch.Tensor) -> dict[str, torch.Tensor]:
        s = normalise_rgb(self.sensor(x))
        z = self.fc(self.pool(self.body(s)))
        return {k: head(z) for k, head in self.heads.items()}


def train_faces(
    data: dict[str, np.ndarray],
    train_idx: np.ndarray,
    test_idx: np.ndarray,
    layout: str,
    size: tuple[int, int],
    *,
    seed: int = 0,
    epochs: int = DEFAULTS.epochs,
    freeze_epochs: int = DEFAULTS.freeze_epochs,
    batch_size: int = 64,
    lr: float = 2e-3,
    theta_lr: float = 0.01,
    progress: bool = True,
    sensor: dict | None = None,
    device: str | torch.device = "cpu",
    amp: bool = False,
) -> tuple[TaskRun, FaceNet]:
    """Train sensor + FaceNet on the ``train_idx`` faces; accuracies on ``test_idx``."""
    torch.manual_seed(seed)
    gen = torch.Generator().manual_seed(seed)
    model = FaceNet(layout, size, learn=layout != "uniform", **(sensor or DEFAULTS.sensor())).to(device)
    opt = optimizer(model, lr, theta_lr)
    x = to_tensor(data["images"])
    targets = {k: torch.from_numpy(data[k]).long().to(device) for k in FaceNet.HEADS}

    def batch_loss(idx: torch.Tensor, net: nn.Module) -> torch.Tensor:
        xb = x[idx].to(device).float().div_(255)
        if bool(torch.rand((), generator=gen) < 0.5):  # horizontal flip
            xb = xb.flip(-1)
        out = net(xb)
        return sum(F.cross_entropy(out[key], targets[key][idx.to(device)]) for key in out)

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
        desc=f"faces {layout_name(layout)} {size[1]}x{size[0]} seed {seed}",
        progress=progress,
        amp=amp,
    )
    test = torch.from_numpy(test_idx)
    scores = evaluate_faces(model, x[test], {k: v[test.to(device)] for k, v in targets.items()})
    run = TaskRun(
        "faces", layout_name(layout), list(size), seed, scores, model.sensor.theta.detach().tolist(), history
    )
    run.seconds = time.perf_counter() - t0
    return run, model


@torch.no_grad()
def evaluate_faces(
    model: FaceNet, x: torch.Tensor, targets: dict[str, torch.Tensor], batch_size: int = 256
) -> dict:
    """Accuracy (percent) per attribute and their mean."""
    model.eval()
    device = model_device(model)
    correct = dict.fromkeys(targets, 0)
    for k in range(0, len(x), batch_size):
        out = model(x[k : k + batch_size].to(device).float().div(255))
        for key in targets:
            correct[key] += int((out[key].argmax(1) == targets[key][k : k + batch_size].to(device)).sum())
    acc = {key: 100.0 * c / len(x) for key, c in correct.items()}
    return {**acc, "mean": float(np.mean(list(acc.values())))}


def run_faces_experiment(
    data_dir: str | Path,
    out: str | Path,
    families: tuple[str, ...] = DEFAULTS.families,
    sizes: tuple[tuple[int, int], ...] = DEFAULTS.sizes,
    seeds: tuple[int, ...] = tuple(range(DEFAULTS.seeds)),
    epochs: int = DEFAULTS.epochs,
    limit: int | None = None,
    test_fraction: float = 0.2,
    progress: bool = True,
    sensor: dict | None = None,
    device: str | torch.device = "cpu",
    amp: bool = False,
) -> dict:
    """Every family × sensor size × seed on UTKFace attributes; writes results.json and figures."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    sensor = sensor or DEFAULTS.sensor()
    data = load_faces(data_dir, limit)
    n = len(data["images"])
    order = np.random.default_rng(1234).permutation(n)  # one fixed split for every run
    n_test = max(1, round(n * test_fraction))
    test_idx, train_idx = np.sort(order[:n_test]), np.sort(order[n_test:])
    metrics = (*FaceNet.HEADS, "mean")
    configs = [(f, tuple(size), seed) for size in sizes for f in families for seed in seeds]
    models = run_grid(
        "faces",
        out,
        configs,
        lambda layout, size, seed: train_faces(
            data,
            train_idx,
            test_idx,
            layout,
            size,
            seed=seed,
            epochs=epochs,
            progress=progress,
            sensor=sensor,
            device=device,
            amp=amp,
        ),
        sensor=sensor,
        training={"epochs": epochs},
        describe=lambda run: "  ".join(f"{k} {run.scores[k]:5.1f}" for k in metrics),
        save=lambda runs: save_runs(
            out, "faces", data_dir, len(train_idx), len(test_idx), epochs, runs, metrics, sensor
        ),
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


def _faces_figure(images: np.ndarray, models: dict, out: Path) -> None:
    from .plots import draw_layout, figure, save_figure

    models = {key: model.cpu() for key, model in models.items()}  # figures are drawn on the CPU

    keys = list(models)
    fig, axes = figure(2, len(keys), figsize=(3 * len(keys), 6), squeeze=False)
    for k, (layout, size) in enumerate(keys):
        model = models[(layout, size)]
        draw_layout(axes[0, k], model.sensor.layout, size, image=images[0] / 255.0, lw=0.8)
        axes[0, k].set_title(f"{layout} {size[1]}x{size[0]} {theta_text(model)}", fontsize=8)
        with torch.no_grad():
            s = model.sensor(torch.from_numpy(images[0]).permute(2, 0, 1)[None].float() / 255)[0]
        axes[1, k].imshow(np.clip(s.permute(1, 2, 0).numpy(), 0, 1), interpolation="nearest")
        axes[1, k].set_xticks([])
        axes[1, k].set_yticks([])
    save_figure(fig, out / "faces_layouts.png", dpi=100)
