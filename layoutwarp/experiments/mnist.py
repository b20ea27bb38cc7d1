"""MNIST with a 4x4 sensor: the paper's first experiment (§5).

A layout initialised at θ = 0 trains jointly with a CNN with two conv layers (32, 64
channels), max pooling and two fully connected layers (hidden 128): Adam with learning rate
0.01, 14 epochs, batch 64; the baseline is the uniform layout.
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
from .data import load_mnist_split
from .protocols import SPECS
from .tasks import Task, TaskData, register_task
from .training import BatchLoss, model_device

__all__ = ["MnistNet", "MnistTask"]

MNIST_MEAN, MNIST_STD = 0.1307, 0.3081


class MnistNet(nn.Module):
    """Sensor layer + the paper's small CNN (conv 32, conv 64, max pool, fc 128, fc 10)."""

    def __init__(
        self,
        layout: str | Layout = "curv",
        size: tuple[int, int] = (4, 4),
        learn: bool | None = None,
        **sensor: Any,
    ):
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


def _images(images: np.ndarray, device: torch.device) -> torch.Tensor:
    return torch.from_numpy(images).float().div(255)[:, None].to(device)


@register_task
class MnistTask(Task):
    """MNIST digits (train: the training set; report: the test set), accuracy in percent."""

    spec = SPECS["mnist"]

    def load(self, folder: Path, limit: int | None = None) -> TaskData:
        train = tuple(a[:limit] for a in load_mnist_split(folder, "train"))
        test = tuple(a[:limit] for a in load_mnist_split(folder, "test"))
        return TaskData(train, test, Path(folder), {"train": len(train[0]), "report": len(test[0])})

    def load_split(self, folder: Path, split: str | None) -> Any:
        return load_mnist_split(folder, split or "test")

    def density_images(self, data: TaskData) -> torch.Tensor:
        return torch.from_numpy(data.train[0][:4000]).float()

    def scene(self, data: TaskData) -> np.ndarray:
        return data.report[0][4] / 255.0  # a "4", as in the paper's figure

    def network(
        self, layout: str | Layout, size: tuple[int, int], learn: bool | None = None, **sensor: Any
    ) -> nn.Module:
        return MnistNet(layout, size, learn=learn, **sensor)

    def batches(
        self, model: nn.Module, train: Any, gen: torch.Generator, options: dict[str, Any]
    ) -> tuple[torch.Tensor, BatchLoss]:
        device = model_device(model)
        x, y = _images(train[0], device), torch.from_numpy(train[1]).long().to(device)
        return torch.arange(len(x)), lambda idx, net: F.cross_entropy(net(x[idx]), y[idx])

    @torch.no_grad()
    def score(self, model: nn.Module, part: Any, batch_size: int = 1000) -> dict[str, Any]:
        model.eval()
        device = model_device(model)
        x, y = _images(part[0], device), torch.from_numpy(part[1]).long().to(device)
        correct = sum(
            int((model(x[k : k + batch_size]).argmax(1) == y[k : k + batch_size]).sum())
            for k in range(0, len(x), batch_size)
        )
        return {"accuracy": 100.0 * correct / max(len(x), 1)}
