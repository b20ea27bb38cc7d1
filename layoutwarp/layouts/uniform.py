"""The uniform layout: φ the identity, the sensor every camera has."""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

from .base import Layout, register_family

__all__ = ["UniformLayout"]


@register_family
class UniformLayout(Layout):
    """The uniform layout ``φ(p) = p`` (no parameters): the classical sensor."""

    family = "uniform"
    num_params = 0
    separable = True
    straight_edges = True

    def phi(self, p: Tensor, theta: Tensor) -> Tensor:
        return p

    def phi_inverse(self, q: Tensor, theta: Tensor) -> Tensor:
        return q

    def phi_jacobian(self, p: Tensor, theta: Tensor) -> Tensor:
        return torch.eye(2, dtype=p.dtype, device=p.device).expand(*p.shape, 2).clone()

    def phi_jacobian_det(self, p: Tensor, theta: Tensor) -> Tensor:
        return torch.ones_like(p[..., 0])

    def phi_dtheta(self, p: Tensor, theta: Tensor) -> Tensor:
        return p.new_zeros(*p.shape, 0)

    def to_config(self) -> dict[str, Any]:
        return {}

    def extra_repr(self) -> str:
        return ""
