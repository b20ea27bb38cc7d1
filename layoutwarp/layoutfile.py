"""Layout files: a layout, its sensor size and free-form extras as a small JSON document.

A file holds ``format`` (``"layoutwarp.layout/2"``), ``family`` (a registered family, see
[`register_family`][layoutwarp.layouts.register_family]), the family's constructor arguments
([`to_config`][layoutwarp.layouts.base.Layout.to_config]: for the paper's families ``theta``, ``bound``,
``center`` and ``learn_center``; for splines ``theta``, ``knots`` and ``kind``; for grids
``grid`` and ``control``), ``size_hw`` (optional sensor size ``[H, W]``), ``version`` (the
package version that wrote it) and ``extra`` (anything JSON-able the writer adds, e.g. the
training metric).

Format history: ``/1`` (layoutwarp 0.1–0.2: uniform, rect and curv with ``theta`` and
``bound``) still loads, as a centred layout; ``/2`` adds the centre and the spline and grid
families. A file of a later format is refused with a message saying so.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import torch

from .caches import ObjectMemo, version_of
from .checks import ArgumentError, check_size
from .files import atomic_write
from .layouts import FAMILIES, Layout, check_layout
from .version import __version__

__all__ = [
    "FORMAT",
    "READS",
    "layout_from_spec",
    "layout_key",
    "layout_spec",
    "load_layout",
    "same_spec",
    "save_layout",
]

FORMAT = "layoutwarp.layout/2"
#: Every format this version reads.
READS = ("layoutwarp.layout/1", FORMAT)
#: Keys of a layout file (or description) that are not the family's constructor arguments.
_RESERVED = ("format", "family", "size_hw", "version", "extra")


def layout_spec(layout: Layout) -> dict[str, Any]:
    """A layout's description: ``{"family": name, **layout.to_config()}``, JSON-able.

    The one form in which a layout travels: in layout files, model files, preprocessing
    manifests, benchmark rows and to the workers of a cluster.

    Examples:
        >>> from layoutwarp import RectLayout
        >>> layout_spec(RectLayout((0.5, 0.25), dtype=torch.float64))["family"]
        'rect'
    """
    return {"family": layout.family, **layout.to_config()}


#: [`layout_key`][]'s texts, per layout ([`layoutwarp.caches`][]).
LAYOUT_KEYS = ObjectMemo("layout keys")


def layout_key(layout: Layout) -> str | None:
    """The layout's identity as text (its [`layout_spec`][], keys sorted), for caches keyed by
    layout; ``None`` for a layout that is not of a registered family, whose description may not
    hold all its state (such a layout is never cached).

    Kept per layout while its tensors (the same objects, unchanged in place) and its other
    attributes are as they were: a fixed layout's repeated [`simulate`][layoutwarp.sensor.simulate] call asks
    for it every time, and writing the JSON text cost more than checking that."""
    if FAMILIES.get(layout.family) is not type(layout):
        return None
    tensors = (*layout.parameters(), *layout.buffers())
    settings = tuple(v for k, v in vars(layout).items() if k[0] != "_")
    state = (*tensors, *(version_of(t) for t in tensors), settings)
    return LAYOUT_KEYS.get(layout, state, lambda: json.dumps(layout_spec(layout), sort_keys=True))


def layout_from_spec(
    spec: dict[str, Any], *, learn: bool = False, dtype: torch.dtype | None = None
) -> Layout:
    """Rebuild a layout from [`layout_spec`][]'s dict (other keys, e.g. ``size_hw``, are ignored
    by the families that do not take them).

    Raises:
        ValueError: an unknown family or a bad parameter, on one line.
    """
    family = spec.get("family")
    cls = FAMILIES.get(family) if isinstance(family, str) else None
    if cls is None:
        raise ValueError(
            f"unknown layout family {family!r}; expected one of {', '.join(map(repr, FAMILIES))}"
        )
    config = {k: v for k, v in spec.items() if k not in _RESERVED}
    try:
        return cls.from_config(config, learn=learn, dtype=dtype)
    except TypeError as exc:
        raise ValueError(str(exc)) from None


def same_spec(a: dict[str, Any], b: dict[str, Any], atol: float = 1e-12) -> bool:
    """Whether two layout descriptions describe the same layout (numbers within ``atol``)."""
    if set(a) != set(b):
        return False
    for k, v in a.items():
        numbers = isinstance(v, list) and v and all(isinstance(x, float | int) for x in v)
        if numbers:
            w = b[k]
            if not (
                isinstance(w, list)
                and len(w) == len(v)
                and all(abs(x - y) <= atol for x, y in zip(v, w, strict=True))
            ):
                return False
        elif v != b[k]:
            return False
    return True


def save_layout(layout: Layout, path: str | Path, size: tuple[int, int] | None = None, **extra: Any) -> Path:
    """Write ``layout`` (family, its parameters, optional sensor size ``(H, W)``) to a JSON file.

    The file is written atomically (a temporary file renamed into place). Extra keyword
    values (JSON-serialisable, finite numbers) are stored under ``"extra"``.

    Raises:
        ValueError: a ``layout`` that is not a Layout, a bad ``size``, or ``extra`` values that
            JSON cannot hold (NaN, infinities, objects), before anything is written.
    """
    check_layout(layout)
    size = check_size(size) if size is not None else None
    data: dict[str, Any] = {"format": FORMAT, **layout_spec(layout)}
    data |= {"size_hw": list(size) if size is not None else None, "version": __version__, "extra": extra}
    try:
        text = json.dumps(data, indent=2, allow_nan=False)
    except (TypeError, ValueError) as exc:
        raise ArgumentError(
            "extra", f"extra values must be JSON numbers, text, lists or dicts ({exc})"
        ) from None
    return atomic_write(path, text)


def load_layout(
    path: str | Path, *, learn: bool = False, dtype: torch.dtype | None = None
) -> tuple[Layout, dict[str, Any]]:
    """Read a layout file written by [`save_layout`][].

    Returns:
        ``(layout, info)`` where ``info`` holds ``size_hw``, ``version`` and ``extra``.

    Raises:
        ValueError: a missing, unreadable or malformed file, an unknown family or a
            parameter out of range, with the file's name and the problem on one line.
    """
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        raise ValueError(f"{path}: no such layout file") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ValueError(f"{path}: not a readable layout JSON ({exc})") from None
    fmt = data.get("format") if isinstance(data, dict) else None
    if isinstance(fmt, str) and fmt.startswith("layoutwarp.layout/") and fmt not in READS:
        raise ValueError(
            f"{path}: layout file format {fmt!r} is newer than this layoutwarp reads "
            f"({', '.join(READS)}); upgrade layoutwarp"
        )
    if fmt not in READS:
        raise ValueError(f"{path}: not a layoutwarp layout file (expected format {FORMAT!r})")
    size = data.get("size_hw")
    if size is not None and not (
        isinstance(size, list) and len(size) == 2 and all(isinstance(v, int) and v > 0 for v in size)
    ):
        raise ValueError(f"{path}: 'size_hw' must be [H, W] with positive integers, got {size!r}")
    try:
        layout = layout_from_spec(data, learn=learn, dtype=dtype)
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from None
    return layout, {k: data.get(k) for k in ("size_hw", "version", "extra")}
