"""What layoutwarp's torch operators share: how a layout and a camera travel into one, which
backend runs it, where its randomness comes from, and how a second derivative is refused.

layoutwarp's compiled kernels enter PyTorch as registered operators in the ``layoutwarp``
namespace (``torch.ops.layoutwarp.*``), each defined next to its implementation with
``torch.library.custom_op``, a fake kernel (shapes only) and an autograd formula that saves its
tensors the standard way. An operator is opaque to ``torch.compile``: the mesh's data-dependent
sizes, numpy and the kernels' locks stay inside it, so a model holding a
[`SensorLayer`][layoutwarp.sensor.SensorLayer] compiles to one graph and exports
(``torch.export``). [`OPERATORS`][] lists them (the tests run ``torch.library.opcheck`` on each).

Operators take tensors and one text, the call's *description* ([`describe_call`][]): the
settings that do not change with θ, as JSON. A layout travels in it as its *token*
([`layout_token`][]: its description as JSON text, or a handle of the object for a family
that is not registered) next to its θ as a tensor, and a camera as its JSON text
([`SensorPhysics.to_json`][layoutwarp.physics.SensorPhysics.to_json]). A new θ or a loaded
checkpoint leaves the description as it was, so a compiled graph is not compiled again.
"""

from __future__ import annotations

import contextlib
import json
import math
import sys
from collections.abc import Callable, Iterator, Sequence
from types import SimpleNamespace
from typing import TYPE_CHECKING, Any, NoReturn

import torch
from torch import Tensor
from torch._C._functorch import TransformType
from torch._functorch.pyfunctorch import retrieve_all_functorch_interpreters
from torch.autograd import forward_ad

from .. import jit, kernels
from ..caches import LRU, ObjectMemo, version_of
from ..checks import values_readable
from ..kernels.device import runs_on_device, usable
from ..layoutfile import layout_from_spec
from ..layouts import layout_by_handle

if TYPE_CHECKING:
    from ..layouts import Layout

__all__ = [
    "OPERATORS",
    "RANDOM",
    "SECOND_ORDER",
    "TEMPLATES",
    "TRANSFORMS",
    "CallSettings",
    "autograd_inside",
    "backend",
    "batch_rule",
    "check_theta",
    "describe_call",
    "first_order_only",
    "generator_of",
    "layout_of",
    "layout_token",
    "no_context",
    "object_of",
    "object_token",
    "operator_theta",
    "random_seed",
    "read_call",
    "refuse",
    "refuse_grad_transforms",
    "seed_value",
    "theta_values",
]

#: Every operator layoutwarp registers, by name in the ``layoutwarp`` namespace (filled as their
#: modules are imported: those of [`layoutwarp.operators`][], [`layoutwarp.resampler`][],
#: [`layoutwarp.physics`][], [`layoutwarp.maps`][]).
OPERATORS: dict[str, Any] = {}

#: The message of a refused second derivative (``{op}``: the operator).
SECOND_ORDER = (
    "layoutwarp::{op} has exact first derivatives only (its backward is a compiled formula, not a "
    "differentiable graph); for second derivatives of a layout use method='point' or "
    "method='montecarlo' with grad='autograd' (bilinear radiance)"
)

#: Layouts rebuilt from their tokens inside the operators: a template per token (its own θ
#: unused), and a layout per token and θ where the operator needs one whose own θ is that θ.
TEMPLATES: LRU[Layout] = LRU("layouts of operators", 16)


def layout_token(layout: Layout) -> str:
    """The text by which ``layout`` enters an operator: the JSON description of a registered
    family (so an exported program holds all it needs), else a handle of the object in this
    process ([`Layout.make_token`][layoutwarp.layouts.base.Layout.make_token]). Made when the
    layout is constructed (and again when a state dict is loaded into it, θ's part kept), so
    that reading it costs a compiled graph nothing and a new θ compiles nothing again; θ
    travels beside it as a tensor."""
    token = getattr(layout, "_token", None)
    if token is None or (token.startswith("object:") and token != f"object:{id(layout)}"):
        token = layout._token = layout.make_token()  # a constructor skipped, or a copy's handle
    return token


def describe_call(**settings: bool | int | float | str | Sequence[int] | torch.dtype) -> str:
    """The text an operator takes beside its tensors: ``settings`` (a layout's token, sizes, the
    tolerance, flags, a dtype, ...) as one JSON object, read back by [`read_call`][]. Plain string
    work, so ``torch.compile`` folds it into a constant of the graph."""
    return "{" + ", ".join(f'"{key}": {_json_text(value)}' for key, value in settings.items()) + "}"


def _json_text(value: bool | int | float | str | Sequence[int] | torch.dtype) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(int(value))
    if isinstance(value, float):
        return repr(float(value)) if math.isfinite(value) else _NONFINITE[str(float(value))]
    if isinstance(value, torch.dtype):
        return f'"{str(value).removeprefix("torch.")}"'
    if isinstance(value, (tuple, list)):
        return "[" + ", ".join(_json_text(v) for v in value) + "]"
    if isinstance(value, str):
        for raw, escaped in _ESCAPES:
            value = value.replace(raw, escaped)
        return '"' + value + '"'
    raise TypeError(
        f"describe_call takes bools, numbers, texts, sequences and dtypes, got {type(value).__name__}"
    )


#: How JSON writes what a float's ``repr`` cannot, and the characters a JSON text escapes.
_NONFINITE = {"nan": "NaN", "inf": "Infinity", "-inf": "-Infinity"}
_ESCAPES = (("\\", "\\\\"), ('"', '\\"'), ("\n", "\\n"), ("\r", "\\r"), ("\t", "\\t"))


class CallSettings(SimpleNamespace):
    """The settings of a call's description as attributes; one it lacks is refused in one line
    naming the operator."""

    def __getattr__(self, name: str) -> Any:
        if name.startswith("__"):
            raise AttributeError(name)
        refuse(self.__dict__.get("_op", "operator"), "call", f"has no setting {name!r}")


#: The settings of the descriptions operators were handed, per operator and text.
CALLS: LRU[CallSettings] = LRU("descriptions of operator calls", 64)


def read_call(text: str, op: str) -> CallSettings:
    """The settings of a [`describe_call`][] text as attributes (lists as tuples, dtypes as
    ``torch.dtype``; kept per text: read them, never change them). A text that is not one, or a
    setting it lacks, is refused in one line naming ``op``."""
    return CALLS.get((op, text), lambda: _parse_call(text, op))


def _parse_call(text: str, op: str) -> CallSettings:
    try:
        settings = json.loads(text)
        if not isinstance(settings, dict):
            raise ValueError("not a JSON object")
    except ValueError as err:
        refuse(op, "call", f"must be a call's description (describe_call), got {text[:60]!r}: {err}")
    for key, value in settings.items():
        if isinstance(value, list):
            settings[key] = value = tuple(value)
        if key == "dtype":
            settings[key] = getattr(torch, str(value), None)
            if not isinstance(settings[key], torch.dtype):
                refuse(op, "call", f"names no torch dtype: {value!r}")
        elif key in _SETTING_KINDS and not _SETTING_KINDS[key][0](value):
            refuse(op, "call", f"setting {key!r} must be {_SETTING_KINDS[key][1]}, got {value!r}")
    settings["_op"] = op  # the operator its refusals name (a setting of that name is replaced)
    return CallSettings(**settings)


def _count(value: Any, least: int) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and value >= least


#: What the operators' shared settings must be: a test and its words.
_SETTING_KINDS: dict[str, tuple[Callable[[Any], bool], str]] = {
    "size": (
        lambda v: isinstance(v, tuple) and len(v) == 2 and all(_count(n, 1) for n in v),
        "[h, w], positive",
    ),
    "tol": (
        lambda v: isinstance(v, (int, float)) and not isinstance(v, bool) and 0 < v < math.inf,
        "a positive number",
    ),
    "samples": (lambda v: _count(v, 1), "a positive integer"),
    **{k: (lambda v: isinstance(v, bool), "true or false") for k in ("jacobian", "check", "with_areas")},
    **{
        k: (lambda v: isinstance(v, str), "a text")
        for k in ("layout", "backend", "physics", "output", "radiance", "radiance_fn")
    },
}


def refuse(op: str, argument: str, message: str) -> NoReturn:
    """Raise ``ValueError`` in one line naming the operator and its argument: how every operator
    answers a bad argument (a user may call ``torch.ops.layoutwarp.*`` directly)."""
    raise ValueError(f"layoutwarp::{op}: {argument} {message}")


def check_theta(op: str, theta: Tensor, layout: Layout, bounds: Tensor | None = None) -> None:
    """Refuse (in one line) a θ (or ρ) that is not the layout's ``P`` values, or bounds of
    another length."""
    n = layout.num_params or 0
    if theta.shape != (n,):
        refuse(
            op, "theta", f"must hold the {layout.family} layout's {n} values, got shape {tuple(theta.shape)}"
        )
    if bounds is not None and bounds.numel() and bounds.shape != theta.shape:
        refuse(op, "bounds", f"must be empty or as long as theta ({n}), got shape {tuple(bounds.shape)}")


def layout_of(token: str, theta: Tensor | None = None, op: str = "operator") -> Layout:
    """The layout of a [`layout_token`][]: with ``theta``, one whose own θ is ``theta`` (kept per
    token and value); without, a template for the maps that take θ as an argument. A text that
    is no layout's token is refused in one line naming ``op``."""
    if token.startswith("object:"):
        layout = layout_by_handle(token)
        if layout is None:
            raise RuntimeError(f"layoutwarp: the layout {token} no longer exists in this process")
        return layout
    if not token.startswith("{"):
        refuse(op, "layout", f"must be a layout's token (layout_token(layout)), got {token[:60]!r}")

    def spec() -> dict[str, Any]:
        try:
            return json.loads(token)
        except json.JSONDecodeError as err:
            refuse(op, "layout", f"must be a layout's token (JSON text), got {token[:60]!r}: {err}")

    if theta is None:  # kept: never made of inference-mode tensors, which autograd refuses later
        return TEMPLATES.get(token, lambda: _outside_inference(lambda: layout_from_spec(spec())))
    values = theta_values(theta)

    def build() -> Layout:
        layout = layout_from_spec(spec())
        layout.set_theta(torch.tensor(values, dtype=torch.float64))
        return layout

    return TEMPLATES.get((token, values), lambda: _outside_inference(build))


def _outside_inference(make: Callable[[], Any]) -> Any:
    """``make()`` with inference mode off: what the caches keep must serve autograd later."""
    with torch.inference_mode(False):
        return make()


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


#: The values of the θ tensors that operators were handed, per tensor and version (a fixed
#: layout's θ is the same buffer every call: read once).
THETA_VALUES = ObjectMemo("θ values of operators")


def operator_theta(layout: Layout) -> Tensor:
    """θ as ``layout`` hands it to the operators beside its token: a fixed layout's as it was set
    (float64, [`Layout.theta_as`][layoutwarp.layouts.base.Layout.theta_as]), a learnable one's in
    its dtype (differentiable, as a training step computes it, with or without gradient)."""
    return layout.theta if layout.learnable else layout.theta_as(torch.float64)


def theta_values(theta: Tensor) -> tuple[float, ...]:
    """θ's values as float64 numbers, read once per tensor, version and data (``.to()`` and a new
    ``.data`` change a tensor's data, and no version counts it)."""
    state = (version_of(theta), theta.data_ptr(), theta.dtype)
    return THETA_VALUES.get(theta, state, lambda: tuple(theta.detach().to("cpu", torch.float64).tolist()))


#: The values of [`operator_theta`][] per layout, while the tensors θ is made of (``rho``, and
#: a fixed layout's ``fixed_theta``) are the same, unchanged in place, with the same data
#: (``.to()`` sets a parameter's ``.data``, which no version counts), as trainable as they were,
#: and its token the same.
LAYOUT_THETAS = ObjectMemo("θ values of layouts")


def layout_theta_values(layout: Layout) -> tuple[float, ...]:
    """θ's values as float64 numbers, of [`operator_theta`][] of ``layout``, remembered per
    layout (a fixed layout's small call pays a look-up, not θ's computation)."""
    state: tuple = (layout_token(layout),)
    for t in (layout.rho, getattr(layout, "fixed_theta", None)):
        if t is not None:
            state += (t, version_of(t), t.data_ptr(), t.dtype, t.requires_grad)
    return LAYOUT_THETAS.get(layout, state, lambda: theta_values(operator_theta(layout)))


def backend(x: Tensor, group: str, *, name: str | None = None, wait: bool = False) -> str:
    """Which implementation runs an operator's work on ``x``: ``"cuda"`` (numba-cuda kernels, on
    a CUDA device or in numba's CUDA simulator, unless the kernel ``name`` failed here before),
    ``"numba"`` (the compiled CPU kernels of ``group``, when [`layoutwarp.jit`][] has them ready,
    or at once with ``wait``) or ``"torch"`` (the reference, any device). The one place that
    decides; callers that need autograd through the work ask for ``"torch"`` themselves."""
    dtype = torch.float32 if x.dtype == torch.float32 else torch.float64
    if runs_on_device(x):
        ok = kernels.available() and kernels.cuda_available(str(dtype).split(".")[1])
        return "cuda" if ok and (name is None or usable(name)) else "torch"
    if x.device.type == "cpu" and jit.ready(group, dtype, wait=wait):
        return "numba"
    return "torch"


#: The dispatcher's keys turned off outside any operator (autocast's): inside an operator's
#: implementation it turns autograd off too.
with torch.inference_mode(False):  # as outside inference mode, wherever the package is imported
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
    """A 0-d int64 tensor that seeds an operator's random draws: ``seed`` as it is (modulo 2^63:
    the seeds a call derives from its own, ``seed + 1`` and ``seed + 2``, wrap past
    ``layoutwarp.checks.SEED_MAX``), else a draw of ``generator`` (torch's global one
    when ``None``; under ``torch.compile`` a draw of the compiled graph's). Operators that draw
    noise take their randomness from it (the same seed, the same draws, eager or compiled)."""
    if seed is not None:
        return torch.tensor(seed % 2**63, dtype=torch.int64)
    if generator is None:
        return torch.randint(0, 2**62, (), dtype=torch.int64)
    return torch.randint(0, 2**62, (), generator=generator, dtype=torch.int64, device=generator.device).cpu()


def register(op: Any, fold: int | None = None, outputs: tuple[str, ...] = ("image",)) -> Any:
    """Add ``op`` to [`OPERATORS`][] (by its name without the namespace), give it a ``torch.vmap``
    rule ([`batch_rule`][]: the batch folded into the images of argument ``fold``, each output
    split back by its role in ``outputs``, else one call per sample) and return it."""
    OPERATORS[op._name] = op
    op.register_vmap(batch_rule(op, fold, outputs))
    _disable_dynamo_lazily(op)
    return op


def _disable_dynamo_lazily(op: Any) -> None:
    """torch runs a custom operator's implementation through ``torch._dynamo.disable``, made at
    its first call, which imports ``torch._dynamo`` (1–2 s) in every process, compiled or not.
    Until something imports it (``torch.compile``, ``torch.export``), nothing can trace the
    implementation, so it runs as it is; from then on through torch's own disabled wrapper.
    Where a torch release keeps these internals otherwise, nothing changes."""
    for wrapper in getattr(op, "_backend_fns", {}).values():
        impl = getattr(wrapper, "__wrapped__", None)  # torch._disable_dynamo's functools.wraps
        if impl is None or getattr(impl, "__dynamo_disable", None) is not None:
            continue

        def run(*args: Any, _impl: Callable = impl, _wrapper: Callable = wrapper, **kwargs: Any) -> Any:
            if "torch._dynamo" not in sys.modules:
                return _impl(*args, **kwargs)
            _impl.__dynamo_disable = None  # torch's wrapper makes its disabled function from now on
            return _wrapper(*args, **kwargs)

        impl.__dynamo_disable = run


#: The message of a refused ``torch.func`` gradient transform.
TRANSFORMS = (
    "layoutwarp's operators take torch.func.vmap, not torch.func.{what} (their gradients are "
    "registered with autograd): use torch.autograd.grad, or loss.backward()"
)


FORWARD_AD = (
    "layoutwarp's operators have no forward-mode derivatives (a tangent from "
    "torch.autograd.forward_ad would be dropped): use torch.autograd.grad, or loss.backward()"
)


def refuse_forward_ad(*tensors: object) -> None:
    """Raise, in one line, where any of ``tensors`` carries a forward-mode tangent
    (``torch.autograd.forward_ad.make_dual``): the operators register reverse-mode formulas only,
    and torch would drop the tangent without a word."""
    if forward_ad._current_level < 0 or torch.compiler.is_compiling():
        return  # no dual level open (the usual case: one integer read)
    if any(isinstance(t, Tensor) and forward_ad.unpack_dual(t).tangent is not None for t in tensors):
        raise RuntimeError(FORWARD_AD)


def plain_eager(*tensors: Tensor) -> bool:
    """Whether a call on ``tensors`` may run an operator's implementation directly, skipping
    torch's dispatcher (about 140 µs of a small call): eager, not compiling or tracing, no
    ``vmap`` or other transform, no dispatch mode (fake tensors, ``make_fx``), plain tensors, and
    none that autograd must follow. Anything else goes through the registered operator."""
    if not values_readable():
        return False
    grad = torch.is_grad_enabled()
    return all(type(t) is Tensor and not (grad and t.requires_grad) for t in tensors)


def refuse_grad_transforms() -> None:
    """Raise, in one line, inside ``torch.func.grad``, ``jacrev``, ``vjp`` or ``jvp``, whose
    autograd layers cannot enter layoutwarp's operators (``torch.func.vmap`` can)."""
    if torch.compiler.is_compiling() or torch._C._functorch.maybe_current_level() is None:
        return  # no transform around the call (a compiled graph is asked first: it reads no level)
    for interpreter in retrieve_all_functorch_interpreters():
        if interpreter.key() in (TransformType.Grad, TransformType.Jvp):
            what = "grad, jacrev or vjp" if interpreter.key() == TransformType.Grad else "jvp or jacfwd"
            raise RuntimeError(TRANSFORMS.format(what=what))


def batch_rule(
    op: Any, fold: int | None, outputs: tuple[str, ...] = ("image",)
) -> Callable[..., tuple[Any, Any]]:
    """A ``torch.vmap`` rule for ``op``: where only argument ``fold`` (images ``(N, H, W)``) is
    batched, the batch joins ``N`` and the operator runs once, its outputs split back by their
    role in ``outputs``: ``"image"`` (``(N, ...)``), ``"jacobian"`` (``(N + 1, ...)``, the shared
    area row repeated) or ``"shared"`` (the same for the batch); otherwise one call per sample,
    stacked. Operators
    that draw noise follow ``vmap``'s ``randomness``: ``"error"`` refuses, ``"same"`` gives every
    sample the same draws, ``"different"`` draws for each."""
    name = op._name

    def rule(info: Any, in_dims: tuple, *args: Any) -> tuple[Any, Any]:
        batched = [i for i, d in enumerate(in_dims) if d is not None]
        random = name in RANDOM and (
            name != "area" or bool(read_call(args[3], name).physics)
        )  # with a camera
        if random and info.randomness == "error":
            raise RuntimeError(
                f"layoutwarp::{name} draws random numbers: pass randomness='same' or 'different' to vmap"
            )
        if fold is not None and batched == [fold] and not (random and info.randomness == "same"):
            return _folded(op, in_dims, args, fold, outputs)
        outs = []
        for b in range(info.batch_size):
            sample = [a.select(d, b) if d is not None else a for a, d in zip(args, in_dims, strict=True)]
            if random and info.randomness == "different":
                sample = [
                    _next_seed(a, b) if isinstance(a, Tensor) and a.dtype == torch.int64 else a
                    for a in sample
                ]
            outs.append(op(*sample))
        if isinstance(outs[0], tuple):
            return tuple(torch.stack(o) for o in zip(*outs, strict=True)), (0,) * len(outs[0])
        return torch.stack(outs), 0

    return rule


#: Operators that draw random numbers (their 0-d int64 argument is a seed; ``area`` with a camera).
RANDOM = frozenset({"measure", "draws", "uniform", "seed_sequence", "area"})


def _next_seed(seed: Tensor, b: int) -> Tensor:
    """Sample ``b``'s seed of a batch drawn ``"different"``."""
    return seed + 7919 * (b + 1) if seed.ndim == 0 else seed


def _folded(op: Any, in_dims: tuple, args: tuple, fold: int, roles: tuple[str, ...]) -> tuple[Any, Any]:
    """``op`` once on images whose batch joined their first axis ``N``; outputs split back by role."""
    x = args[fold].movedim(in_dims[fold], 0)
    b, n = x.shape[:2]
    out = op(*args[:fold], x.reshape(b * n, *x.shape[2:]), *args[fold + 1 :])
    outs = out if isinstance(out, tuple) else (out,)
    split, dims = [], []
    for o, role in zip(outs, roles, strict=True):
        if role == "image":  # per image: split back
            split.append(o.reshape(b, n, *o.shape[1:]))
            dims.append(0)
        elif role == "jacobian" and o.numel():  # a Jacobian's rows and its shared area row
            rows = o[:-1].reshape(b, n, *o.shape[1:])
            split.append(torch.cat([rows, o[-1:].expand(b, 1, *o.shape[1:])], 1))
            dims.append(0)
        else:  # shared by the batch
            split.append(o)
            dims.append(None)
    return (tuple(split), tuple(dims)) if isinstance(out, tuple) else (split[0], dims[0])


def seed_value(seed: Tensor) -> int:
    """The value of a 0-d seed tensor, read inside an operator (a CPU seed's by numpy: no torch
    operation, no device wait)."""
    return int(seed.numpy() if seed.device.type == "cpu" else seed)


def generator_of(seed: Tensor, device: torch.device) -> torch.Generator:
    """A generator on ``device`` seeded with the value of the 0-d ``seed`` (read inside an
    operator: where its draws are made)."""
    return torch.Generator(device).manual_seed(seed_value(seed) % 2**63)
