"""What layoutwarp keeps between calls, and when it lets go of it: one rule for every cache.

* **Results** (a fixed layout's pixel mesh, its area weights, a camera's per-pixel inputs) are
  kept in bounded least-recently-used caches ([`LRU`][]), keyed by *values*: a layout's
  description text, the sizes, the tolerance, the dtype, the device. Only what cannot change
  under the key is cached: fixed inputs (θ without gradient) of registered families, whose
  description holds all their state. A result goes when newer ones push it out (the cache's
  ``maxsize``; 0 keeps none) or at [`clear_caches`][].
* **Keys of objects** (a layout's description text, the values of a small tensor on a device,
  a tensor's identity) are remembered per object ([`ObjectMemo`][]) while the object lives and
  its tensors are the same objects, unchanged in place (their versions): an in-place change, a
  new buffer or the object's end drops the entry. Reading them again would cost a JSON text or
  a wait for the device every call.

**What a key cannot see.** A tensor's version counter moves with every in-place change made
through it (`set_theta`, an optimiser's step, `load_state_dict`, `add_` under `no_grad`), and
every key here holds the version of each tensor it was computed from, so results follow such
changes (`tests/test_cache_keys.py` changes every family's state each of these ways and compares
every kept path with a layout made anew); θ's keys also hold its data's address and dtype, so
they follow a new ``tensor.data = ...`` and a parameter's ``.to()`` too. A change that bypasses
the counter in place is not seen: writing through ``tensor.data`` (its own counter, e.g.
``.data.copy_``), through a numpy view (``tensor.numpy()``) or DLPack, or into a tensor's
storage by other means. After such a write, [`clear_caches`][] is the
one remedy (e.g. ``layout.fixed_theta.data.copy_(new)`` then ``lw.caches.clear_caches()``;
better: ``layout.set_theta(new)``).

Every cache registers itself in [`CACHES`][] under its name, so a user (or a test) sees and
clears them all in one place. One store is kept outside the rule on purpose: the rooms of the
device meshes (``layoutwarp.kernels.mesh.MESH_ROOMS``, a few bytes of mapped host memory per
layout kind and size), which a captured CUDA graph writes into for as long as it lives, so they
live as long as the process. (Pure functions of values alone, e.g. a mesh's topology for a size
or a frozen camera's PSF taps, are memoized where they are written, with ``functools.lru_cache``:
nothing they depend on can change.)
"""

from __future__ import annotations

import contextlib
import threading
import weakref
from collections import OrderedDict
from collections.abc import Callable, Hashable, Iterator
from typing import Any, Generic, TypeVar

from torch import Tensor

__all__ = ["CACHES", "LRU", "ObjectMemo", "clear_caches", "tensor_token"]

V = TypeVar("V")

CACHES: dict[str, LRU | ObjectMemo] = {}
"""Every cache by name: the [`LRU`][]s of results and the [`ObjectMemo`][]s of keys."""


class LRU(Generic[V]):
    """Results kept by value key, the last ``maxsize`` used (least recently used out first).

    Args:
        name: the name it is registered under in [`CACHES`][].
        maxsize: how many results it keeps (0: none; settable).
    """

    def __init__(self, name: str, maxsize: int) -> None:
        self.name, self.maxsize = name, maxsize
        self._items: OrderedDict[Hashable, V] = OrderedDict()
        self._lock = threading.Lock()  # threads may share a cache: each look and change whole
        CACHES[name] = self

    def get(self, key: Hashable, build: Callable[[], V], keep: bool = True) -> V:
        """The result under ``key``, else ``build()``, kept if ``keep`` and ``maxsize`` allow.
        (Built outside the cache's lock: two threads missing one key at once build it twice, and
        the second's is kept.)"""
        with self._lock:
            if key in self._items:
                self._items.move_to_end(key)
                return self._items[key]
        value = build()
        if keep:
            self.put(key, value)
        return value

    def put(self, key: Hashable, value: V) -> None:
        """Keep ``value`` under ``key`` (if ``maxsize`` allows), the least recently used out."""
        with self._lock:
            if self.maxsize > 0:
                self._items[key] = value
                self._items.move_to_end(key)
                while len(self._items) > self.maxsize:
                    self._items.popitem(last=False)

    def pop(self, key: Hashable) -> V | None:
        """The result under ``key``, no longer kept; ``None`` where there is none."""
        with self._lock:
            return self._items.pop(key, None)

    def clear(self) -> None:
        """Forget every result."""
        with self._lock:
            self._items.clear()

    def keys(self) -> list[Hashable]:
        """The keys held, least recently used first."""
        with self._lock:
            return list(self._items)

    def __len__(self) -> int:
        return len(self._items)

    @contextlib.contextmanager
    def kept(self) -> Iterator[None]:
        """Within: as usual; after: as it was before (what was built within is forgotten, and
        nothing held before was pushed out)."""
        with self._lock:
            saved = self._items.copy()
        try:
            yield
        finally:
            with self._lock:
                self._items.clear()
                self._items.update(saved)

    def __repr__(self) -> str:
        return f"LRU({self.name!r}, {len(self)} of {self.maxsize})"


def _same(a: tuple, b: tuple) -> bool:
    """Two states alike: tensors the same objects, everything else equal."""
    if len(a) != len(b):
        return False
    for x, y in zip(a, b, strict=True):  # a loop, not all(...): a small call's keys are read often
        if x is not y and (isinstance(x, Tensor) or isinstance(y, Tensor) or x != y):
            return False
    return True


class ObjectMemo:
    """A value computed from an object, remembered per object while it lives and is in the same
    ``state`` (a tuple the caller forms: its tensors, compared as objects, their versions and
    any settings, compared by value).

    Args:
        name: the name it is registered under in [`CACHES`][].
    """

    def __init__(self, name: str) -> None:
        self.name = name
        # no lock: each look and change is one dict step (atomic under the GIL), and an entry
        # is replaced whole
        self._entries: dict[int, tuple[weakref.ref, tuple, Any]] = {}
        CACHES[name] = self

    def get(self, obj: Any, state: tuple, compute: Callable[[], V]) -> V:
        """The value remembered for ``obj`` in ``state``, else ``compute()`` remembered (a state
        holding ``None``, a [`version_of`][] that cannot be told, is computed and not kept)."""
        for v in state:
            if v is None:
                return compute()
        key = id(obj)
        hit = self._entries.get(key)
        if hit is not None and hit[0]() is obj and _same(hit[1], state):
            return hit[2]
        value = compute()
        entries = self._entries
        ref = weakref.ref(obj, lambda _, key=key: entries.pop(key, None))  # gone with the object
        self._entries[key] = (ref, state, value)
        return value

    def clear(self) -> None:
        """Forget every value."""
        self._entries.clear()

    def __len__(self) -> int:
        return len(self._entries)

    def __repr__(self) -> str:
        return f"ObjectMemo({self.name!r}, {len(self)} objects)"


_TOKENS = ObjectMemo("tensor tokens")


def tensor_token(t: Tensor) -> object:
    """A token for ``t`` as it is now, for value keys of results computed from it: the same
    token while it is the same tensor, unchanged in place; a new one after an in-place change.
    (A token held in a key never matches another tensor, whatever its ``id``.)"""
    return _TOKENS.get(t, (version_of(t),), object)


def version_of(t: Tensor) -> int | None:
    """``t``'s version counter (it grows with every in-place change), or ``None`` for a tensor
    made under ``torch.inference_mode``, which keeps none (what is keyed by it is not kept)."""
    return None if t.is_inference() else t._version


def clear_caches() -> None:
    """Forget everything every cache holds."""
    for cache in CACHES.values():
        cache.clear()
