"""What every compiled kernel of the package shares: numba (optional: without it the torch paths
run), the decorators each kernel is compiled with, the thread count and the launch lock."""

from __future__ import annotations

import contextlib
import threading
import types
from collections.abc import Callable, Iterator
from typing import Any

try:  # numba is a dependency, but the torch reference keeps working without it
    from numba import config as numba_config
    from numba import get_num_threads, njit, prange, set_num_threads
except ImportError:  # pragma: no cover - depends on the environment
    njit = prange = get_num_threads = set_num_threads = numba_config = None

__all__ = [
    "CHUNK",
    "LOCK",
    "SMALL_WORK",
    "available",
    "inline",
    "njit",
    "numba_config",
    "one_thread_below",
    "parallel",
    "plain_python",
    "prange",
    "quick_build",
    "retain_freed_memory",
    "serial",
    "threads",
    "without_ir_inlining",
]

#: Segments per work chunk; chunks go to the threads in turn.
CHUNK = 256
#: Held around every launch of a parallel kernel: numba's ``workqueue`` threading layer (used
#: where no OpenMP or TBB runtime is installed) aborts the process on concurrent launches from
#: several Python threads. Each launch uses every core anyway.
LOCK = threading.Lock()


def available() -> bool:
    """Whether the compiled kernels can run (numba is importable)."""
    return njit is not None


def plain_python() -> bool:
    """Whether numba runs the kernels as plain Python (``NUMBA_DISABLE_JIT=1``: how the CUDA
    simulator's tests run them): nothing is compiled, so nothing waits for a compile."""
    return njit is not None and bool(numba_config.DISABLE_JIT)


#: Per Python thread: torch's thread count at [`threads`][]' last call there, and what it set.
_THREADS = threading.local()


def threads() -> int:
    """The number of threads the kernels share their work out to, and set for the calling thread's
    launches: numba's, at most torch's current count, so that ``torch.set_num_threads`` and
    ``OMP_NUM_THREADS`` bound both (jobs meant for one core each no longer fight over the cores:
    two such jobs with numba on two threads each ran a small training step 60x slower). Numba's
    count is set again only when torch's changed since the calling thread's last call (asking
    numba costs microseconds a launch)."""
    if get_num_threads is None:
        return 1
    import torch

    wanted = torch.get_num_threads()
    if getattr(_THREADS, "wanted", None) == wanted:
        return _THREADS.n
    current = get_num_threads()  # the first call starts numba's OpenMP layer, which resets torch's count
    if torch.get_num_threads() != wanted:
        torch.set_num_threads(wanted)
    n = max(1, min(wanted, numba_config.NUMBA_NUM_THREADS))
    if n != current:
        set_num_threads(n)
    _THREADS.wanted, _THREADS.n = wanted, n
    return n


#: Work (elements) below which a parallel kernel runs on one thread ([`one_thread_below`][]).
SMALL_WORK = 1 << 20


@contextlib.contextmanager
def one_thread_below(work: int, limit: int = SMALL_WORK) -> Iterator[None]:
    """Within: numba's parallel kernels run on one thread where ``work`` (elements) is under
    ``limit``. Such a kernel takes about a millisecond; a parallel region's fork and join cost a
    good part of that on a quiet machine, and on a busy one the join waits for a descheduled
    thread, 10-80x the work (a learnable step's edge gradient: 0.4 ms quiet, 56 ms beside one
    busy process). Larger work keeps every thread."""
    if set_num_threads is None or work >= limit:
        yield
        return
    n = get_num_threads()
    set_num_threads(1)
    try:
        yield
    finally:
        set_num_threads(n)


def retain_freed_memory(trim_bytes: int = 1 << 30) -> bool:
    """Let glibc's allocator keep freed memory for the next allocations of the process instead of
    handing it back to the system (blocks up to 32 MiB from the heap, not from fresh mappings;
    up to ``trim_bytes`` of free heap kept). A training step allocates about 100 MB of arrays
    (mesh, tables, moments) and frees them again; fresh pages cost a page fault each, about
    20 000 a step at 2048x1024 → 257x129, which took 37–41 % of the step on the (virtualised)
    2-core machine of the figures in ``docs/speed.md``. The command line calls this once;
    library users may. Returns whether it took effect (``False`` where the C library is not
    glibc). The price: the process's resident memory stays near its peak."""
    import ctypes
    import platform

    if platform.libc_ver()[0] != "glibc":
        return False
    try:
        libc = ctypes.CDLL(None)
        m_trim_threshold, m_mmap_threshold = -1, -3  # mallopt's parameter numbers (malloc.h)
        return bool(
            libc.mallopt(m_mmap_threshold, 32 << 20) and libc.mallopt(m_trim_threshold, int(trim_bytes))
        )
    except (OSError, AttributeError):  # pragma: no cover - a libc without mallopt
        return False


def parallel(fn):
    """A kernel with ``prange`` loops, called from Python (numpy's error model: a division by zero
    gives inf, unchecked, so loops with one vectorise)."""
    return njit(parallel=True, cache=True, nogil=True, error_model="numpy")(fn) if njit is not None else fn


def serial(fn):
    """A serial kernel compiled once and called as a function: a driver of parallel kernels (one
    call from Python), or a step called once a chunk that is not worth inlining everywhere."""
    return njit(cache=True, nogil=True, error_model="numpy")(fn) if njit is not None else fn


def inline(fn):
    """A helper inlined into each kernel that calls it, at numba's IR level (``inline="always"``):
    the mesh builds in half the time of plain calls; the price is compile time, which
    [`layoutwarp.jit.quick`][] avoids where a first call cannot wait."""
    return njit(inline="always", cache=True)(fn) if njit is not None else fn


_QUICK: dict[Any, Any] = {}  # each kernel's quick build
_QUICK_LOCK = threading.RLock()


def quick_build(kernel: Any) -> Any:
    """``kernel`` (a compiled function) recompiled without numba's IR inlining: its Python
    function, every compiled function it calls replaced by its own quick build
    ([`without_ir_inlining`][]), and its options less ``inline``; cached on disk under its name
    with ``_quick`` (see [`layoutwarp.jit.quick`][] for what it costs and saves)."""
    with _QUICK_LOCK:
        if kernel not in _QUICK:
            func = without_ir_inlining(kernel.py_func)
            options = {k: v for k, v in kernel.targetoptions.items() if k not in ("inline", "nopython")}
            _QUICK[kernel] = njit(cache=True, **options)(func)  # every kernel of the package is cached
        return _QUICK[kernel]


def without_ir_inlining(func: Callable) -> Callable:
    """A copy of the Python function ``func`` (named ``NAME_quick``: numba's cache files are
    named by it) whose compiled callees (``inline="always"`` or not) are their quick builds
    ([`quick_build`][]): numba then types and lowers each helper once, as a function of its own,
    instead of again at every call site. The CUDA kernels compile from such copies: NVVM inlines
    the device functions afterwards (the same PTX to within a few instructions), in a fifth of the
    compile time (a learnable step's kernels: 51 s to 9 s on 2 cores)."""
    from numba.core.dispatcher import Dispatcher

    scope = dict(func.__globals__)
    for name in func.__code__.co_names:  # the compiled functions it calls, by their global names
        if isinstance(scope.get(name), Dispatcher):
            scope[name] = quick_build(scope[name])
    rebuilt = types.FunctionType(func.__code__, scope, func.__name__, func.__defaults__, func.__closure__)
    rebuilt.__qualname__ = f"{func.__qualname__}_quick"
    rebuilt.__module__, rebuilt.__doc__ = func.__module__, func.__doc__
    return rebuilt
