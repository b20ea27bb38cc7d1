"""The paper's rectangular family φ_rect: separable, every pixel an axis-aligned rectangle.

``φ_j(p) = p_j (θ_j − 1) / (2 θ_j |p_j| − θ_j − 1)`` for ``|p_j| < 1``; the functional forms take θ
explicitly and [`RectLayout`][] wraps them.
"""

from __future__ import annotations

import torch
from torch import Tensor

from .arith import denom, promote
from .base import register_family
from .centered import CenteredLayout

__all__ = ["RectLayout", "phi_rect", "phi_rect_dtheta", "phi_rect_inverse", "phi_rect_jacobian"]


def phi_rect(p: Tensor, theta: Tensor) -> Tensor:
    """φ_rect: ``φ_j(p) = p_j (θ_j − 1) / (2 θ_j |p_j| − θ_j − 1)`` for ``|p_j| < 1``, else ``p_j``.

    Args:
        p: points ``(..., 2)`` in sensor coordinates.
        theta: ``(2,)`` deformation strengths in ``(-1, 1)``.

    Returns:
        ``(..., 2)`` deformed points. Separable: each deformed pixel is an axis-aligned
        rectangle. The centre pixel shrinks by ``(1 − θ)/(1 + θ)``.
    """
    p, theta = promote(p, theta)
    a = p.abs()
    return torch.where(a < 1, p * (1 - theta) / denom(a.clamp(max=1), theta), p)


def phi_rect_inverse(q: Tensor, theta: Tensor) -> Tensor:
    """Closed-form inverse of [`phi_rect`][]: ``φ_rect⁻¹(·, θ) = φ_rect(·, −θ)``."""
    return phi_rect(q, -theta)


def phi_rect_jacobian(p: Tensor, theta: Tensor) -> Tensor:
    """Spatial Jacobian ``∂φ_i/∂p_j`` of [`phi_rect`][], shape ``(..., 2, 2)`` (diagonal).

    ``dφ_j/dp_j = (1 − θ_j²) / D_j²`` with ``D_j = 1 + θ_j − 2θ_j|p_j|``; 1 outside S.
    """
    p, theta = promote(p, theta)
    a = p.abs()
    d = torch.where(a < 1, (1 - theta) * (1 + theta) / denom(a.clamp(max=1), theta) ** 2, 1.0)
    return torch.diag_embed(d)


def phi_rect_dtheta(p: Tensor, theta: Tensor) -> Tensor:
    """``∂φ_i/∂θ_j`` of [`phi_rect`][], shape ``(..., 2, 2)`` (diagonal).

    ``∂φ_j/∂θ_j = 2 p_j (|p_j| − 1) / D_j²``.
    """
    p, theta = promote(p, theta)
    a = p.abs()
    d = torch.where(a < 1, 2 * p * (a - 1) / denom(a.clamp(max=1), theta) ** 2, 0.0)
    return torch.diag_embed(d)


@register_family
class RectLayout(CenteredLayout):
    """The rectangular layout φ_rect of the paper (separable; pixels are rectangles), about a
    movable centre (see [`CenteredLayout`][]: ``center``, ``learn_center``).

    Examples:
        >>> layout = RectLayout(theta=(0.3, -0.2))
        >>> q = layout(torch.tensor([[0.5, 0.5]]))
        >>> torch.allclose(layout.inverse(q), torch.tensor([[0.5, 0.5]]), atol=1e-6)
        True
        >>> RectLayout((0.5, 0.5), center=(0.25, -0.5))(torch.tensor([[0.25, -0.5]]))
        tensor([[ 0.2500, -0.5000]])
    """

    family = "rect"
    separable = True
    straight_edges = True

    def _phi0(self, p: Tensor, theta: Tensor) -> Tensor:
        return phi_rect(p, theta)

    def _inverse0(self, q: Tensor, theta: Tensor) -> Tensor:
        return phi_rect_inverse(q, theta)

    def _jacobian0(self, p: Tensor, theta: Tensor) -> Tensor:
        return phi_rect_jacobian(p, theta)

    def _det0(self, p: Tensor, theta: Tensor) -> Tensor:
        return torch.diagonal(phi_rect_jacobian(p, theta), dim1=-2, dim2=-1).prod(-1)

    def _dtheta0(self, p: Tensor, theta: Tensor) -> Tensor:
        return phi_rect_dtheta(p, theta)
