"""Network building blocks the tasks' networks share."""

from __future__ import annotations

import torch
from torch import nn

__all__ = ["conv_block", "normalise_rgb"]

RGB_MEAN = (0.45, 0.45, 0.45)
RGB_STD = (0.28, 0.28, 0.28)


def normalise_rgb(s: torch.Tensor) -> torch.Tensor:
    """Sensor values ``(B, 3, h, w)`` centred and scaled for the networks (on ``s``'s device)."""
    mean = torch.tensor(RGB_MEAN, dtype=s.dtype, device=s.device).view(1, 3, 1, 1)
    std = torch.tensor(RGB_STD, dtype=s.dtype, device=s.device).view(1, 3, 1, 1)
    return (s - mean) / std


def conv_block(cin: int, cout: int) -> nn.Sequential:
    """Two 3x3 convolutions, each with batch normalisation and ReLU."""
    return nn.Sequential(
        nn.Conv2d(cin, cout, 3, padding=1, bias=False),
        nn.BatchNorm2d(cout),
        nn.ReLU(inplace=True),
        nn.Conv2d(cout, cout, 3, padding=1, bias=False),
        nn.BatchNorm2d(cout),
        nn.ReLU(inplace=True),
    )
