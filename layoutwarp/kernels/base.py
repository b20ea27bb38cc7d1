"""What every compiled kernel of the package shares: numba (optional: without it the torch paths
run), the decorators each kernel is compiled with, and the threads that run a kernel's shares.

A CPU kernel is a serial numba function of its thread's share, ``body(t, threads, ...)``, compiled
with ``nogil=True``; [`run_shares`][] runs the shares ``t = 0 .. threads − 1`` at once on torch's
own OpenMP threads (where torch's runtime is GNU OpenMP's), else on a pool of Python threads
([`set_team`][]). numba's ``parallel=True`` is not used: its parfor passes took two thirds of the
kernels' compile time, and its threading layer made a forked child (a DataLoader worker)
abort."""

from __future__ import annotations

import ctypes
import functools
import glob
import itertools
import math
import os
import signal
import sys
import threading
import time
import types
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any

import numpy as np

try:  # numba is a dependency, but the torch reference keeps working without it
    from numba import config as numba_config
    from numba import njit
except ImportError:  # pragma: no cover - depends on the environment
    njit = numba_config = None

__all__ = [
    "CHUNK",
    "OPTIONS",
    "SMALL_WORK",
    "TEAM_ENV",
    "available",
    "inline",
    "inline_ir",
    "machine_busy",
    "njit",
    "numba_config",
    "own",
    "per_thread",
    "plain_python",
    "retain_freed_memory",
    "run_chunks",
    "run_shares",
    "serial",
    "set_team",
    "take",
    "team_name",
    "threads",
    "tries",
    "without_ir_inlining",
]

#: Segments per work chunk; chunks go to the threads in turn.
CHUNK = 256
#: Work (elements) below which a kernel runs on one thread ([`threads`][]) on torch's OpenMP team
#: (four times as much on Python threads, which take longer to wake).
SMALL_WORK = 1 << 18


#: Where the digest of the kernels' sources is kept, in the kernels' cache folder.
SOURCES_DIGEST = "layoutwarp-kernel-sources.sha256"


def kernel_sources() -> list[str]:
    """Every file the compiled kernels are built from: this package's (its ``mesh`` too) and
    ``layoutwarp/mesh.py`` (the count stage's constants), sorted."""
    here = os.path.dirname(os.path.abspath(__file__))
    found = glob.glob(os.path.join(here, "**", "*.py"), recursive=True)
    return sorted([*found, os.path.join(os.path.dirname(here), "mesh.py")])


def renew_stale_caches(folder: str | None) -> bool:
    """Delete the compiled kernels kept in the cache ``folder`` (the kernels' ``__pycache__``, or its
    place under ``NUMBA_CACHE_DIR``, and the mesh kernels' beside it; ``None``: nothing to do)
    where the digest of [`kernel_sources`][] differs from the one kept there, then keep the new
    one. numba keys a kernel's cache on its own file's content: a kernel that inlines another
    file's function, or reads its constants, kept its old machine code where only that file
    changed (an edited source, a ``git checkout``). Returns whether any was deleted; a folder that
    cannot be written (a read-only installation, which an upgrade rewrites whole) is passed over."""
    if folder is None:
        return False
    import hashlib

    digest = hashlib.sha256()
    for path in kernel_sources():
        with open(path, "rb") as f:
            digest.update(f.read())
    stamp, now = os.path.join(folder, SOURCES_DIGEST), digest.hexdigest()
    try:
        with open(stamp) as f:
            kept = f.read().strip()
    except OSError:
        kept = None
    if kept == now:
        return False
    mesh = os.path.join(os.path.dirname(folder), "mesh", "__pycache__")
    if os.path.basename(folder) != "__pycache__":  # under NUMBA_CACHE_DIR (or numba's user-wide
        from numba.core.caching import _CacheLocator  # folder): flat, a folder a source folder

        here = os.path.dirname(os.path.abspath(__file__))
        sub = _CacheLocator.get_suitable_cache_subpath(os.path.join(here, "mesh", "build.py"))
        mesh = os.path.join(os.path.dirname(folder), sub)
    stale = [f for d in (folder, mesh) for ext in ("*.nbi", "*.nbc") for f in glob.glob(os.path.join(d, ext))]
    for path in stale:
        try:
            os.remove(path)
        except OSError:
            pass
    try:  # whole or not at all: a process reading it meanwhile must not find it empty
        os.makedirs(folder, exist_ok=True)
        part = f"{stamp}.{os.getpid()}"
        with open(part, "w") as f:
            f.write(now + "\n")
        os.replace(part, stamp)
    except OSError:
        pass
    return bool(stale)


def available() -> bool:
    """Whether the compiled kernels can run (numba is importable)."""
    return njit is not None


def plain_python() -> bool:
    """Whether numba runs the kernels as plain Python (``NUMBA_DISABLE_JIT=1``: how the CUDA
    simulator's tests run them): nothing is compiled, so nothing waits for a compile."""
    return njit is not None and bool(numba_config.DISABLE_JIT)


def threads(work: int | None = None) -> int:
    """The number of shares a kernel's work is cut into: torch's thread count
    (``torch.set_num_threads``, ``OMP_NUM_THREADS``), so one setting bounds both; 1 where ``work``
    (elements) is under [`SMALL_WORK`][] (four times that where the shares run on Python threads:
    [`team_name`][]): below it, handing a share to a second thread costs about what the share
    saves (``examples/share_cost.py``), and waking a Python thread costs several times more, and
    more again on a busy machine."""
    import torch

    if work is not None and (work < SMALL_WORK or (work < 4 * SMALL_WORK and _team() is None)):
        return 1  # the team asked for only where the work is between the two
    return max(1, torch.get_num_threads())


_POOL: list[tuple[ThreadPoolExecutor, int]] = []  # the pool and its number of threads
_POOL_LOCK = threading.Lock()


def _pool(workers: int) -> ThreadPoolExecutor:
    """The pool that runs shares 1 .. of every kernel, grown to ``workers`` threads (under
    ``_POOL_LOCK``)."""
    if not _POOL or _POOL[0][1] < workers:
        if _POOL:  # its threads end once they have run what they were given
            _POOL[0][0].shutdown(wait=False)
        _POOL[:] = [(ThreadPoolExecutor(workers, thread_name_prefix="layoutwarp"), workers)]
    return _POOL[0][0]


def _forget_pool() -> None:  # a forked child has none of its parent's threads: it starts its own
    global _POOL_LOCK
    _POOL.clear()
    _POOL_LOCK = threading.Lock()  # another thread may have held it at the fork


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_forget_pool)

#: The team [`run_shares`][] runs on, once chosen: torch's OpenMP threads' runner, or ``None``
#: (a pool of Python threads), and whether it was the default (then a busy machine's calls run on
#: the Python threads: [`machine_busy`][]).
_TEAM: list[tuple[Callable[..., list[Any]] | None, bool]] = []
_JOBS: dict[int, tuple] = {}  # the shares each running team is given, by key
_KEYS = itertools.count(1)
_PID = os.getpid()  # a child forked from this process cannot use its OpenMP threads
#: The environment variable that sets [`set_team`][]'s default: ``openmp`` or ``python``.
TEAM_ENV = "LAYOUTWARP_TEAM"


def set_team(name: str | None) -> None:
    """Which threads run a kernel's shares ([`run_shares`][]): ``"openmp"``, torch's own OpenMP
    threads, where torch's runtime is GNU OpenMP's (the Linux wheels: its ``libgomp``), and the
    process is not a child forked from one that used them; ``"python"``, a pool of Python
    threads; ``None``, the default: ``LAYOUTWARP_TEAM``'s, else ``"openmp"`` where it can be,
    but the Python threads while the machine is busy ([`machine_busy`][]). On torch's threads no
    thread of the kernel waits for a core that one of them spins on: after each of torch's
    parallel ops its OpenMP threads spin for milliseconds, and a learnable step's share on a
    thread of its own beside one ran at half speed (the step 1.3–1.5x its time on torch's
    threads). On a busy machine the Python threads, which sleep rather than spin while they
    wait, take a fairer share of the cores. A child forked before this module was imported is not
    known as one: run it with one torch thread, as a ``DataLoader`` worker does (its torch ops on
    more would wait for ever there too)."""
    _TEAM.clear()
    if name is not None:
        _TEAM.append((_chosen(name, "set_team: name"), False))


def _chosen(name: str, where: str) -> Callable[..., list[Any]] | None:
    """The team of ``name`` (``where``: who gave it, for the error)."""
    if name not in ("openmp", "python"):
        raise ValueError(f"{where} must be 'openmp' or 'python', got {name!r}")
    team = _openmp_team() if name == "openmp" else None
    if name == "openmp" and team is None:
        raise ValueError(f"{where}: no OpenMP threads of torch's here (not GNU OpenMP's, or a forked child)")
    return team


def _run_job(key: int) -> None:
    """A thread of the team: its shares of job ``key`` (every ``n``-th from its number, where the
    team has ``n`` threads: fewer than asked for, a thread runs several)."""
    body, nt, args, results, errors, lib = _JOBS[key]
    try:
        for t in range(lib.omp_get_thread_num(), nt, lib.omp_get_num_threads()):
            results[t] = body(t, nt, *args)
    except BaseException as e:  # raised again on the calling thread
        errors.append(e)


_CALLBACK = ctypes.CFUNCTYPE(None, ctypes.c_void_p)(_run_job)
_UNDONE = object()  # a share's result before it has run
#: The interrupt ctypes dropped at a callback's edge that no team has raised yet (its class: a
#: ``KeyboardInterrupt``, or the command line's SIGTERM, a subclass of it), else ``None``.
_DROPPED: list[type[BaseException] | None] = [None]


def _unraisable(hook: Callable[[Any], Any]) -> Callable[[Any], Any]:
    """``sys.unraisablehook`` that keeps ``hook`` for everything but a ``KeyboardInterrupt`` (or a
    subclass) that ctypes drops at [`_run_job`][]'s entry or exit (a Ctrl-C there): noted, and
    raised again, of its own class, by the team on the main thread, with no report of its own."""

    def unraisable(report: Any) -> None:
        kind = report.exc_type
        if isinstance(kind, type) and issubclass(kind, KeyboardInterrupt) and report.object is _run_job:
            _DROPPED[0] = kind
        else:
            hook(report)

    return unraisable


@functools.cache
def _note_dropped_interrupts() -> None:
    """Set ``sys.unraisablehook`` to [`_unraisable`][] of the hook before, once (a hook set after
    it is the user's to keep)."""
    sys.unraisablehook = _unraisable(sys.unraisablehook)


@functools.cache
def _openmp_library() -> ctypes.CDLL | None:
    """The ``libgomp`` torch loaded (the same handle), ``None`` where it has none."""
    import torch

    found = glob.glob(os.path.join(os.path.dirname(torch.__file__), "lib", "libgomp*.so*"))
    if not found:
        return None
    lib = ctypes.CDLL(found[0])
    lib.GOMP_parallel.argtypes = [ctypes.c_void_p, ctypes.c_void_p, ctypes.c_uint, ctypes.c_uint]
    lib.GOMP_parallel.restype = None
    return lib


def _openmp_team() -> Callable[..., list[Any]] | None:
    """The runner of shares on torch's OpenMP threads (``GOMP_parallel``); ``None`` where torch
    has none, and in a forked child (GNU OpenMP's threads are not the child's: a team would wait
    for them for ever)."""
    lib = _openmp_library() if os.getpid() == _PID else None
    if lib is None:
        return None
    callback = ctypes.cast(_CALLBACK, ctypes.c_void_p)
    _note_dropped_interrupts()

    def team(body: Callable[..., Any], nt: int, args: tuple) -> list[Any]:
        key, results, errors = next(_KEYS), [_UNDONE] * nt, []
        _JOBS[key] = (body, nt, args, results, errors, lib)
        try:  # the GIL released while the team runs (ctypes.CDLL)
            lib.GOMP_parallel(callback, key, nt, 0)
        finally:
            del _JOBS[key]
        if errors:
            raise errors[0]
        main = threading.current_thread() is threading.main_thread()
        kind = _DROPPED[0] if main else None
        if kind is not None or any(r is _UNDONE for r in results):  # a Ctrl-C at a callback's edge,
            _DROPPED[0] = None  # which ctypes drops (at its entry: the share never ran)
            raise (kind or KeyboardInterrupt)()
        return results

    return team


def _team() -> Callable[..., list[Any]] | None:
    """The team chosen ([`set_team`][]), else ``LAYOUTWARP_TEAM``'s, else torch's OpenMP threads
    where they can be and the machine is not busy; ``None``: the pool of Python threads."""
    if os.getpid() != _PID:
        return None
    if not _TEAM:
        name = os.environ.get(TEAM_ENV)
        _TEAM.append((_chosen(name, TEAM_ENV), False) if name else (_openmp_team(), True))
    team, default = _TEAM[0]
    return None if default and machine_busy() else team


def team_name() -> str:
    """The threads a kernel's shares run on now ([`set_team`][]): ``"openmp"`` (torch's OpenMP
    team) or ``"python"`` (a pool of Python threads)."""
    return "python" if _team() is None else "openmp"


_LOAD: list[float] = [-1.0, 0.0]  # when the load was last read, and whether it was busy


def machine_busy() -> bool:
    """Whether more threads are running or waiting for a core than the cores this process may use
    and one more (Linux's ``/proc/loadavg`` at this moment, read at most once a second;
    elsewhere never busy)."""
    now = time.monotonic()
    if now - _LOAD[0] > 1.0:
        try:
            with open("/proc/loadavg") as f:
                runnable = int(f.read().split()[3].split("/")[0])
        except (OSError, IndexError, ValueError):
            runnable = 0
        cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
        _LOAD[:] = [now, float(runnable > cores + 1)]
    return bool(_LOAD[1])


def run_shares(body: Callable[..., Any], threads: int, *args: Any) -> list[Any]:
    """``body(t, threads, *args)`` for every share ``t < threads`` at once (``body``: a numba
    function compiled with ``nogil=True``, so the shares run in parallel), on torch's OpenMP
    threads or a pool of Python threads ([`set_team`][]), share 0 on the calling thread (an
    OpenMP team given fewer threads than asked for, e.g. under ``OMP_THREAD_LIMIT``, runs the
    rest in turn); returns their results in the order of ``t``. Shares write disjoint parts of
    the outputs, so the result does not depend on the thread count or on which thread ran
    what."""
    if threads <= 1:
        return [body(0, 1, *args)]
    team = _team()
    if team is not None:
        return team(body, threads, args)
    # a Ctrl-C (or SIGTERM) is taken once the shares are done: raised inside the pool's locks, it
    # left one held, and a worker waited on it for ever (the process hung at its exit)
    held = _hold_stops()
    try:
        with _POOL_LOCK:  # a thread that grows the pool meanwhile would shut this one down under us
            pool = _pool(threads - 1)
            futures: list[Future] = [pool.submit(body, t, threads, *args) for t in range(1, threads)]
        first = body(0, threads, *args)
        return [first, *(f.result() for f in futures)]
    finally:
        if held is not None:
            signal.pthread_sigmask(signal.SIG_SETMASK, held)


def _hold_stops() -> set[int] | None:
    """On the main thread, where Python takes signals: SIGINT and SIGTERM held back (delivered
    when the mask before, which this returns, is set again); elsewhere, or where the system has no
    signal masks, nothing (``None``)."""
    if not hasattr(signal, "pthread_sigmask") or threading.current_thread() is not threading.main_thread():
        return None
    return signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT, signal.SIGTERM})


def run_chunks(body: Callable[..., Any], threads: int, chunks: int, *args: Any) -> list[Any]:
    """[`run_shares`][] of a kernel cut into ``chunks`` chunks that any thread may take:
    ``body(t, threads, claims, *args)``, ``claims`` a fresh ``(chunks,)`` array of zeros that
    [`take`][] marks. Each share takes its own chunks first (``t``, ``t + threads``, …), then
    what is left of the others', from the last chunk down: a share the machine holds back leaves
    its work to the others (torch's OpenMP threads spin for milliseconds on the cores after each
    of torch's parallel ops, and a share's thread beside one runs at half speed meanwhile). Two
    shares may both take a chunk (no atomic operations): a chunk must write the same values
    whichever thread runs it, into outputs of its own, so the result does not depend on who ran
    what."""
    return run_shares(body, threads, np.zeros(max(int(chunks), 1), np.uint8), *args)


#: Bytes between two threads' work space ([`per_thread`][]): a page. Two cache lines apart, the
#: two shares of a learnable fovea step's integrals took 1.2–1.4x the time they take a page apart
#: (the 2-core machine of docs/speed.md; the hardware's prefetchers, or its cores' sharing).
APART = 4096


def per_thread(nt: int, shape: tuple[int, ...], dtype: type = np.float64) -> np.ndarray:
    """Work space of ``shape`` for each of ``nt`` threads, none sharing a cache line with another's
    or with its neighbours in the heap (threads writing to one line in turn stall each other: a
    learnable step's integrals ran 2.5x slower on two threads than on one, and 1.2x slower with
    the threads' rows 128 bytes apart): ``((nt + 2)·k, *shape)``, thread ``t``'s at row ``(t + 1)·k``
    ([`own`][]), with ``k - 1`` rows (at least [`APART`][] bytes) unused between two threads' and
    ``k`` at either end."""
    row = math.prod(shape) * np.dtype(dtype).itemsize
    k = 1 + -(-APART // row) if row else 1
    return np.empty(((nt + 2) * k, *shape), dtype=dtype)


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


#: The options every kernel and helper is compiled with: numpy's error model (a division by zero
#: gives inf, unchecked, so loops with one vectorise) and no reference counting (``_nrt=False``:
#: a kernel allocates nothing, its caller hands it its outputs and work space; counting the
#: references of the arrays a helper takes cost atomic operations in the innermost loops, 2-6x a
#: mesh stage's time).
OPTIONS = {"cache": True, "error_model": "numpy", "_nrt": False}


def serial(fn):
    """A kernel (or a thread's share of one, [`run_shares`][]) compiled once and called as a
    function, the GIL released while it runs."""
    return njit(nogil=True, **OPTIONS)(fn) if njit is not None else fn


def inline(fn):
    """A helper inlined into every kernel that calls it by LLVM (``forceinline``: compiled once per
    signature, as a function of its own, and inlined afterwards; numba's IR-level inlining typed
    and lowered it again at every call site, most of the compile time), so that the loops it is
    called in still run in SIMD lanes. Called from compiled code only (no Python wrapper)."""
    if njit is None:
        return fn
    return njit(forceinline=True, no_cpython_wrapper=True, no_cfunc_wrapper=True, **OPTIONS)(fn)


_COPIES: dict[Any, Any] = {}  # each helper's copy without IR inlining
_COPIES_LOCK = threading.RLock()


def _plain_copy(kernel: Any) -> Any:
    """``kernel`` (a compiled function) recompiled without numba's IR inlining: its Python
    function with its compiled callees replaced by their own plain copies, and its options less
    ``inline``; cached on disk under its name with ``_quick``."""
    with _COPIES_LOCK:
        if kernel not in _COPIES:
            func = without_ir_inlining(kernel.py_func)
            options = {k: v for k, v in kernel.targetoptions.items() if k not in ("inline", "nopython")}
            _COPIES[kernel] = njit(cache=True, **options)(func)
        return _COPIES[kernel]


def without_ir_inlining(func: Callable) -> Callable:
    """A copy of the Python function ``func`` (named ``NAME_quick``: numba's cache files are
    named by it) whose compiled callees (``inline="always"`` or not) are copies without IR
    inlining: numba then types and lowers each helper once, as a function of its own, instead of
    again at every call site. The CUDA kernels compile from such copies: NVVM inlines the device
    functions afterwards (the same PTX to within a few instructions), in a fifth of the compile
    time."""
    from numba.core.dispatcher import Dispatcher

    scope = dict(func.__globals__)
    for name in func.__code__.co_names:  # the compiled functions it calls, by their global names
        if isinstance(scope.get(name), Dispatcher):
            scope[name] = _plain_copy(scope[name])
    rebuilt = types.FunctionType(func.__code__, scope, func.__name__, func.__defaults__, func.__closure__)
    rebuilt.__qualname__ = f"{func.__qualname__}_quick"
    rebuilt.__module__, rebuilt.__doc__ = func.__module__, func.__doc__
    return rebuilt


def inline_ir(fn):
    """A helper inlined at numba's IR level (``inline="always"``): for a helper that returns a view
    of an array it was given (a function compiled without reference counting returns none), or a
    small one called with many different constant arguments (each combination of constants is a
    compile of its own for [`inline`][]'s helpers)."""
    return njit(inline="always", **OPTIONS)(fn) if njit is not None else fn


def _own(rows: np.ndarray, t: int, nt: int) -> np.ndarray:
    """Thread ``t``'s work space in [`per_thread`][]'s ``rows`` (``nt`` threads): a view, so
    inlined at numba's IR level (a function without reference counting returns no view)."""
    return rows[(t + 1) * (rows.shape[0] // (nt + 2))]


own = inline_ir(_own)


@inline
def tries(claims: np.ndarray, nt: int) -> int:
    """How many chunks a share of [`run_chunks`][] looks at, at most: ``range(tries(claims, nt))``
    gives [`take`][]'s ``m``."""
    n = claims.shape[0]
    return n + (n + nt - 1) // nt


@inline
def take(claims: np.ndarray, t: int, nt: int, m: int) -> int:
    """The ``m``-th chunk share ``t`` of ``nt`` looks at ([`run_chunks`][]: its own chunks
    ``t, t + nt, …``, then every chunk from the last down), marked taken; −1 where that one is
    taken already (or ``m`` is past the last)."""
    n = claims.shape[0]
    mine = (n - t + nt - 1) // nt
    i = t + m * nt if m < mine else n - 1 - (m - mine)
    if i < 0 or claims[i]:
        return -1
    claims[i] = 1
    return i
