"""What layoutwarp's torch operators share: how a layout and a camera travel into one, which
backend runs it, where its randomness comes from, and how a second derivative is refused.

layoutwarp's compiled kernels enter PyTorch as registered operators in the ``layoutwarp``
namespace (``torch.ops.layoutwarp.*``), each defined next to its implementation with
``torch.library.custom_op``, a fake kernel (shapes only) and an autograd formula that saves its
tensors the standard way. An operator is opaque to ``torch.compile``: the mesh's data-dependent
sizes, numpy and the kernels' locks stay inside it, so a model holding a
[`SensorLayer`][layoutwarp.sensor.SensorLayer] compiles to one graph and exports
(``torch.export``). [`OPERATORS`][] lists them (the tests run ``torch.library.opcheck`` on each).

Operators take tensors, numbers and text only, so a layout travels as its *token*
([`layout_token`][]: its description as JSON text, or a handle of the object for a family
that is not registered) next to its θ as a tensor, and a camera as its JSON text
([`SensorPhysics.to_json`][layoutwarp.physics.SensorPhysics.to_json]).
"""

from __future__ import annotations

import contextlib
import json
import weakref
from collections.abc import Iterator
from typing import TYPE_CHECKING, Any

import torch
from torch import Tensor

from .caches import LRU
from .checks import all_finite, raise_nonfinite

if TYPE_CHECKING:
    from .layouts import Layout
    from .physics import SensorPhysics

__all__ = [
    "OPERATORS",
    "SECOND_ORDER",
    "TEMPLATES",
    "autograd_inside",
    "backend",
    "first_order_only",
    "generator_of",
    "layout_of",
    "layout_token",
    "no_context",
    "object_of",
    "object_token",
    "physics_of",
    "random_seed",
    "seed_value",
]

#: Every operator layoutwarp registers, by name in the ``layoutwarp`` namespace (filled as their
#: modules are imported: [`layoutwarp.integrators`][], [`layoutwarp.resampler`][],
#: [`layoutwarp.physics`][]).
OPERATORS: dict[str, Any] = {}

#: The message of a refused second derivative (``{op}``: the operator).
SECOND_ORDER = (
    "layoutwarp::{op} has exact first derivatives only (its backward is a compiled formula, not a "
    "differentiable graph); for second derivatives of a layout use method='point' or "
    "method='montecarlo' with grad='autograd' (bilinear radiance)"
)

_OBJECTS: weakref.WeakValueDictionary[str, Layout] = weakref.WeakValueDictionary()
#: Layouts rebuilt from their tokens inside the operators: a template per token (its own θ
#: unused), and a layout per token and θ where the operator needs one whose own θ is that θ.
TEMPLATES: LRU[Layout] = LRU("layouts of operators", 16)


def make_token(layout: Layout) -> str:
    """A layout's token as made at its construction (see [`layout_token`][])."""
    from .layoutfile import layout_spec
    from .layouts import FAMILIES

    if FAMILIES.get(layout.family) is type(layout):
        return json.dumps(layout_spec(layout), sort_keys=True)
    token = f"object:{id(layout)}"
    _OBJECTS[token] = layout
    return token


def layout_token(layout: Layout) -> str:
    """The text by which ``layout`` enters an operator: the JSON description of a registered
    family (so an exported program holds all it needs), else a handle of the object in this
    process. Made when the layout is constructed (and again when a state dict is loaded into
    it), so that reading it costs a compiled graph nothing; θ travels beside it as a tensor."""
    token = getattr(layout, "_token", None)
    if token is None:  # a subclass that skipped Layout's constructor: made now (eagerly)
        token = layout._token = make_token(layout)
    return token


def layout_of(token: str, theta: Tensor | None = None) -> Layout:
    """The layout of a [`layout_token`][]: with ``theta``, one whose own θ is ``theta`` (kept per
    token and value); without, a template for the maps that take θ as an argument."""
    if token.startswith("object:"):
        layout = _OBJECTS.get(token)
        if layout is None:
            raise RuntimeError(f"layoutwarp: the layout {token} no longer exists in this process")
        return layout
    from .layoutfile import layout_from_spec

    if theta is None:
        return TEMPLATES.get(token, lambda: layout_from_spec(json.loads(token)))
    values = tuple(theta.detach().to("cpu", torch.float64).tolist())

    def build() -> Layout:
        layout = layout_from_spec(json.loads(token))
        layout.set_theta(torch.tensor(values, dtype=torch.float64))
        return layout

    return TEMPLATES.get((token, values), build)


_CALLABLES: LRU[Any] = LRU("callables of operators", 32)


def object_token(obj: Any) -> str:
    """A handle (text) of a Python object an operator needs, e.g. a callable radiance, valid in
    this process while it is among the last 32 handed in."""
    token = f"callable:{id(obj)}"
    _CALLABLES.get(token, lambda: obj)
    return token


def object_of(token: str) -> Any:
    """The object of an [`object_token`][]."""
    return _CALLABLES.get(token, lambda: _gone(token))


def _gone(token: str) -> Any:
    raise RuntimeError(f"layoutwarp: the object {token} is no longer held by this process")


def physics_of(text: str) -> SensorPhysics | None:
    """The camera of a [`SensorPhysics.to_json`][layoutwarp.physics.SensorPhysics.to_json] text
    (``""``: none)."""
    if not text:
        return None
    from .physics import SensorPhysics

    return _PHYSICS.get(text, lambda: SensorPhysics.from_json(text))


_PHYSICS: LRU[SensorPhysics] = LRU("cameras of operators", 16)


def backend(x: Tensor, group: str, *, name: str | None = None, wait: bool = False) -> str:
    """Which implementation runs an operator's work on ``x``: ``"cuda"`` (numba-cuda kernels, on
    a CUDA device or in numba's CUDA simulator, unless the kernel ``name`` failed here before),
    ``"numba"`` (the compiled CPU kernels of ``group``, when [`layoutwarp.jit`][] has them ready,
    or at once with ``wait``) or ``"torch"`` (the reference, any device). The one place that
    decides; callers that need autograd through the work ask for ``"torch"`` themselves."""
    from . import jit, kernels
    from .kernels.device import runs_on_device, usable

    dtype = torch.float32 if x.dtype == torch.float32 else torch.float64
    if runs_on_device(x):
        ok = kernels.available() and kernels.cuda_available(str(dtype).split(".")[1])
        return "cuda" if ok and (name is None or usable(name)) else "torch"
    if x.device.type == "cpu":
        with autograd_inside():  # a first call's warm-up trains a step
            if jit.ready(group, dtype, wait=wait):
                return "numba"
    return "torch"


#: The dispatcher's keys turned off outside any operator (autocast's): inside an operator's
#: implementation it turns autograd off too.
_OUTSIDE = torch._C._dispatch_tls_local_exclude_set()


@contextlib.contextmanager
def autograd_inside() -> Iterator[None]:
    """Autograd recording inside an operator's implementation, where the dispatcher has turned it
    off: for the work an operator does with autograd of its own (a gradient computed again on the
    torch path, a warm-up's training step)."""
    include = torch._C._dispatch_tls_local_include_set()
    with torch._C._ForceDispatchKeyGuard(include, _OUTSIDE), torch.enable_grad():
        yield


def first_order_only(op: Any, name: str) -> None:
    """Register on ``op`` (a backward operator) an autograd formula that refuses, in one line, the
    derivative of the derivative it computes: a second derivative is exact or refused, never a
    value that leaves out the second-order terms."""

    def refuse(ctx: Any, *grads: Tensor) -> None:
        raise RuntimeError(SECOND_ORDER.format(op=name))

    op.register_autograd(refuse, setup_context=no_context)


def no_context(ctx: Any, inputs: tuple, output: Any) -> None:
    """An operator's ``setup_context`` where its backward needs nothing saved."""
    return None


def random_seed(generator: torch.Generator | None, seed: int | None = None) -> Tensor:
    """A 0-d int64 tensor that seeds an operator's random draws: ``seed`` as it is, else a draw
    of ``generator`` (torch's global one when ``None``; under ``torch.compile`` a draw of the
    compiled graph's). Operators that draw noise take their randomness from it (the same seed,
    the same draws, eager or compiled)."""
    if seed is not None:
        return torch.tensor(seed, dtype=torch.int64)
    if generator is None:
        return torch.randint(0, 2**62, (), dtype=torch.int64)
    return torch.randint(0, 2**62, (), generator=generator, dtype=torch.int64, device=generator.device).cpu()


def register(op: Any) -> Any:
    """Add ``op`` to [`OPERATORS`][] (its name without the namespace) and return it."""
    OPERATORS[op._name] = op
    return op


def seed_value(seed: Tensor) -> int:
    """The value of a 0-d seed tensor, read inside an operator (a CPU seed's by numpy: no torch
    operation, no device wait)."""
    return int(seed.numpy() if seed.device.type == "cpu" else seed)


def generator_of(seed: Tensor, device: torch.device) -> torch.Generator:
    """A generator on ``device`` seeded with the value of the 0-d ``seed`` (read inside an
    operator: where its draws are made)."""
    return torch.Generator(device).manual_seed(seed_value(seed) % 2**63)


# ----------------------------------------------------------------------------------------
# Operators of their own: a finiteness guard and seeded draws
# ----------------------------------------------------------------------------------------
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
def _uniform(seed: Tensor, shape: list[int], like: Tensor) -> Tensor:
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
