"""Operators of their own: a finiteness guard inside the graph and seeded draws
(``layoutwarp::guard_finite``, ``layoutwarp::uniform``, ``layoutwarp::seed_sequence``)."""

from __future__ import annotations

from collections.abc import Sequence  # an operator's list argument (torch 2.6 reads no list[int])
from typing import Any

import torch
from torch import Tensor

from ..checks import all_finite, raise_nonfinite
from .base import generator_of, no_context, register, seed_value

__all__: list[str] = []


@torch.library.custom_op("layoutwarp::guard_finite", mutates_args=())
def _guard_finite(out: Tensor, source: Tensor, name: str) -> Tensor:
    """``out`` (a copy), after a one-line ``ValueError`` naming ``name`` where ``source`` holds
    NaN or Inf: the check of an input a sampling integrator may miss, inside the graph."""
    if not all_finite(source):
        raise_nonfinite(source, name)
    return out.clone()


@_guard_finite.register_fake
def _(out, source, name):
    return torch.empty_like(out)


def _guard_grad(ctx: Any, grad: Tensor) -> tuple:
    return grad, None, None


_guard_finite.register_autograd(_guard_grad, setup_context=no_context)
register(_guard_finite)


@torch.library.custom_op("layoutwarp::uniform", mutates_args=())
def _uniform(seed: Tensor, shape: Sequence[int], like: Tensor) -> Tensor:
    """Uniform draws in ``[0, 1)`` of ``shape``, ``like``'s dtype and device: the first draws of a
    generator on that device seeded with ``seed`` (what ``torch.rand(shape,
    generator=torch.Generator(device).manual_seed(seed))`` gives)."""
    return torch.rand(shape, generator=generator_of(seed, like.device), dtype=like.dtype, device=like.device)


@_uniform.register_fake
def _(seed, shape, like):
    return like.new_empty(shape)


register(_uniform)


@torch.library.custom_op("layoutwarp::seed_sequence", mutates_args=())
def _seed_sequence(count: Tensor, seed: int) -> Tensor:
    """The ``count``-th seed (0-d int64) of the sequence that ``seed`` starts: one draw of a
    generator seeded with both, so consecutive calls draw new noise and every run the same."""
    g = torch.Generator().manual_seed((seed * 1_000_003 + seed_value(count)) % 2**63)
    return torch.randint(0, 2**62, (), generator=g, dtype=torch.int64)


@_seed_sequence.register_fake
def _(count, seed):
    return torch.empty((), dtype=torch.int64)


register(_seed_sequence)
