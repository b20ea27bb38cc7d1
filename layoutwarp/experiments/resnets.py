"""ResNet-18/50 and PSPNet, the paper's networks, written here (torchvision is no dependency).

The ResNets follow torchvision's layout exactly (He et al. 2016, "v1.5": the stride of a
bottleneck on its 3x3 convolution), parameter names included, so a torchvision-format state dict
a user downloaded loads with [`load_backbone`][] (``--backbone-weights FILE``; nothing downloads
at run time). [`PSPNet`][] is Zhao et al.'s pyramid scene parsing network ("Pyramid Scene
Parsing Network", CVPR 2017) on a dilated ResNet-50: layers 3 and 4 dilated instead of strided
(output stride 8), a pyramid pooling module of bins 1, 2, 3 and 6 on the 2048 channels, a 3x3
fusion to 512 channels, dropout 0.1 and a 1x1 classifier; during training an auxiliary head on
layer 3 (1024 channels → 256 → classes, weight [`AUX_WEIGHT`][] in the loss).

Shapes: images ``(B, 3, H, W)``; [`ResNet.features`][] returns layer 3 and layer 4
``(B, C, H/8, W/8)`` dilated (``(B, C, H/16, W/16)``, ``(B, C, H/32, W/32)`` plain).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import Tensor, nn

__all__ = [
    "AUX_WEIGHT",
    "IMAGENET_MEAN",
    "IMAGENET_STD",
    "PSP_BINS",
    "PSPNet",
    "ResNet",
    "load_backbone",
    "resnet18",
    "resnet50",
]

#: The pyramid pooling module's bins (Zhao et al.).
PSP_BINS = (1, 2, 3, 6)
#: The auxiliary loss's weight (Zhao et al.).
AUX_WEIGHT = 0.4
#: ImageNet's channel means and deviations, which a pretrained ResNet expects its inputs scaled by.
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


class BasicBlock(nn.Module):
    """Two 3x3 convolutions and a shortcut (ResNet-18/34)."""

    expansion = 1

    def __init__(
        self, cin: int, width: int, stride: int = 1, dilation: int = 1, downsample: nn.Module | None = None
    ):
        super().__init__()
        self.conv1 = nn.Conv2d(cin, width, 3, stride, padding=dilation, dilation=dilation, bias=False)
        self.bn1 = nn.BatchNorm2d(width)
        self.conv2 = nn.Conv2d(width, width, 3, padding=dilation, dilation=dilation, bias=False)
        self.bn2 = nn.BatchNorm2d(width)
        self.relu = nn.ReLU(inplace=True)
        self.downsample = downsample

    def forward(self, x: Tensor) -> Tensor:
        out = self.relu(self.bn1(self.conv1(x)))
        out = self.bn2(self.conv2(out))
        return self.relu(out + (x if self.downsample is None else self.downsample(x)))


class Bottleneck(nn.Module):
    """1x1 → 3x3 (strided, dilated) → 1x1 at four times the width, and a shortcut (ResNet-50)."""

    expansion = 4

    def __init__(
        self, cin: int, width: int, stride: int = 1, dilation: int = 1, downsample: nn.Module | None = None
    ):
        super().__init__()
        self.conv1 = nn.Conv2d(cin, width, 1, bias=False)
        self.bn1 = nn.BatchNorm2d(width)
        self.conv2 = nn.Conv2d(width, width, 3, stride, padding=dilation, dilation=dilation, bias=False)
        self.bn2 = nn.BatchNorm2d(width)
        self.conv3 = nn.Conv2d(width, width * 4, 1, bias=False)
        self.bn3 = nn.BatchNorm2d(width * 4)
        self.relu = nn.ReLU(inplace=True)
        self.downsample = downsample

    def forward(self, x: Tensor) -> Tensor:
        out = self.relu(self.bn1(self.conv1(x)))
        out = self.relu(self.bn2(self.conv2(out)))
        out = self.bn3(self.conv3(out))
        return self.relu(out + (x if self.downsample is None else self.downsample(x)))


class ResNet(nn.Module):
    """A ResNet in torchvision's layout (``conv1``, ``bn1``, ``layer1``–``layer4``, ``fc``).

    Args:
        block: [`BasicBlock`][] or [`Bottleneck`][].
        layers: blocks per stage.
        classes: outputs of ``fc`` (``0``: no ``fc``, a backbone).
        dilate: stages 3 and 4 dilated (2 and 4) instead of strided, as torchvision's
            ``replace_stride_with_dilation=[False, True, True]``: output stride 8.
    """

    def __init__(self, block: type, layers: Sequence[int], classes: int = 1000, dilate: bool = False):
        super().__init__()
        self.cin, self.dilation = 64, 1
        self.conv1 = nn.Conv2d(3, 64, 7, 2, 3, bias=False)
        self.bn1 = nn.BatchNorm2d(64)
        self.relu = nn.ReLU(inplace=True)
        self.maxpool = nn.MaxPool2d(3, 2, 1)
        self.layer1 = self._stage(block, 64, layers[0])
        self.layer2 = self._stage(block, 128, layers[1], stride=2)
        self.layer3 = self._stage(block, 256, layers[2], stride=2, dilate=dilate)
        self.layer4 = self._stage(block, 512, layers[3], stride=2, dilate=dilate)
        self.channels = 512 * block.expansion
        self.avgpool = nn.AdaptiveAvgPool2d(1)
        self.fc = nn.Linear(self.channels, classes) if classes else None
        for m in self.modules():
            if isinstance(m, nn.Conv2d):
                nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu")
        for m in self.modules():  # each residual branch starts at zero: the block starts as its shortcut
            if isinstance(m, Bottleneck):
                nn.init.zeros_(m.bn3.weight)
            elif isinstance(m, BasicBlock):
                nn.init.zeros_(m.bn2.weight)

    def _stage(self, block: type, width: int, n: int, stride: int = 1, dilate: bool = False) -> nn.Sequential:
        previous = self.dilation
        if dilate:
            self.dilation, stride = self.dilation * stride, 1
        downsample = None
        if stride != 1 or self.cin != width * block.expansion:
            downsample = nn.Sequential(
                nn.Conv2d(self.cin, width * block.expansion, 1, stride, bias=False),
                nn.BatchNorm2d(width * block.expansion),
            )
        blocks = [block(self.cin, width, stride, previous, downsample)]
        self.cin = width * block.expansion
        blocks += [block(self.cin, width, dilation=self.dilation) for _ in range(1, n)]
        return nn.Sequential(*blocks)

    def features(self, x: Tensor) -> tuple[Tensor, Tensor]:
        """Layer 3's and layer 4's outputs (PSPNet's auxiliary and main inputs)."""
        x = self.maxpool(self.relu(self.bn1(self.conv1(x))))
        c3 = self.layer3(self.layer2(self.layer1(x)))
        return c3, self.layer4(c3)

    def embed(self, x: Tensor) -> Tensor:
        """Layer 4 averaged over the image: ``(B, channels)``, what ``fc`` reads."""
        return torch.flatten(self.avgpool(self.features(x)[1]), 1)

    def forward(self, x: Tensor) -> Tensor:
        """Class logits ``(B, classes)`` ([`embed`][], then ``fc``)."""
        if self.fc is None:
            raise RuntimeError("a backbone (classes=0) has no fc: call features() or embed()")
        return self.fc(self.embed(x))


def resnet18(classes: int = 1000) -> ResNet:
    """ResNet-18 (BasicBlock, 2-2-2-2)."""
    return ResNet(BasicBlock, (2, 2, 2, 2), classes)


def resnet50(classes: int = 1000, dilate: bool = False) -> ResNet:
    """ResNet-50 (Bottleneck, 3-4-6-3), dilated for PSPNet with ``dilate``."""
    return ResNet(Bottleneck, (3, 4, 6, 3), classes, dilate)


def load_backbone(net: ResNet, path: str | Path) -> ResNet:
    """Load a torchvision-format ResNet state dict (e.g. an ImageNet checkpoint a user
    downloaded) into ``net``: every parameter and buffer but ``fc`` (whose classes differ) must be
    there with its shape.

    Raises:
        ValueError: the file is not readable or does not fit the network (named, one line).
    """
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except FileNotFoundError:
        raise ValueError(f"backbone weights {str(path)!r}: no such file") from None
    except Exception as exc:
        raise ValueError(
            f"backbone weights {str(path)!r}: not a readable state dict ({type(exc).__name__})"
        ) from None
    if isinstance(state, dict) and "state_dict" in state:
        state = state["state_dict"]
    if not isinstance(state, dict):
        raise ValueError(f"backbone weights {str(path)!r}: not a state dict")
    own = {k: v for k, v in net.state_dict().items() if not k.startswith("fc.")}
    missing = [k for k in own if k not in state]
    wrong = [k for k in own if k in state and tuple(state[k].shape) != tuple(own[k].shape)]
    if missing or wrong:
        first = (missing or wrong)[0]
        what = "missing" if missing else f"shape {tuple(state[first].shape)}, not {tuple(own[first].shape)}"
        raise ValueError(
            f"backbone weights {str(path)!r} do not fit a torchvision ResNet of this depth: {first} {what} "
            f"({len(missing)} missing, {len(wrong)} of another shape)"
        )
    net.load_state_dict({k: state[k] for k in own}, strict=False)
    return net


class PSPNet(nn.Module):
    """PSPNet on a dilated ResNet-50 (module docstring): ``(B, 3, H, W)`` normalised images to
    logits ``(B, classes, H, W)``; in training mode ``(logits, aux_logits)``, both at ``H x W``."""

    def __init__(self, classes: int, bins: Sequence[int] = PSP_BINS, dropout: float = 0.1):
        super().__init__()
        self.backbone = resnet50(classes=0, dilate=True)
        c = self.backbone.channels
        self.bins = tuple(bins)
        self.ppm = nn.ModuleList(
            nn.Sequential(
                nn.Conv2d(c, c // len(self.bins), 1, bias=False),
                nn.BatchNorm2d(c // len(self.bins)),
                nn.ReLU(inplace=True),
            )
            for _ in self.bins
        )
        self.head = nn.Sequential(
            nn.Conv2d(2 * c, 512, 3, padding=1, bias=False),
            nn.BatchNorm2d(512),
            nn.ReLU(inplace=True),
            nn.Dropout2d(dropout),
            nn.Conv2d(512, classes, 1),
        )
        self.aux = nn.Sequential(
            nn.Conv2d(c // 2, 256, 3, padding=1, bias=False),
            nn.BatchNorm2d(256),
            nn.ReLU(inplace=True),
            nn.Dropout2d(dropout),
            nn.Conv2d(256, classes, 1),
        )

    def forward(self, x: Tensor) -> Tensor | tuple[Tensor, Tensor]:
        size = x.shape[-2:]
        c3, c4 = self.backbone.features(x)
        pooled = [
            F.interpolate(
                m(F.adaptive_avg_pool2d(c4, b)), c4.shape[-2:], mode="bilinear", align_corners=False
            )
            for b, m in zip(self.bins, self.ppm, strict=True)
        ]
        out = F.interpolate(
            self.head(torch.cat([c4, *pooled], 1)), size, mode="bilinear", align_corners=False
        )
        if not self.training:
            return out
        return out, F.interpolate(self.aux(c3), size, mode="bilinear", align_corners=False)
