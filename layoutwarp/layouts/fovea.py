"""The fovea family: φ_curv about a centre that is learned with θ."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from torch import Tensor

from .base import register_family
from .curv import CurvLayout

__all__ = ["FoveaLayout"]


@register_family
class FoveaLayout(CurvLayout):
    """φ_curv about a learnable centre: [`CurvLayout`][] with ``learn_center=True``, so θ is
    ``(θ_x, θ_y, c_x, c_y)`` and a learned layout moves its fovea to where the task needs it.

    Examples:
        >>> FoveaLayout((0.5, 0.2), center=(0.3, -0.1)).theta
        tensor([ 0.5000,  0.2000,  0.3000, -0.1000])
    """

    family = "fovea"
    kernel_map = "curv"

    def __init__(
        self, theta: Sequence[float] | Tensor | None = None, *, learn_center: bool = True, **kwargs: Any
    ) -> None:
        super().__init__(theta, learn_center=learn_center, **kwargs)
