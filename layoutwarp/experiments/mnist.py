"""MNIST with a 4x4 sensor: the paper's first experiment (§5).

``train_mnist`` trains a layout initialised at θ = 0 jointly with a CNN with two conv layers
(32, 64 channels), max pooling and two fully connected layers (hidden 128), Adam with
learning rate 0.01, 14 epochs, batch 64; the baseline is the uniform layout.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from ..files import atomic_write
from ..integrators import data_tolerance
from ..layoutfile import save_layout
from ..sensor import SensorLayer
from .data import load_mnist
from .models import save_run_model
from .training import ExperimentDefaults, fit, format_theta, layout_name, model_device, theta_text

__all__ = ["DEFAULTS", "MnistNet", "RunResult", "run_mnist_experiment", "train_mnist"]

DEFAULTS = ExperimentDefaults(
    task="mnist",
    shared="mnist",
    sample="mnist",
    families=("uniform", "curv", "rect"),
    sizes=((4, 4),),
    seeds=3,
    epochs=14,
    quick_epochs=3,
    tol=data_tolerance(np.uint8)[0],  # MNIST is 8-bit: a quarter of one level
)
MNIST_MEAN, MNIST_STD = 0.1307, 0.3081


class MnistNet(nn.Module):
    """Sensor layer + the paper's small CNN (conv 32, conv 64, max pool, fc 128, fc 10)."""

    def __init__(self, layout: str = "curv", size: tuple[int, int] = (4, 4), learn: bool = True, **sensor):
        super().__init__()
        self.sensor = SensorLayer(size, layout, learn=learn, **sensor)
        h, w = size
        self.conv1 = nn.Conv2d(1, 32, 3, padding=1)
        self.conv2 = nn.Conv2d(32, 64, 3, padding=1)
        self.fc1 = nn.Linear(64 * max(h // 2, 1) * max(w // 2, 1), 128)
        self.fc2 = nn.Linear(128, 10)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """``(B, 1, 28, 28)`` images in [0, 1] to ``(B, 10)`` logits."""
        s = (self.sensor(x) - MNIST_MEAN) / MNIST_STD
        s = F.relu(self.conv2(F.relu(self.conv1(s))))
        s = F.max_pool2d(s, 2) if min(s.shape[-2:]) >= 2 else s
        return self.fc2(F.relu(self.fc1(s.flatten(1))))


@dataclass
class RunResult:
    """One training run."""

    layout: str
    seed: int
    test_accuracy: float
    theta: list[float]
    theta_history: list[list[float]] = field(default_factory=list)
    seconds: float = 0.0


def train_mnist(
    data: dict[str, np.ndarray],
    layout: str = "curv",
    *,
    seed: int = 0,
    epochs: int = DEFAULTS.epochs,
    batch_size: int = 64,
    lr: float = 0.01,
    size: tuple[int, int] = (4, 4),
    progress: bool = True,
    sensor: dict | None = None,
    device: str | torch.device = "cpu",
    amp: bool = False,
) -> tuple[RunResult, MnistNet]:
    """Train sensor + CNN jointly (``layout="uniform"``: the fixed uniform baseline) and test it.

    ``sensor`` holds :class:`~layoutwarp.SensorLayer` options (``method``, ``samples``,
    ``radiance``, ...); the default is the exact integrator at ``DEFAULTS.tol``.
    """
    torch.manual_seed(seed)
    gen = torch.Generator().manual_seed(seed)
    model = MnistNet(layout, size, learn=layout != "uniform", **(sensor or DEFAULTS.sensor())).to(device)
    opt = torch.optim.Adam(model.parameters(), lr=lr)
    x_train = torch.from_numpy(data["train_images"]).float().div(255)[:, None].to(device)
    y_train = torch.from_numpy(data["train_labels"]).long().to(device)
    t0 = time.perf_counter()
    history = fit(
        model,
        torch.arange(len(x_train)),
        lambda idx, net: F.cross_entropy(net(x_train[idx]), y_train[idx]),
        opt,
        gen,
        epochs=epochs,
        batch_size=batch_size,
        desc=f"mnist {layout_name(layout)} seed {seed}",
        progress=progress,
        amp=amp,
    )
    acc = evaluate(model, data["test_images"], data["test_labels"])
    result = RunResult(
        layout_name(layout),
        seed,
        acc,
        model.sensor.theta.detach().tolist(),
        history,
        time.perf_counter() - t0,
    )
    return result, model


@torch.no_grad()
def evaluate(model: MnistNet, images: np.ndarray, labels: np.ndarray, batch_size: int = 1000) -> float:
    """Test accuracy in percent."""
    model.eval()
    device = model_device(model)
    x = torch.from_numpy(images).float().div(255)[:, None].to(device)
    y = torch.from_numpy(labels).long().to(device)
    correct = sum(
        int((model(x[k : k + batch_size]).argmax(1) == y[k : k + batch_size]).sum())
        for k in range(0, len(x), batch_size)
    )
    return 100.0 * correct / len(x)


def run_mnist_experiment(
    data_dir: str | Path,
    out: str | Path,
    families: tuple[str, ...] = DEFAULTS.families,
    seeds: tuple[int, ...] = tuple(range(DEFAULTS.seeds)),
    epochs: int = DEFAULTS.epochs,
    limit_train: int | None = None,
    progress: bool = True,
    sensor: dict | None = None,
    device: str | torch.device = "cpu",
    amp: bool = False,
) -> dict:
    """Train every family for every seed; write ``results.json``, ``layout.json`` and figures."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    sensor = sensor or DEFAULTS.sensor()
    data = load_mnist(data_dir)
    if limit_train:
        data = {
            **data,
            "train_images": data["train_images"][:limit_train],
            "train_labels": data["train_labels"][:limit_train],
        }
    runs: list[RunResult] = []
    models: dict[str, MnistNet] = {}
    for layout in families:
        for seed in seeds:
            res, model = train_mnist(
                data,
                layout,
                seed=seed,
                epochs=epochs,
                progress=progress,
                sensor=sensor,
                device=device,
                amp=amp,
            )
            save_run_model(
                out,
                "mnist",
                layout,
                (4, 4),
                seed,
                model,
                sensor=sensor,
                training={"epochs": epochs, "scores": {"accuracy": res.test_accuracy}},
            )
            runs.append(res)
            models.setdefault(layout, model)
            print(
                f"  {layout:8s} seed {seed}: test accuracy {res.test_accuracy:6.2f}%  "
                f"θ = {format_theta(res.theta)}  [{res.seconds:.0f} s]"
            )
    summary = {}
    for layout in families:
        accs = np.array([r.test_accuracy for r in runs if r.layout == layout])
        thetas = np.array([r.theta for r in runs if r.layout == layout])
        summary[layout] = {
            "accuracy_mean": float(accs.mean()),
            "accuracy_std": float(accs.std(ddof=1)) if len(accs) > 1 else 0.0,
            "n": len(accs),
            "theta_mean": thetas.mean(0).tolist(),
        }
    result = {
        "data": str(data_dir),
        "train_size": len(data["train_images"]),
        "test_size": len(data["test_images"]),
        "epochs": epochs,
        "seeds": list(seeds),
        "sensor": sensor,
        "summary": summary,
        "runs": [r.__dict__ for r in runs],
    }
    atomic_write(out / "results.json", json.dumps(result, indent=2))
    best = "curv" if "curv" in models else families[-1]
    save_layout(
        models[best].sensor.layout,
        out / "layout.json",
        size=(4, 4),
        experiment="mnist",
        accuracy=summary[best]["accuracy_mean"],
    )
    for layout, model in models.items():
        save_layout(model.sensor.layout, out / f"layout_{layout}.json", size=(4, 4), experiment="mnist")
    _figures(data, models, runs, out)
    return result


def _figures(data, models: dict[str, MnistNet], runs: list[RunResult], out: Path) -> None:
    from .plots import draw_layout, figure, save_figure

    digit = data["test_images"][4] / 255.0  # a "4", as in the paper's figure
    names = list(models)
    fig, axes = figure(2, len(names), figsize=(3.2 * len(names), 6.4), squeeze=False)
    for k, name in enumerate(names):
        sensor = models[name].sensor
        draw_layout(axes[0, k], sensor.layout, (4, 4), image=digit, color="tab:orange", lw=1.5)
        axes[0, k].set_title(f"{name}: {theta_text(models[name])}", fontsize=10)
        with torch.no_grad():
            s = sensor.cpu()(torch.from_numpy(digit).float()[None, None])[0, 0].numpy()
        axes[1, k].imshow(s, cmap="gray", vmin=0, vmax=1, interpolation="nearest")
        axes[1, k].set_title("4x4 sensor output", fontsize=9)
        axes[1, k].set_xticks([])
        axes[1, k].set_yticks([])
    save_figure(fig, out / "mnist_layouts.png", dpi=110)
    fig, ax = figure(figsize=(6, 3.5))
    for r in runs:
        if r.layout == "uniform":
            continue
        hist = np.array(r.theta_history)
        for j, (lab, ls) in enumerate((("θx", "-"), ("θy", "--"))):
            ax.plot(
                hist[:, j],
                ls,
                color="tab:blue" if r.layout == "curv" else "tab:green",
                label=f"{r.layout} {lab}" if r.seed == runs[0].seed or len(runs) < 3 else None,
            )
    ax.set_xlabel("epoch")
    ax.set_ylabel("θ")
    ax.set_title("θ during training (each seed)")
    handles, labels = ax.get_legend_handles_labels()
    uniq = dict(zip(labels, handles, strict=False))
    ax.legend(uniq.values(), uniq.keys(), fontsize=8)
    save_figure(fig, out / "mnist_theta.png", dpi=110)
