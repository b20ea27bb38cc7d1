"""What every layout family does with its numbers: the dtype a layout takes
([`tensor_dtype`][]), θ from its unconstrained parameter ([`theta_of`][]), whether a tensor can
carry a gradient ([`wants_grad`][]), and a layout description's lists of numbers
([`config_numbers`][])."""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

__all__ = ["config_numbers", "gradient_asked", "tensor_dtype", "theta_of", "wants_grad"]


def tensor_dtype(*values: Any) -> torch.dtype:
    """The dtype a layout built from ``values`` gets unless ``dtype=`` says otherwise: that of the
    first floating-point tensor among them (as torch and Kornia keep an argument's dtype), else
    torch's default dtype."""
    for v in values:
        if isinstance(v, Tensor) and v.is_floating_point():
            return v.dtype
    return torch.get_default_dtype()


def theta_of(param: Tensor, bounds: Tensor) -> Tensor:
    """θ in float64 from what [`Layout.theta_source`][layoutwarp.layouts.base.Layout.theta_source]
    gives: ``bounds · tanh(param)``, or ``param`` itself where ``bounds`` is empty
    (differentiable; the formula a learnable layout's θ is made by, at float64)."""
    x = param.double()
    return x if bounds.numel() == 0 else bounds.to(x) * torch.tanh(x)


def wants_grad(t: Tensor) -> bool:
    """Whether ``t`` can carry a gradient to a parameter: it requires grad, or it is batched under
    ``torch.vmap`` (a batched tensor reports no ``requires_grad``, though what it holds may)."""
    return t.requires_grad or torch._C._functorch.is_batchedtensor(t)


def gradient_asked(t: Tensor) -> bool:
    """Whether autograd may ask ``t`` for a gradient: it requires grad, or, batched under
    ``torch.vmap``, the tensor it wraps does (a batched tensor reports no ``requires_grad`` of
    its own; [`wants_grad`][] counts every batched tensor)."""
    while torch._C._functorch.is_batchedtensor(t):
        t = torch._C._functorch.get_unwrapped(t)
    return t.requires_grad


def config_numbers(
    config: dict[str, Any], key: str, default: list[float] | None = None, *, required: bool = False
) -> list[float] | None:
    """``config[key]`` as a list of numbers (``default`` when absent, unless ``required``: a
    layout file without its θ must not become the uniform layout); ``ValueError`` otherwise.

    Used by [`Layout.from_config`][layoutwarp.layouts.base.Layout.from_config] of every family
    to read layout files.
    """
    if required and key not in config:
        raise ValueError(f"{key!r} is missing: the layout's description must give it")
    value = config.get(key, default)
    if value is not None and (
        not isinstance(value, list) or not all(isinstance(v, (int, float)) for v in value)
    ):
        raise ValueError(f"{key!r} must be a list of numbers, got {value!r}")
    return value
