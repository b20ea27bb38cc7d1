"""The elliptic family: φ_curv in a disk that fills the square (the reference code's third family)."""

from __future__ import annotations

import math
from collections.abc import Callable

import torch
from torch import Tensor

from .arith import promote, safe_norm
from .base import Layout, register_family
from .curv import phi_curv_inverse

__all__ = ["EllipticLayout", "disk_to_square", "square_to_disk"]


def _sqrt0(x: Tensor) -> Tensor:
    """``√max(x, 0)`` with a zero (not infinite) gradient where the argument is 0."""
    pos = x > 0
    return torch.where(pos, torch.sqrt(torch.where(pos, x, torch.ones_like(x))), torch.zeros_like(x))


def square_to_disk(p: Tensor) -> Tensor:
    """The elliptical grid mapping of the square onto the unit disk: ``u = x √(1 − y²/2)``,
    ``v = y √(1 − x²/2)`` (points ``(..., 2)``; the square's border goes to the unit circle)."""
    x, y = p[..., 0], p[..., 1]
    return torch.stack([x * _sqrt0(1 - y * y / 2), y * _sqrt0(1 - x * x / 2)], -1)


def disk_to_square(q: Tensor) -> Tensor:
    """The inverse of [`square_to_disk`][]: ``x = ½√(2 + u² − v² + 2√2 u) − ½√(2 + u² − v² − 2√2 u)``
    and likewise ``y`` with ``u`` and ``v`` exchanged, evaluated as ``x = √2 u / (√(…+…) + √(…−…))``
    (the two roots' difference is ``4√2 u`` over their sum): the difference of two nearly equal
    roots lost all but a few digits of a small ``x`` (near the axes, 8e-9 relative); the quotient
    keeps them."""
    u, v = q[..., 0], q[..., 1]
    r2 = 2 * math.sqrt(2)
    a, b = 2 + u * u - v * v, 2 - u * u + v * v
    return torch.stack([_root_difference(a, r2 * u), _root_difference(b, r2 * v)], -1)


def _root_difference(a: Tensor, t: Tensor) -> Tensor:
    """``(√(a + t) − √(a − t)) / 2`` as ``t / (√(a + t) + √(a − t))``, without cancellation (0
    where both roots are 0)."""
    total = _sqrt0(a + t) + _sqrt0(a - t)
    return torch.where(
        total > 0, t / torch.where(total > 0, total, torch.ones_like(total)), torch.zeros_like(t)
    )


@register_family
class EllipticLayout(Layout):
    """The curvilinear map in a disk that fills the square: ``φ = E⁻¹ ∘ φ_curv ∘ E`` with ``E`` the
    elliptical square-to-disk mapping ([`square_to_disk`][]).

    The paper's φ_curv deforms only inside the unit circle, so the sensor's corners keep uniform
    pixels (§5: "restricted to a circular region"); the paper's public code has this third family,
    which first maps the whole square onto the disk, applies φ_curv there and maps back, so the
    deformation reaches the corners. ``E`` is a bijection of the open square onto the open disk
    sending the border onto the unit circle, which φ_curv fixes pointwise, so φ is again a
    bijection of S that fixes its border; it is smooth inside the square (φ_curv's kink lies on
    the circle, which is the square's border here), so pixel edges are curved but have no kinks.
    The inverse is closed form: ``E⁻¹ ∘ φ_curv⁻¹ ∘ E``. ``θ > 0`` puts more pixels at the centre;
    θ = 0 is the uniform layout. Jacobian and ∂φ/∂θ come from autograd through the closed forms.

    Examples:
        >>> layout = EllipticLayout((0.5, 0.3), dtype=torch.float64)
        >>> p = torch.tensor([[0.9, -0.95], [0.2, 0.1]], dtype=torch.float64)
        >>> torch.allclose(layout.inverse(layout(p)), p, atol=1e-12)
        True
    """

    family = "elliptic"
    kernel_map = "elliptic"

    def phi(self, p: Tensor, theta: Tensor) -> Tensor:
        return _elliptic_phi(p, theta)

    def phi_inverse(self, q: Tensor, theta: Tensor) -> Tensor:
        # E⁻¹ takes a difference of nearly equal roots near the corners: in float32 it lost 4e-5
        # there (and left the square by 1e-5); computed in float64 and rounded once
        dtype = torch.promote_types(q.dtype, theta.dtype)
        wide = torch.promote_types(dtype, torch.float64)
        return _through_disk(phi_curv_inverse, q.to(wide), theta.to(wide)).to(dtype)


def _elliptic_phi(p: Tensor, theta: Tensor) -> Tensor:
    """``E⁻¹ ∘ φ_curv ∘ E`` evaluated to a few ulps everywhere in the open square (the identity
    on and outside its border). Written out, each coordinate is a difference of two roots
    ``(√A₊ − √A₋)/2``; near a corner ``A₋`` is a difference of nearly equal numbers, so a rounding
    of ``E(p)`` of one ulp moved φ by ``√ε`` (1e-8 at 1e-12 from a corner). Here every small
    quantity is formed from ``x`` and ``y`` directly, by the identities (``c_x = 1 − x²``,
    ``c_y = 1 − y²``, coordinates taken as ``|x|, |y|`` and the signs restored, ``u, v = E(p)``):
    ``1 − ‖E(p)‖ = c_x c_y / (1 + ‖E(p)‖)``; φ_curv's change ``Δu = −2θ (1 − r) u / (1 − θ + 2θ(1 − r))``;
    ``(√2 − u)² − v² = (√(2 − y²) − x)²`` with ``√(2 − y²) − x = (c_x + c_y) / (√(2 − y²) + x)``; so
    ``A₋ = m² − 2(√2 − u)Δu − 2vΔv + Δu² − Δv²``, and the coordinate is ``2√2 u' / (√A₊ + √A₋)``.
    At θ = 0 the value is ``p`` exactly (the derivatives the closed form's)."""
    p, theta = promote(p, theta)
    inside = (p.abs() < 1).all(-1, keepdim=True)
    q = torch.where(inside, p, torch.zeros_like(p))
    ax, ay = q[..., 0].abs(), q[..., 1].abs()
    cx, cy = (1 - ax) * (1 + ax), (1 - ay) * (1 + ay)
    sx, sy = torch.sqrt(1 + cy), torch.sqrt(1 + cx)  # √(2 − y²), √(2 − x²)
    h = math.sqrt(2)
    u, v = ax * sx / h, ay * sy / h
    r = safe_norm(torch.stack([u, v], -1))
    gap = cx * cy / (1 + r)  # 1 − r
    tx, ty = theta[..., 0], theta[..., 1]
    du = -2 * tx * gap * u / ((1 - tx) + 2 * tx * gap)
    dv = -2 * ty * gap * v / ((1 - ty) + 2 * ty * gap)
    u2, v2 = u + du, v + dv
    mx, my = (cx + cy) / (sx + ax), (cx + cy) / (sy + ay)
    a_minus = mx * mx - 2 * (h - u) * du - 2 * v * dv + du * du - dv * dv
    b_minus = my * my - 2 * (h - v) * dv - 2 * u * du + dv * dv - du * du
    a_plus = 2 + u2 * u2 - v2 * v2 + 2 * h * u2
    b_plus = 2 - u2 * u2 + v2 * v2 + 2 * h * v2
    x = 2 * h * u2 / (torch.sqrt(a_plus) + _sqrt0(a_minus))
    y = 2 * h * v2 / (torch.sqrt(b_plus) + _sqrt0(b_minus))
    out = torch.stack([torch.copysign(x, q[..., 0]), torch.copysign(y, q[..., 1])], -1)
    # θ = 0 is the uniform layout: φ is p itself, exactly, with the closed form's derivatives (it
    # rounds off p by an ulp, which put an edge meant to lie on a source cell line on either side
    # of it: one-sided θ-gradients there, other ones on the compiled mesh)
    uniform = ((tx == 0) & (ty == 0))[..., None]
    out = torch.where(uniform, out + (q - out).detach(), out)
    return torch.where(inside, out, p)


def _through_disk(fn: Callable[[Tensor, Tensor], Tensor], p: Tensor, theta: Tensor) -> Tensor:
    """``E⁻¹ ∘ fn ∘ E`` inside the open square ([`square_to_disk`][]), the identity on and outside
    its border."""
    p, theta = promote(p, theta)
    inside = (p.abs() < 1).all(-1, keepdim=True)
    out = disk_to_square(fn(square_to_disk(torch.where(inside, p, torch.zeros_like(p))), theta))
    return torch.where(inside, out, p)
