"""UTKFace attributes (the paper's CelebA experiment, on UTKFace).

Gender (2 classes), age group ([`AGE_GROUPS`][layoutwarp.experiments.data.AGE_GROUPS]) and race (5)
from an 8x8 or 16x16 sensor, one head each; accuracies per attribute and their mean. The
faces are split once (a fixed permutation, a fifth for testing); the uniform layout is the
baseline. Two networks (``--net``): ``small`` (the default, a small CNN) and ``resnet18``, the
paper's ResNet-18 with its CelebA protocol (Adam 1e-3, batch 64, 15 epochs; start it from
ImageNet weights with ``--backbone-weights FILE``).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from ..layouts import Layout
from ..sensor import SensorLayer
from .data import AGE_GROUPS, images_to_tensor, load_faces
from .nets import conv_block, normalise_rgb
from .protocols import SPECS
from .resnets import IMAGENET_MEAN, IMAGENET_STD, load_backbone, resnet18
from .tasks import Task, TaskData, register_task
from .training import BatchLoss, model_device

__all__ = [
    "TEST_FRACTION",
    "FaceNet",
    "FaceResNet",
    "FacesTask",
    "SensorResNet",
    "split_faces",
]

#: The share of the faces held out for testing.
TEST_FRACTION = 0.2


class FaceNet(nn.Module):
    """Sensor layer + a small CNN with one head per attribute (gender, age group, race)."""

    HEADS: ClassVar[dict[str, int]] = {"gender": 2, "age_group": len(AGE_GROUPS), "race": 5}

    def __init__(self, layout: str | Layout, size: tuple[int, int], learn: bool | None = None, **sensor: Any):
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


class SensorResNet(nn.Module):
    """Sensor layer + ResNet-18 ([`resnet18`][]) on the sensor image as it is (an
    8x8 sensor leaves layer 4 a 1x1 map), ImageNet's scaling first, as a pretrained backbone
    expects ([`load_backbone`][]): ``(B, 3, H, W)`` images in [0, 1] to ``(B, classes)``
    logits."""

    def __init__(
        self,
        layout: str | Layout,
        size: tuple[int, int],
        classes: int,
        learn: bool | None = None,
        **sensor: Any,
    ):
        super().__init__()
        self.sensor = SensorLayer(size, layout, learn=learn, **sensor)
        self.resnet = resnet18(classes)
        self.register_buffer("mean", torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(IMAGENET_STD).view(1, 3, 1, 1), persistent=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.resnet((self.sensor(x) - self.mean) / self.std)

    def load_backbone(self, path: str | Path) -> None:
        """Start the ResNet-18 from a torchvision-format state dict (its ``fc`` is the task's)."""
        load_backbone(self.resnet, path)


class FaceResNet(SensorResNet):
    """[`SensorResNet`][] with one head per attribute (gender, age group, race): its ``fc``
    gives all the heads' logits, split into [`FaceNet`][]'s dict."""

    def __init__(self, layout: str | Layout, size: tuple[int, int], learn: bool | None = None, **sensor: Any):
        super().__init__(layout, size, sum(FaceNet.HEADS.values()), learn, **sensor)

    def forward(self, x: torch.Tensor) -> dict[str, torch.Tensor]:
        logits = super().forward(x).split(list(FaceNet.HEADS.values()), 1)
        return dict(zip(FaceNet.HEADS, logits, strict=True))


def split_faces(faces: dict[str, np.ndarray]) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """The one fixed train/test split of a faces set (a permutation seeded 1234; the test part is
    [`TEST_FRACTION`][] of the faces, at least one), each part in its original order."""
    n = len(faces["images"])
    order = np.random.default_rng(1234).permutation(n)
    n_test = max(1, round(n * TEST_FRACTION))
    test_idx, train_idx = np.sort(order[:n_test]), np.sort(order[n_test:])
    return {k: v[train_idx] for k, v in faces.items()}, {k: v[test_idx] for k, v in faces.items()}


@register_task
class FacesTask(Task):
    """UTKFace attributes (train and test: the fixed split of [`split_faces`][])."""

    spec = SPECS["faces"]

    def load(self, folder: Path, limit: int | None = None) -> TaskData:
        train, test = split_faces(load_faces(folder, limit))
        return TaskData(
            train, test, Path(folder), {"train": len(train["images"]), "report": len(test["images"])}
        )

    def load_split(self, folder: Path, split: str | None) -> Any:
        if split is not None:
            raise ValueError(
                f"a faces folder has no splits (every face in labels.csv is scored), got split {split!r}"
            )
        return load_faces(folder)

    def density_images(self, data: TaskData) -> torch.Tensor:
        return torch.from_numpy(data.train["images"][:1000]).float().permute(0, 3, 1, 2)

    def scene(self, data: TaskData) -> np.ndarray:
        return data.train["images"][:500].mean(0) / 255.0  # the mean face

    def network(
        self, layout: str | Layout, size: tuple[int, int], learn: bool | None = None, **sensor: Any
    ) -> nn.Module:
        return (FaceResNet if self.net == "resnet18" else FaceNet)(layout, size, learn=learn, **sensor)

    def batches(
        self, model: nn.Module, train: Any, gen: torch.Generator, options: dict[str, Any]
    ) -> tuple[torch.Tensor, BatchLoss]:
        device = model_device(model)
        x = images_to_tensor(train["images"])
        targets = {k: torch.from_numpy(train[k]).long().to(device) for k in FaceNet.HEADS}

        def batch_loss(idx: torch.Tensor, net: nn.Module) -> torch.Tensor:
            xb = x[idx].to(device).float().div_(255)
            if bool(torch.rand((), generator=gen) < 0.5):  # horizontal flip
                xb = xb.flip(-1)
            out = net(xb)
            return sum(F.cross_entropy(out[key], targets[key][idx.to(device)]) for key in out)

        return torch.arange(len(x)), batch_loss

    @torch.no_grad()
    def score(self, model: nn.Module, part: Any, batch_size: int = 256) -> dict[str, Any]:
        """Accuracy (percent) per attribute and their mean."""
        model.eval()
        device = model_device(model)
        x = images_to_tensor(part["images"])
        correct = dict.fromkeys(FaceNet.HEADS, 0)
        for k in range(0, len(x), batch_size):
            out = model(x[k : k + batch_size].to(device).float().div(255))
            for key in correct:
                truth = torch.from_numpy(part[key][k : k + batch_size]).long().to(device)
                correct[key] += int((out[key].argmax(1) == truth).sum())
        acc = {key: 100.0 * c / max(len(x), 1) for key, c in correct.items()}
        return {"mean": float(np.mean(list(acc.values()))), **acc}
