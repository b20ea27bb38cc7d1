"""The arithmetic the families' maps are written in: denominators summed without cancellation
([`denom`][]), norms with a gradient at the origin ([`safe_norm`][]), and a point's and θ's
common precision ([`promote`][])."""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["denom", "promote", "safe_norm"]


def denom(a: Tensor, t: Tensor) -> Tensor:
    """``D(a, t) = 1 + t − 2ta`` (> 0 for ``|t| < 1``, ``0 <= a <= 1``), free of cancellation.

    For ``t >= 0`` it is summed as ``(1 − t) + 2t(1 − a)`` and for ``t < 0`` as
    ``(1 + t) + 2|t|a``: two non-negative terms either way, so the relative error stays at
    a few ulp even when ``t → ±1`` and ``a → 1``. Written as ``(1 − |t|) + 2|t| g`` with
    ``g = s + (1 − 2s) a`` (``s = [t >= 0]``, so ``g`` is ``1 − a`` or ``a``) to need only
    two fused multiply-adds on the large tensor ``a``.
    """
    s = (t >= 0).to(a.dtype)
    t_abs = t * (2 * s - 1)  # |t| whose derivative at t = 0 is the t >= 0 branch's, not 0
    g = torch.addcmul(s, 1 - 2 * s, a)
    return torch.addcmul(1 - t_abs, 2 * t_abs, g)


def safe_norm(p: Tensor) -> Tensor:
    """``‖p‖`` over the last axis (of size 2) with a zero (not NaN) gradient at the origin."""
    x, y = p[..., 0], p[..., 1]
    r2 = x * x + y * y
    nonzero = r2 > 0
    return torch.where(nonzero, torch.sqrt(torch.where(nonzero, r2, torch.ones_like(r2))), 0.0)


def promote(p: Tensor, theta: Tensor) -> tuple[Tensor, Tensor]:
    dtype = torch.promote_types(p.dtype, theta.dtype)
    return p.to(dtype), theta.to(device=p.device, dtype=dtype)
