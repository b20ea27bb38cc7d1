"""Counting what a call costs, for tests and benchmarks: torch operator calls and GPU launches,
counted without a GPU.

Not imported by the library; the tests bound a training step's operators and launches with
these, and `layoutwarp.experiments.bench` reports them.
"""

from __future__ import annotations

import contextlib
import os
import sys
from collections import Counter
from collections.abc import Callable, Iterator

from .kernels.device import LAUNCHES

__all__ = ["HOST_READS", "NO_KERNEL_OPS", "count_host_reads", "count_launches", "count_ops"]


def count_ops(fn: Callable[[], object]) -> int:
    """The number of torch operator calls (``aten::`` events at the top level of the profiler's
    tree, or inside layoutwarp's operators) ``fn`` makes: how many kernel launches it would cost
    on a GPU."""
    from torch.profiler import ProfilerActivity, profile

    def top(event: object) -> bool:  # no parent but layoutwarp's operators
        parent = event.cpu_parent  # type: ignore[attr-defined]
        while parent is not None and parent.name.startswith("layoutwarp::"):
            parent = parent.cpu_parent
        return parent is None

    prof = profile(activities=[ProfilerActivity.CPU])
    with _without_stderr():  # the profiler's own start line (its C++ logging, not ours)
        prof.__enter__()
    try:
        fn()
    finally:
        with _without_stderr():  # and its stop line
            prof.__exit__(None, None, None)
    return sum(1 for e in prof.events() if e.name.startswith("aten::") and top(e))


@contextlib.contextmanager
def _without_stderr() -> Iterator[None]:
    """The process's standard error (file descriptor 2, where C++ logs) sent nowhere meanwhile."""
    sys.stderr.flush()
    saved = os.dup(2)
    try:
        with open(os.devnull, "w") as null:
            os.dup2(null.fileno(), 2)
            yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)


#: aten operators that launch no GPU kernel: allocations (views are told by their schema).
NO_KERNEL_OPS = frozenset(
    "empty empty_like empty_strided new_empty new_empty_strided detach alias lift_fresh _unsafe_view".split()
)


#: The tensor methods that read a value back to the host (on a GPU: wait for the device).
HOST_READS = ("item", "tolist", "numpy", "cpu", "__bool__", "__int__", "__float__", "__index__")


def count_host_reads(fn: Callable[[], object]) -> Counter[str]:
    """The values ``fn`` reads back from tensors to the host, by method (``item``, ``__int__``,
    ``numpy`` ...; see [`HOST_READS`][]): on a GPU each is a wait for the device. Counted without
    a GPU where the device path runs on the CPU (numba's CUDA simulator), so a CPU tensor's read
    counts as a device tensor's would; not counted: the arrays a kernel launch hands to the
    simulator, and reads of host memory the kernels write directly
    ([`host_mapped`][layoutwarp.kernels.device.host_mapped]: no wait). A lower bound: a copy to
    the CPU by ``to`` or ``copy_``, and operators whose output size depends on values
    (``nonzero``, masks, ``unique``), also wait, and are not counted."""
    from torch.overrides import TorchFunctionMode

    counts: Counter[str] = Counter()

    class Reads(TorchFunctionMode):
        def __torch_function__(self, func, types, args=(), kwargs=None):
            name = getattr(func, "__name__", "")
            if name in HOST_READS and sys._getframe(1).f_code.co_name != "_device_array":
                counts[name] += 1
            return func(*args, **(kwargs or {}))

    with Reads():
        fn()
    return counts


def _copied(args: tuple, out: object) -> bool:
    """Whether an operator that may return its input (``to``, ``contiguous``, ``reshape``: an
    alias in its schema) made a new tensor instead: a copy, which on a device is a launch. Inside
    layoutwarp's operators such calls reach the count whole, not as the ``_to_copy`` they run."""
    import torch

    base = next((a for a in args if isinstance(a, torch.Tensor)), None)
    return (
        isinstance(out, torch.Tensor)
        and base is not None
        and out.layout == base.layout == torch.strided  # a sparse tensor has no storage to compare
        and out.numel() > 0
        and out.untyped_storage().data_ptr() != base.untyped_storage().data_ptr()
    )


def count_launches(fn: Callable[[], object]) -> Counter[str]:
    """The GPU launches ``fn`` makes, counted without a GPU: every launch of a numba CUDA kernel
    ([`LAUNCHES`][layoutwarp.kernels.device.LAUNCHES], by kernel name, ``numba:NAME``) and every
    torch operator that runs a kernel or a copy on a device (``aten:NAME``; views and bare
    allocations run none, and an operator that may return its input counts where it copied),
    including those of the backward; ``aten:_local_scalar_dense`` is a
    host wait (a value read back). Run it where the device path runs: on a CUDA device, or on the
    CPU under numba's CUDA simulator. The total is what the torch profiler's count of GPU
    activities approximates (it adds cuBLAS's and cuSPARSE's inner kernels). layoutwarp's own
    operators launch nothing themselves: what runs inside them is counted."""
    from torch.utils._python_dispatch import TorchDispatchMode

    counts: Counter[str] = Counter()

    from .operators.base import OPERATORS

    class Ops(TorchDispatchMode):
        def __torch_dispatch__(self, func, types, args=(), kwargs=None):
            name = func.overloadpacket.__name__
            if func.namespace == "layoutwarp":  # an operator of ours: what its work launches
                with Ops():
                    return OPERATORS[name]._init_fn(*args, **(kwargs or {}))
            out = func(*args, **(kwargs or {}))
            if _copied(args, out) if func.is_view else name.rstrip("_") not in NO_KERNEL_OPS:
                counts[f"aten:{name}"] += 1
            return out

    before = Counter(LAUNCHES)
    with Ops():
        fn()
    counts.update({f"numba:{k}": v for k, v in (LAUNCHES - before).items()})
    return counts
