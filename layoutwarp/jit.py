"""Compiled code without the wait: which groups of kernels are ready, and compiling them once.

numba compiles a kernel at its first call and keeps the machine code in a disk cache
(``cache=True``: beside the package, or under ``NUMBA_CACHE_DIR``), so only the first process of
an installation pays. From an empty cache that first payment is about a minute and a half of
compiling on 2 cores for the kernels a user meets first (``docs/speed.md``), and nothing could be
cut from it without slowing every later call. So by default no call waits for it:

- ``"background"`` (the default): the first call that could use a group of kernels missing from
  the cache starts one worker process (at idle priority) that compiles the groups of its dtype into the
  cache, the one asked for first, and the call answers from the torch path (the same values to rounding). A
  call after the worker has compiled its group loads it from the cache in milliseconds and runs
  compiled from then on. A call whose result would differ beyond rounding (the sensor's noise
  draws: the compiled sampler and torch's are different streams) takes [`compiled`][]. The
  worker compiles the groups of the dtype asked for; after its parent has ended it finishes the
  group it is on, so the next process finds it in the cache, and ends. One worker fills a
  cache: a process that finds another process's worker at work starts none and looks at the
  cache every few seconds (back-to-back commands share the first one's).
  The sensor's noise is the one such call, and it does not wait long: while the worker has its
  group to do, it runs a *quick build* of its kernel ([`quick`][]: the same code compiled
  without numba's IR inlining, in seconds rather than half a minute, the same values to the bit,
  1.5–6x slower), compiled in the process and kept in the cache beside the full build.
- ``"wait"``: compile at first use and wait for it: every call compiled, and results the same to
  the bit from a process's first call on (the test suite runs this way). A group is compiled
  whole, in a child process (the compiler's ~300 MB of heap leave with it; the caller then
  loads the group from the cache), and processes on one cache (the ranks of a ``torchrun`` job,
  pytest's workers) take each group in turn: the others wait for it and load it rather than
  compile it again.
- ``"off"``: the torch path only.

The mode comes from the environment variable ``LAYOUTWARP_JIT`` or [`set_mode`][]. Any group
that has to be compiled in a process says so once, in one line on stderr. ``layoutwarp doctor``
reports each group's state; ``layoutwarp doctor --compile`` fills the cache in the foreground
(for a container image or a cluster node, before the jobs start).
"""

from __future__ import annotations

import contextlib
import importlib
import math
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from typing import TYPE_CHECKING, Any

from . import kernels

if TYPE_CHECKING:
    import torch

__all__ = [
    "DTYPES",
    "GROUPS",
    "MODES",
    "UNITS",
    "cache_folder",
    "compile_all",
    "compiled",
    "mode",
    "quick",
    "ready",
    "register_warmup",
    "serve",
    "set_mode",
    "status",
    "stop_worker",
    "use_mode",
]

#: What each group of kernels computes (the names [`ready`][] takes).
GROUPS = {
    "fixed": "a fixed layout's forward (area weights and their product)",
    "learn": "the exact integrator and the mesh of a learnable layout",
    "measure": "the sensor's measurement (noise, full well, ADC)",
}
#: The image dtypes kernels are compiled for, each on its own (a process seldom needs both).
DTYPES = ("float32", "float64")
#: A group for one dtype: what is compiled, loaded and reported at a time.
UNITS = tuple(f"{g}/{d}" for d in DTYPES for g in GROUPS)
#: The modes of [`set_mode`][] and of ``LAYOUTWARP_JIT``.
MODES = ("background", "wait", "off")
#: The environment variable that sets the mode.
ENV = "LAYOUTWARP_JIT"

_LOCK = threading.RLock()
_READY: set[str] = set()  # units loaded (or compiled) in this process
_ANNOUNCED: set[tuple[str, str]] = set()
_MODE: list[str] = []  # set_mode's choice, if any
_WORKER: _Worker | None = None
_CHECKING = threading.local()  # set while this thread checks the cache: numba may load, not compile
_WARMING = threading.local()  # set while this thread runs a warm-up


def mode() -> str:
    """The current mode: [`set_mode`][]'s, else ``LAYOUTWARP_JIT``'s, else ``"background"``."""
    if _MODE:
        return _MODE[-1]
    value = os.environ.get(ENV, "background")
    if value not in MODES:
        raise ValueError(f"{ENV} must be one of {', '.join(MODES)}, got {value!r}")
    return value


def set_mode(value: str | None) -> None:
    """Set the mode for this process (``None``: back to ``LAYOUTWARP_JIT``'s)."""
    if value is not None and value not in MODES:
        raise ValueError(f"mode must be one of {', '.join(MODES)}, got {value!r}")
    _MODE[:] = [] if value is None else [value]


@contextlib.contextmanager
def use_mode(value: str) -> Iterator[None]:
    """Within: mode ``value`` (e.g. ``"wait"`` where the compiled kernels are what is measured)."""
    saved = _MODE[:]
    set_mode(value)
    try:
        yield
    finally:
        _MODE[:] = saved


def ready(group: str, dtype: str | torch.dtype = "float32", wait: bool = False) -> bool:
    """Whether ``group``'s compiled kernels for images of ``dtype`` (float32 or float64) run now
    (see the module docstring). ``wait``: the caller needs the compiled kernels (its result would
    differ on the torch path): unless the mode is ``"off"``, wait for the background worker where
    it is on them, else compile here, then ``True``. ``False`` where numba is missing or the mode
    is ``"off"``: the caller takes its torch path."""
    unit = _unit(group, dtype)
    if getattr(_WARMING, "on", False):  # a warm-up takes the compiled paths
        return True
    current = mode()
    if not kernels.available() or current == "off":
        return False
    if unit in _READY:
        return True
    if kernels.base.plain_python():  # NUMBA_DISABLE_JIT: nothing to compile, nothing to warm
        _READY.add(unit)
        return True
    with _LOCK:
        worker = _WORKER
        if worker is not None and worker.has(unit) and not wait and current == "background":
            return False  # still to compile: no need to look at the cache
        if not wait and current == "background" and _looked_recently(unit):
            return False  # another process's worker has it: looked at the cache a moment ago
        if unit not in _READY and _loads(unit):
            _READY.add(unit)
        if unit in _READY:
            return True
        if current == "background" and not wait:  # the worker takes it: queued, or a new worker
            if worker is None or not worker.enqueue(unit):
                _start_worker(unit)  # unless another process's worker fills this cache
            return False
        if worker is not None and worker.current == unit and worker.has(unit):
            _announce(unit, "waiting for the background compile of")
            worker.wait_for(unit)
            if _loads(unit):
                _READY.add(unit)
                return True
        if worker is not None:
            worker.drop(unit)  # compiled here, beside the worker's current unit
        if current == "wait":  # the whole unit, taken in turn with the other processes on this
            with _unit_lock(unit):  # cache (the ranks of a torchrun job, pytest's workers): each
                if not _loads(unit):  # after the first loads it
                    _announce(unit, "compiling")
                    _compile_in_child(unit)
                    if not _loads(unit):  # the child could not fill the cache: compiled here
                        _warm(unit)
        else:
            _announce(unit, "compiling")  # numba compiles what the call uses, as it comes
        _READY.add(unit)
        return True


def compiled(group: str, dtype: str | torch.dtype, kernel: Any) -> Any | None:
    """What to call for ``kernel`` (a compiled kernel of ``group``) where the result must come
    from compiled code (the sensor's noise draws): ``kernel`` itself where its group is ready or
    the mode is ``"wait"`` (compiled here if need be); in ``"background"`` mode while the worker
    has the group to do, its [`quick`][] build (compiled here in seconds the first time, the
    same values); ``None`` where numba is missing or the mode is ``"off"`` (the torch path)."""
    if ready(group, dtype):  # in wait mode, compiled here; in background mode, starts the worker
        return kernel
    if mode() == "off" or not kernels.available():
        return None
    unit = _unit(group, dtype)  # background mode, the worker on the group
    _announce(unit, "compiling a quick build (seconds; the full one follows in the background) of")
    return quick(kernel)


def quick(kernel: Any) -> Any:
    """``kernel``'s quick build: its Python function and every compiled function it calls,
    recompiled without numba's IR inlining (``inline="always"``; the rest of its options kept).
    IR inlining makes numba type and lower each helper again at every call site, most of a large
    kernel's compile time (``sensor_measure``: 21 s, quick 6 s); without it LLVM still inlines
    small helpers, and the arithmetic is the same, so the results are the same to the bit (the
    kernels use no fast-math), at 1.5–6x the run time. Cached under a name of its own
    (``NAME_quick``) beside the full build. (The CUDA kernels are always built this way:
    `layoutwarp.kernels.base.quick_build`.)"""
    return kernels.base.quick_build(kernel)


def status() -> dict[str, str]:
    """Each group's state per dtype in this process (``"learn/float32"``: ...): ``"ready"``
    (loaded), ``"in cache"`` (compiled, not yet loaded), ``"compiling"`` (the background worker
    has it to do), ``"compiling elsewhere"`` (another process's worker, which fills this cache),
    ``"not compiled"`` or ``"no numba"``."""
    out = {}
    for unit in UNITS:
        if not kernels.available():
            out[unit] = "no numba"
        elif unit in _READY:
            out[unit] = "ready"
        elif _WORKER is not None and _WORKER.has(unit):
            out[unit] = "compiling"
        elif _looked_recently(unit):
            out[unit] = "compiling elsewhere"
        else:
            out[unit] = "in cache" if _loads(unit) else "not compiled"
    return out


def compile_all(progress: Callable[[str, float], None] | None = None, units: tuple[str, ...] = UNITS) -> None:
    """Compile (or load) every group for both dtypes (or ``units``, names from ``UNITS``) in
    this process, telling ``progress(unit, seconds)`` after each: what ``layoutwarp doctor
    --compile`` runs."""
    for unit in units:
        start = time.perf_counter()
        _warm(unit)
        _READY.add(unit)
        if progress is not None:
            progress(unit, time.perf_counter() - start)


def _compile_in_child(unit: str) -> None:
    """Compile ``unit`` into the disk cache in a child process and wait for it (wait mode): a
    process that has compiled a group keeps about 300 MB more of heap than one that loaded it
    (numba's and LLVM's), which leaves with the child. A child that fails (it cannot import the
    package, say) leaves the unit to the caller, which then compiles it and reports any error."""
    code = f"from layoutwarp.jit import compile_all; compile_all(units=({unit!r},))"
    quiet = dict.fromkeys(("stdin", "stdout", "stderr"), subprocess.DEVNULL)
    with contextlib.suppress(OSError):  # no Python to start (an embedded interpreter, say)
        subprocess.run([sys.executable, "-c", code], **quiet, check=False)


def _unit(group: str, dtype: str | torch.dtype) -> str:
    name = str(dtype).removeprefix("torch.")
    if group not in GROUPS:
        raise ValueError(f"group must be one of {', '.join(GROUPS)}, got {group!r}")
    if name not in DTYPES:
        raise ValueError(f"dtype must be one of {', '.join(DTYPES)}, got {dtype!r}")
    return f"{group}/{name}"


# ----------------------------------------------------------------------------------------
# Is a group in the cache? Run its warm-up with numba allowed to load, not to compile.
# ----------------------------------------------------------------------------------------
class _WouldCompile(Exception):
    pass


def _abort_compiles() -> contextlib.AbstractContextManager:
    """Within: a numba compile in this thread raises [`_WouldCompile`][] before it starts
    (loading from the disk cache happens before numba's compile event, so it still works)."""
    from numba.core import event

    class Abort(event.Listener):
        def on_start(self, ev: event.Event) -> None:
            if getattr(_CHECKING, "on", False):
                raise _WouldCompile

        def on_end(self, ev: event.Event) -> None:
            pass

    return event.install_listener("numba:compile", Abort())


def _loads(unit: str) -> bool:
    """Whether every kernel of ``unit`` loads from the disk cache (then they stay loaded: numba
    keeps what it loaded)."""
    _CHECKING.on = True
    try:
        with _abort_compiles():
            _warm(unit)
        return True
    except _WouldCompile:
        return False
    except Exception:  # a look must not fail the user's call: what failed here is compiled (and
        return False  # fails, if it does) where the call itself runs it
    finally:
        _CHECKING.on = False


def _warm(unit: str) -> None:
    """Run ``unit``'s warm-up, every [`ready`][] within it answering ``True``."""
    import torch

    group, dtype = unit.split("/")
    if group not in _WARMUPS:  # registered when the warm-ups' module loads (with the package's core)
        importlib.import_module(f"{__package__}.warmups")
    from .ops import autograd_inside

    _WARMING.on = True
    try:
        with autograd_inside():  # whatever the caller's grad mode, inside an operator too: the
            _WARMUPS[group](getattr(torch, dtype))  # learnable paths train a step
    finally:
        _WARMING.on = False


def _announce(unit: str, doing: str) -> None:
    if (unit, doing) not in _ANNOUNCED:
        _ANNOUNCED.add((unit, doing))
        group, dtype = unit.split("/")
        once = "once per installation; see layoutwarp doctor"
        print(f"layoutwarp: {doing} {GROUPS[group]}, {dtype} ({once})", file=sys.stderr, flush=True)


#: Each group's warm-up: its public paths on tiny inputs of one dtype, in every type the library
#: calls its kernels with (registered by [`layoutwarp.warmups`][], loaded when first needed).
_WARMUPS: dict[str, Callable[[torch.dtype], None]] = {}


def register_warmup(group: str, fn: Callable[[torch.dtype], None]) -> None:
    """Make ``fn(dtype)`` the warm-up of ``group`` (one of [`GROUPS`][])."""
    if group not in GROUPS:
        raise ValueError(f"group must be one of {', '.join(GROUPS)}, got {group!r}")
    _WARMUPS[group] = fn


# ----------------------------------------------------------------------------------------
# The background worker: one process, a unit at a time, the most wanted first
# ----------------------------------------------------------------------------------------
class _Worker:
    """A ``python -m layoutwarp.jit`` process compiling the units it is sent, one a line on its
    stdin, and answering each on stdout; the next unit goes out as the last comes back (the
    first asked for first, then the other groups of its dtype: the other dtype's wait until a
    call needs them), so a process that needs a unit the worker has not begun compiles it itself
    beside it ([`drop`][]). One worker serves a cache: it holds the cache's worker lock
    ([`_take_worker_lock`][]) while it lives, and a process that finds it held starts none of its
    own ([`_elsewhere`][]); a unit of the other dtype joins the queue of a worker at work
    ([`enqueue`][])."""

    def __init__(self, first: str, lock: Any) -> None:
        dtype = first.split("/")[1]
        self.queue = [u for u in UNITS if u != first and u.endswith(dtype)]
        self.done: set[str] = set()
        self.current = first
        self.changed = threading.Condition(_LOCK)
        self.proc = subprocess.Popen(
            [sys.executable, "-c", "from layoutwarp.jit import serve; serve()"],  # the package's
            # import registers the warm-ups
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.DEVNULL,
            text=True,
            env={**os.environ, ENV: "wait", "OMP_NUM_THREADS": "1"},
            # in the parent's session: a session of its own gets a CPU share of its own (Linux's
            # autogroups) whatever its priority, and a torch-path step on 2 cores ran 50x slower
            pass_fds=() if lock is None else (lock.fileno(),),  # the worker holds the lock now
        )
        if lock is not None:
            lock.close()  # ... and alone: it is released when the worker ends
        self._send(first)
        threading.Thread(target=self._read, daemon=True, name="layoutwarp-jit").start()

    def has(self, unit: str) -> bool:
        """Whether ``unit`` is still to come from the worker."""
        return (unit == self.current or unit in self.queue) and self.proc.poll() is None

    def enqueue(self, unit: str) -> bool:
        """Add ``unit`` to the queue of a worker still at work; ``False`` where it has ended (or
        is ending: its queue ran out, and it finishes the unit it is on)."""
        with self.changed:
            if self.proc.poll() is not None or self.current is None:
                return False
            if unit != self.current and unit not in self.queue:
                self.queue.append(unit)
            return True

    def drop(self, unit: str) -> None:
        with self.changed:
            if unit in self.queue:
                self.queue.remove(unit)

    def wait_for(self, unit: str) -> None:
        with self.changed:
            while self.has(unit):
                self.changed.wait(0.5)

    def _send(self, unit: str | None) -> None:
        self.current = unit
        if unit is None:
            self.proc.stdin.close()
        else:
            self.proc.stdin.write(unit + "\n")
            self.proc.stdin.flush()

    def _read(self) -> None:
        for line in self.proc.stdout:
            if not line.startswith("done "):  # anything else a warm-up printed
                continue
            with self.changed:
                self.done.add(line.split()[-1])
                self._send(self.queue.pop(0) if self.queue else None)
                self.changed.notify_all()
        with self.changed:
            self.current, self.queue = None, []  # ended: nothing more will come from it
            self.changed.notify_all()


def _start_worker(unit: str) -> None:
    """Start this process's worker on ``unit``, handing it the cache's worker lock; where another
    process's worker holds the lock, start none ([`_elsewhere`][])."""
    global _WORKER
    lock = _take_worker_lock()
    if lock is False:
        _elsewhere(unit)
        return
    _announce(unit, "compiling in the background (the torch path answers meanwhile):")
    try:
        _WORKER = _Worker(unit, lock)
    except BaseException:
        if lock is not None:
            lock.close()  # no worker holds it: another process may start one
        raise


#: How often a process whose cache another process's worker fills looks at the cache again (s).
ELSEWHERE_LOOK_S = 2.0
_LOOKED: dict[str, float] = {}  # unit: when this process last found it compiling elsewhere


def _looked_recently(unit: str) -> bool:
    """Whether this process found ``unit`` compiling elsewhere less than `ELSEWHERE_LOOK_S` ago."""
    return time.monotonic() - _LOOKED.get(unit, -math.inf) < ELSEWHERE_LOOK_S


def _elsewhere(unit: str) -> None:
    """Note that another process's background worker fills this cache: this process answers
    from the torch path, and [`ready`][] looks at the cache again every `ELSEWHERE_LOOK_S`
    seconds rather than on every call (or starts a worker of its own once that one has ended)."""
    _announce(unit, "waiting, on the torch path, for another process's background compile of")
    _LOOKED[unit] = time.monotonic()


def stop_worker() -> None:
    """Stop this process's background worker, if any, leaving what it has not finished
    uncompiled (a benchmark's throw-away cache; a test). By default it runs on after its parent
    ends, to finish the cache for the next process."""
    global _WORKER
    with _LOCK:
        worker, _WORKER = _WORKER, None
    if worker is not None:
        worker.proc.kill()
        worker.proc.wait()


def cache_folder() -> str | None:
    """Where numba keeps this installation's compiled kernels (``None`` without numba)."""
    if not kernels.available():
        return None
    return getattr(getattr(kernels.prefix_tables, "_cache", None), "_cache_path", None)


def _lock_path(name: str) -> str:
    folder = cache_folder() or tempfile.gettempdir()
    with contextlib.suppress(OSError):  # a read-only cache: the lock file may exist, or not open
        os.makedirs(folder, exist_ok=True)
    return os.path.join(folder, f"layoutwarp-{name}.lock")


def _take_worker_lock() -> Any:
    """The cache's background-worker lock, taken if free: an open file holding it (handed to the
    worker, which holds it while it lives), ``False`` where another process's worker holds it,
    ``None`` where there are no such locks (not POSIX: every process may start its own)."""
    try:
        import fcntl
    except ImportError:
        return None
    try:  # read-only and shared: flock works on it, whoever created the file, on a read-only cache too
        fd = os.open(_lock_path("worker"), os.O_RDONLY | os.O_CREAT, 0o666)
    except OSError:  # a cache folder this user cannot write: no lock, a worker of its own
        return None
    handle = os.fdopen(fd, "rb")  # handed on to the worker; closed here after
    try:
        fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        handle.close()
        return False
    return handle


@contextlib.contextmanager
def _unit_lock(unit: str) -> Iterator[None]:
    """Held while a worker compiles ``unit``: the workers of several processes on one cache (the
    ranks of a ``torchrun`` job) take the units in turn, and each after the first loads them."""
    try:
        import fcntl
    except ImportError:  # not POSIX: no lock, at worst the same unit compiled twice
        yield
        return
    with open(_lock_path(unit.replace("/", "-")), "w") as handle:
        fcntl.flock(handle, fcntl.LOCK_EX)
        yield


def serve() -> None:
    """The background worker's loop: compile each unit named on stdin, answer ``done UNIT``, and
    end when stdin does (its parent sends no more, or has ended: the unit at hand is finished).
    It holds the cache's worker lock its parent handed it, ignores Ctrl-C (meant for its parent)
    and runs only on cores nobody else wants."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    with contextlib.suppress(OSError, AttributeError):  # the user's own work comes first: this
        os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))  # runs on cores nobody wants
    for line in sys.stdin:
        unit = line.strip()
        with contextlib.suppress(Exception), _unit_lock(unit):  # a failure: a unit that does not load
            _warm(unit)
        print(f"done {unit}", flush=True)
