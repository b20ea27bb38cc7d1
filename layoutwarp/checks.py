"""Input checks used at every public entry point.

Each helper returns the validated (normalised) value or raises with a one-line message that
names the argument, the value it got and what is allowed, in the manner of Kornia's
``KORNIA_CHECK_SHAPE``. Bad values raise [`ArgumentError`][] (a ``ValueError`` that also
carries the argument's name), which the command line turns into an error line naming its flag.
"""

from __future__ import annotations

import math
import numbers
import os
import warnings
from collections.abc import Iterable, Sequence
from typing import Any, Literal, overload

import numpy as np
import torch
from torch import Tensor

__all__ = [
    "ASPECT_TOLERANCE",
    "BYTES_PER_SENSOR_PIXEL",
    "MAX_EXTENT_UM",
    "SEED_MAX",
    "UNCHECKED_BYTES",
    "ArgumentError",
    "all_finite",
    "available_bytes",
    "check_available",
    "check_bool",
    "check_choice",
    "check_device",
    "check_extent",
    "check_float_dtype",
    "check_generator",
    "check_int",
    "check_memory",
    "check_number",
    "check_points",
    "check_shape",
    "check_size",
    "check_tensor",
    "check_type",
    "floating_dtype",
    "raise_nonfinite",
    "values_readable",
    "warn_if_elsewhere",
    "warn_if_finer",
    "warn_if_stretched",
]

#: The largest seed any layoutwarp call takes: what torch's generators hold as a signed 64-bit
#: integer.
SEED_MAX = 2**63 - 1


class ArgumentError(ValueError):
    """A bad argument value. A ``ValueError`` whose message names the argument, the value and
    what is allowed; `argument` holds the argument's name for callers that map it to
    their own (the command line to its flag).

    Examples:
        >>> try:
        ...     check_number(-1, "tol", 0, lo_open=True)
        ... except ArgumentError as exc:
        ...     print(exc.argument)
        tol
    """

    def __init__(self, argument: str, message: str) -> None:
        super().__init__(message)
        self.argument = argument


def _argument(name: str) -> str:
    """The argument a check's ``name`` speaks of: ``"sensor_um[0] (height)"`` → ``"sensor_um"``."""
    return name.split("[")[0].split(" ")[0]


def check_size(size: Any, name: str = "size") -> tuple[int, int]:
    """Validate an ``(H, W)`` size and return it as a tuple of two positive ints.

    Examples:
        >>> check_size((129, 257))
        (129, 257)
    """
    try:
        if isinstance(size, (str, bytes)):  # "34" would be (3, 4)
            raise TypeError
        h, w = (int(v) for v in size)
        whole = all(float(v) == int(v) and not isinstance(v, (bool, np.bool_, str, bytes)) for v in size)
    except (TypeError, ValueError):
        raise ArgumentError(
            _argument(name), f"{name} must be a pair (H, W) of positive integers, got {size!r}"
        ) from None
    if not whole or h <= 0 or w <= 0:
        raise ArgumentError(
            _argument(name), f"{name} must be a pair (H, W) of positive integers, got {size!r}"
        )
    return h, w


#: A lower bound on the memory one sensor pixel needs on any path (its mesh and weights).
BYTES_PER_SENSOR_PIXEL = 200


def available_bytes() -> int:
    """The memory the system can give this process now (Linux: ``MemAvailable``; else all of it)."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")


_WARNED: set[tuple[str, tuple, tuple]] = set()  # (warning, and what it was about)


def warn_if_finer(size: tuple[int, int], src_size: tuple[int, int]) -> None:
    """Warn (a ``UserWarning``, once a process for each pair of sizes) where the sensor
    ``(h, w)`` has more pixels along an axis than its source image ``(H, W)``: each sensor pixel
    is then smaller than a source pixel, which adds no detail and costs memory and time (most
    likely the two sizes were swapped or mistyped)."""
    h, w = size
    src_h, src_w = src_size
    key = ("finer", tuple(size), tuple(src_size))
    if (h > src_h or w > src_w) and key not in _WARNED:
        _WARNED.add(key)
        warnings.warn(
            f"the sensor ({h}, {w}) has more pixels along an axis than its source image "
            f"({src_h}, {src_w}): its pixels are smaller than the image's and add no detail",
            UserWarning,
            stacklevel=3,
        )


def warn_if_elsewhere(layout_device: torch.device, image_device: torch.device) -> None:
    """Warn (a ``UserWarning``, once a process for each pair of devices) where a layout's θ lives
    on another device than the image it integrates: θ is then copied to the image's device on
    every call, a wait for the copy each time."""
    key = ("device", (str(layout_device),), (str(image_device),))
    if layout_device != image_device and key not in _WARNED:
        _WARNED.add(key)
        warnings.warn(
            f"the layout's θ is on {layout_device} and the image on {image_device}: θ is copied to "
            f"{image_device} on every call; move the layout (or its SensorLayer) there with "
            f".to({str(image_device)!r})",
            UserWarning,
            stacklevel=3,
        )


#: How far the sensor's aspect ratio may differ from its source's before [`warn_if_stretched`][] warns.
ASPECT_TOLERANCE = 0.10


def warn_if_stretched(size: tuple[int, int], src_size: tuple[int, int]) -> None:
    """Warn (a ``UserWarning``, once a process for each pair of sizes) where the sensor ``(h, w)``
    and its source image ``(H, W)`` differ in aspect ratio by more than `ASPECT_TOLERANCE`: the
    sensor covers the whole image, so the scene is stretched (a portrait photo into a landscape
    sensor, or the two sizes' width and height swapped)."""
    h, w = size
    src_h, src_w = src_size
    ratio = (w / h) / (src_w / src_h)
    key = ("aspect", tuple(size), tuple(src_size))
    if abs(ratio - 1) > ASPECT_TOLERANCE and key not in _WARNED:
        _WARNED.add(key)
        warnings.warn(
            f"the sensor ({h}, {w}) has another aspect ratio than its source image ({src_h}, {src_w}): "
            f"{w / h:.3g} against {src_w / src_h:.3g} (width / height), so the scene is stretched "
            f"{max(ratio, 1 / ratio):.2f}x along {'x' if ratio > 1 else 'y'}",
            UserWarning,
            stacklevel=3,
        )


#: Sensors needing less than this are not checked against the free memory (every call of
#: [`simulate`][layoutwarp.sensor.simulate] checks its size: reading the system's numbers costs more than
#: a small fixed-layout forward).
UNCHECKED_BYTES = 64 << 20


def check_memory(size: tuple[int, int], name: str = "size", shown: str | None = None) -> None:
    """Refuse a sensor whose pixels alone need more memory than is available, before anything
    is allocated (`BYTES_PER_SENSOR_PIXEL` a pixel, a lower bound; sizes needing less than
    `UNCHECKED_BYTES` pass unread). ``shown``: the size as the caller's user wrote it (default
    ``(H, W) = (h, w)``).

    Raises:
        ArgumentError: naming ``name``, the size, what it needs and what is available.
    """
    h, w = size
    what = f"{name} {shown or f'(H, W) = ({h}, {w})'} is {h * w:.3g} sensor pixels"
    check_available(h * w * BYTES_PER_SENSOR_PIXEL, name, what, f"{BYTES_PER_SENSOR_PIXEL} bytes a pixel")


def check_available(need: float, name: str, what: str, rate: str) -> None:
    """Refuse work that needs ``need`` bytes, more than the memory available, before allocating
    (needs under `UNCHECKED_BYTES` pass unread).

    Raises:
        ArgumentError: ``"{what} and needs at least N GiB of memory ({rate}), more than the M GiB
            available"``, naming the argument ``name``.
    """
    if need < UNCHECKED_BYTES:
        return
    have = available_bytes()
    if need > have:
        raise ArgumentError(
            _argument(name),
            f"{what} and needs at least {_gib(need)} of memory ({rate}), "
            f"more than the {_gib(have)} available",
        )


def _gib(n: float) -> str:
    return f"{n / 2**40:.3g} TiB" if n >= 2**40 else f"{n / 2**30:.3g} GiB"


def check_extent(sensor_um: Any, name: str = "sensor_um") -> tuple[float, float]:
    """A physical extent ``(H_um, W_um)``: two sizes in ``(0, MAX_EXTENT_UM]`` µm, as floats.

    Examples:
        >>> check_extent((4200, 5600))
        (4200.0, 5600.0)
    """
    try:
        hu, wu = sensor_um
    except (TypeError, ValueError):
        raise ArgumentError(
            name, f"{name} must be (H_um, W_um), two positive sizes in µm, got {sensor_um!r}"
        ) from None
    return check_number(hu, f"{name}[0] (height)", 0, MAX_EXTENT_UM, lo_open=True), check_number(
        wu, f"{name}[1] (width)", 0, MAX_EXTENT_UM, lo_open=True
    )


#: The largest extent [`check_extent`][] takes, in µm (a kilometre: areas stay finite in float64).
MAX_EXTENT_UM = 1e9


def check_choice(value: Any, choices: Iterable[Any], name: str) -> Any:
    """``value`` if it is one of ``choices``, else ``ValueError`` listing them."""
    options = tuple(choices)
    if value not in options:
        raise ArgumentError(
            _argument(name), f"{name} must be one of {', '.join(map(repr, options))}; got {value!r}"
        )
    return value


@overload
def check_int(
    value: Any,
    name: str,
    minimum: int | None = ...,
    maximum: int | None = ...,
    *,
    optional: Literal[False] = ...,
) -> int: ...
@overload
def check_int(
    value: Any, name: str, minimum: int | None = ..., maximum: int | None = ..., *, optional: bool
) -> int | None: ...
def check_int(
    value: Any, name: str, minimum: int | None = None, maximum: int | None = None, *, optional: bool = False
) -> int | None:
    """An integer within ``[minimum, maximum]`` as a Python ``int`` (numpy integers too; bools are
    refused), or ``None`` where ``optional``.

    Examples:
        >>> check_int(np.int64(3), "workers", 1)
        3
    """
    if value is None and optional:
        return None
    ok = isinstance(value, numbers.Integral) and not isinstance(value, bool)
    if ok and (minimum is None or value >= minimum) and (maximum is None or value <= maximum):
        return int(value)
    raise ArgumentError(
        _argument(name),
        f"{name} must be an integer {_interval(minimum, maximum, False, False)}"
        f"{' or None' * optional}, got {value!r}",
    )


def check_number(
    value: Any,
    name: str,
    lo: float | None = None,
    hi: float | None = None,
    *,
    lo_open: bool = False,
    hi_open: bool = False,
) -> float:
    """A finite real number in the interval from ``lo`` to ``hi`` (open ends if asked).

    Examples:
        >>> check_number(1e-3, "tol", 0, lo_open=True)
        0.001
    """
    try:
        v = float(value)
        ok = not isinstance(value, bool) and math.isfinite(v)
    except (TypeError, ValueError):
        ok = False
    if ok:
        ok = (lo is None or (v > lo if lo_open else v >= lo)) and (
            hi is None or (v < hi if hi_open else v <= hi)
        )
    if not ok:
        raise ArgumentError(
            _argument(name),
            f"{name} must be a finite number {_interval(lo, hi, lo_open, hi_open)}, got {value!r}",
        )
    return v


def _interval(lo, hi, lo_open: bool, hi_open: bool) -> str:
    def num(v: float | int) -> str:  # an integer bound in full (2**63 - 1 is no 9.22337e+18)
        return str(v) if isinstance(v, int) else f"{v:g}"

    if lo is None and hi is None:
        return ""
    if hi is None:
        return f"{'>' if lo_open else '>='} {num(lo)}"
    if lo is None:
        return f"{'<' if hi_open else '<='} {num(hi)}"
    return f"in {'(' if lo_open else '['}{num(lo)}, {num(hi)}{')' if hi_open else ']'}"


def values_readable() -> bool:
    """Whether a tensor's values may be read here as numbers (``.tolist()``, a branch on them):
    eager, not compiling or tracing, no ``vmap`` or other transform, no dispatch mode (fake
    tensors, ``make_fx``) or torch function mode. Elsewhere a check that reads values is left
    out."""
    if torch.compiler.is_compiling() or torch._C._functorch.maybe_current_level() is not None:
        return False
    return not (torch._C._len_torch_dispatch_stack() or torch._C._is_torch_function_mode_enabled())


def check_device(device: Any, name: str = "device") -> torch.device:
    """``device`` as a ``torch.device``; ``ValueError`` for a name torch does not know or a
    CUDA device on a machine without CUDA."""
    try:
        dev = torch.device(device)
    except (RuntimeError, TypeError):
        raise ArgumentError(
            _argument(name), f"{name} must be a torch device (e.g. cpu, cuda, cuda:1), got {device!r}"
        ) from None
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise ArgumentError(
            _argument(name), f"{name} {str(dev)!r} asked for, but no CUDA GPU is available here"
        )
    if dev.type == "meta":
        raise ArgumentError(
            _argument(name), f"{name} 'meta' holds no data to compute on; use cpu or cuda, got {device!r}"
        )
    return dev


def check_bool(value: Any, name: str) -> bool:
    """``value`` if it is a bool (numpy's too); ``ArgumentError`` otherwise (a string such as
    ``"no"`` would count as true)."""
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    raise ArgumentError(_argument(name), f"{name} must be True or False, got {value!r}")


def check_float_dtype(dtype: Any, name: str = "dtype") -> torch.dtype:
    """``dtype`` if it is a floating-point ``torch.dtype``; ``ArgumentError`` otherwise (an
    integer dtype would truncate θ to zero)."""
    if isinstance(dtype, torch.dtype) and dtype.is_floating_point:
        return dtype
    raise ArgumentError(
        _argument(name), f"{name} must be a floating-point torch.dtype (e.g. torch.float64), got {dtype!r}"
    )


def check_type(value: Any, kind: type | tuple[type, ...], name: str, what: str) -> Any:
    """``value`` if it is an instance of ``kind``; ``TypeError`` naming ``what`` was expected."""
    if isinstance(value, kind):
        return value
    raise ArgumentError(_argument(name), f"{name} must be {what}, got {type(value).__name__}: {value!r:.60}")


def check_generator(generator: Any, name: str = "generator", *, seed: Any = None) -> torch.Generator | None:
    """``generator`` if it is a ``torch.Generator`` or ``None``, and not given with a ``seed``
    (two sources of one call's draws: the call would use one and ignore the other)."""
    if generator is not None and seed is not None:
        raise ArgumentError(
            _argument(name), f"{name} and seed are two sources of the call's random draws: pass one of them"
        )
    if generator is None or isinstance(generator, torch.Generator):
        return generator
    raise ArgumentError(
        _argument(name), f"{name} must be a torch.Generator or None, got {type(generator).__name__}"
    )


def check_tensor(x: Any, name: str) -> Tensor:
    """``x`` if it is a ``torch.Tensor``, else ``TypeError``."""
    if not isinstance(x, Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(x).__name__}")
    return x


def check_shape(x: Any, shape: Sequence[str], name: str) -> Tensor:
    """Check a tensor's shape against a pattern such as ``["N", "H", "W"]``.

    Letters stand for any size, digits for that size exactly, and ``"*"`` (first only) for
    any number of leading dimensions; alternatives are separate patterns joined by ``|`` in
    one string, e.g. ``"B C H W|C H W"``.

    Examples:
        >>> check_shape(torch.zeros(2, 5, 2), ["*", "2"], "points").shape
        torch.Size([2, 5, 2])
    """
    x = check_tensor(x, name)
    patterns = [p.split() for p in shape.split("|")] if isinstance(shape, str) else [list(shape)]
    for pat in patterns:
        if _matches(tuple(x.shape), pat):
            return x
    want = " or ".join("(" + ", ".join("..." if d == "*" else d for d in p) + ")" for p in patterns)
    raise ArgumentError(_argument(name), f"{name} must have shape {want}, got {tuple(x.shape)}")


def _matches(dims: tuple[int, ...], pattern: Sequence[str]) -> bool:
    if pattern and pattern[0] == "*":
        rest = pattern[1:]
        return len(dims) >= len(rest) and _matches(dims[len(dims) - len(rest) :], rest)
    if len(dims) != len(pattern):
        return False
    return all(not p.isdigit() or int(p) == d for d, p in zip(dims, pattern, strict=True))


def check_points(p: Any, name: str = "p") -> Tensor:
    """A floating-point tensor of points ``(..., 2)`` holding ``(x, y)``."""
    check_shape(p, ["*", "2"], name)
    if not p.is_floating_point():
        raise TypeError(f"{name} must be a floating-point tensor, got {p.dtype}")
    return p


def floating_dtype(dtype: torch.dtype) -> torch.dtype:
    """The dtype computations run in: float64 stays, every other dtype becomes float32."""
    return torch.float64 if dtype == torch.float64 else torch.float32


def all_finite(x: Tensor) -> bool:
    """Whether every element of ``x`` is finite: NaN and ±inf reach the sum, so a finite sum says
    so at an eighth of the cost of ``isfinite(x).all()``; only a sum that overflows, of finite
    values, needs the element-wise check. On the CPU numpy sums, on one thread: torch's sum would
    wake its thread pool, whose join waits for the scheduler on a busy machine."""
    if x.device.type == "cpu" and x.dtype in (torch.float32, torch.float64):
        a = x.detach().numpy()
        with np.errstate(over="ignore", invalid="ignore"):
            return bool(np.isfinite(a.sum())) or bool(np.isfinite(a).all())
    x = x.detach()
    return math.isfinite(float(x.sum())) or bool(torch.isfinite(x).all())  # one value read back


def raise_nonfinite(image: Tensor, name: str = "image") -> None:
    """Raise a one-line ``ValueError`` with the number of NaN/Inf values of ``image``, if any
    (the check behind ``allow_nonfinite=False``, called where an integrator's output is not
    finite); where ``image`` has none, the integrator's sums overflowed its dtype: said so."""
    bad = int((~torch.isfinite(image)).sum())
    if bad:
        raise ValueError(
            f"{name} contains {bad} non-finite value(s) (NaN or Inf); clean it or pass allow_nonfinite=True"
        )
    if image.numel() and image.is_floating_point():
        top, kind = float(image.detach().abs().max()), str(image.dtype).removeprefix("torch.")
        raise ValueError(
            f"{name}'s values are finite, but the integrator's sums of them (up to {top:.3g}) overflow "
            f"{kind}: scale the {name} down, or pass allow_nonfinite=True"
        )
