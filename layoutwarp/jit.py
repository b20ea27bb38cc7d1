"""Compiled kernels: which units are ready, and compiling them once per installation.

numba compiles a kernel at its first call and keeps the machine code in a disk cache (``cache=True``:
beside the package, or under ``NUMBA_CACHE_DIR``), so only the first process of an installation
pays: about 80 s of CPU on 2 cores for every unit together (``layoutwarp doctor --compile`` prints
each one's time; ``docs/speed.md``). The kernels are grouped in *units*, each compiled whole: the
learnable layouts' mesh (``mesh``, any dtype), and per image dtype a fixed layout's forward
(``fixed/…``), the exact integrator (``learn/…``, with ``mesh``) and the sensor's measurement
(``measure/…``). The modes:

- ``"background"`` (the default): a call whose unit is missing from the cache answers from the
  torch path (the same values to rounding) while one child process compiles the unit (then the
  other units of its dtype) into the cache at normal priority; a call after that loads the
  compiled kernels in milliseconds. The child ends with its process: it is killed when the
  process exits (or dies), and what it finished stays cached for the next process. A call whose
  result would differ beyond rounding (the sensor's noise: the compiled sampler and torch's are
  different streams) runs a plain compiled kernel of the same values meanwhile, which compiles in
  seconds in the foreground ([`compiled`][]). Its means are what the call's own route gives
  them: from the torch path while a fixed layout's product compiles, equal to rounding, so a
  count drawn from a mean at its edge can differ by one from ``"wait"``'s.
- ``"wait"``: compile at first use, in the process, and wait for it: every call compiled, and
  results the same to the bit from a process's first call on (the test suite runs this way).
- ``"off"``: the torch path only.

The mode comes from the environment variable ``LAYOUTWARP_JIT`` or [`set_mode`][]. A unit
compiled in a process says so once, in one line on stderr. ``layoutwarp doctor`` reports each
unit's state; ``layoutwarp doctor --compile`` fills the cache in the foreground, two units at a
time (for a container image or a cluster node, before the jobs start).
"""

from __future__ import annotations

import atexit
import contextlib
import functools
import importlib
import json
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
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
    "compile_missing",
    "compiled",
    "load",
    "loaded",
    "mode",
    "ready",
    "register_warmup",
    "set_mode",
    "status",
    "stop_worker",
    "use_mode",
]

#: What each group of kernels computes (the names [`ready`][] takes).
GROUPS = {
    "fixed": "a fixed layout's forward (area weights and their product)",
    "learn": "the exact integrator of a learnable layout",
    "measure": "the sensor's measurement (noise, full well, ADC)",
}
#: The image dtypes kernels are compiled for, each on its own (a process seldom needs both).
DTYPES = ("float32", "float64")
#: What is compiled, loaded and reported at a time: the mesh of the learnable curved layouts (any
#: dtype), then each group for one dtype.
UNITS = ("mesh", *(f"{g}/{d}" for d in DTYPES for g in GROUPS))
#: What each unit compiles, in the notices.
_WHAT = {"mesh": "the pixel mesh of the curved layouts", **GROUPS}
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


def loaded(unit: str) -> bool:
    """Whether ``unit``'s kernels (one of [`UNITS`][]) run now: loaded in this process, not "off"."""
    if unit not in UNITS:
        raise ValueError(f"unit must be one of {', '.join(UNITS)}, got {unit!r}")
    return unit in _READY and mode() != "off"


def load(unit: str) -> bool:
    """Whether ``unit``'s kernels (one of [`UNITS`][]) run now, loaded from the disk cache here
    where they are there: never compiled, nor a compile started (a unit found missing is looked
    for again after [`LOOK_AGAIN_S`][]). For work that runs either way and is faster compiled."""
    if loaded(unit):
        return True
    if mode() == "off" or not kernels.available():
        return False
    if kernels.base.plain_python():
        _READY.add(unit)
        return True
    if _looked_lately(unit):
        return False
    if _loads(unit):
        _READY.add(unit)
        return True
    return False


def ready(group: str, dtype: str | torch.dtype = "float32", wait: bool = False) -> bool:
    """Whether ``group``'s compiled kernels (``"mesh"``: the mesh unit alone) for images of ``dtype``
    (float32 or float64) run now (see the module docstring). ``wait``: the caller needs the compiled
    kernels (its result would differ on the torch path): unless the mode is ``"off"``, compile them
    here (or wait for the background child where it is on them), then ``True``. ``False`` where
    numba is missing or the mode is ``"off"``: the caller takes its torch path."""
    units = _units(group, dtype)
    if getattr(_WARMING, "on", False):  # a warm-up takes the compiled paths
        return True
    current = mode()
    if not kernels.available() or current == "off":
        return False
    _share_cores()  # back to the thread's count once the child is done
    if _READY.issuperset(units):
        return True
    if kernels.base.plain_python():  # NUMBA_DISABLE_JIT: nothing to compile
        _READY.update(units)
        return True
    background = current == "background" and not wait
    for unit in units:
        if unit in _READY:
            continue
        worker = _WORKER
        if worker is not None and worker.has(unit):
            if background:
                return False  # the child has it to do: the torch path answers meanwhile
            if worker.current() == unit:  # else compiled here, before the child gets to it
                _announce(unit, "waiting for the background compile of")
                worker.wait_for(unit)
        elif background and worker is not None and worker.busy() and unit not in worker.done:
            return False  # looked at again once the child has it, or is free
        elif background and (unit in _FAILED or _FORKED) and _looked_lately(unit):
            return False  # another process may fill the cache: looked at again now and then
        if _loads(unit):
            _READY.add(unit)
            continue
        if worker is not None and unit in worker.done:
            _FAILED.add(unit)  # the child compiled it into another cache: not started again for it
        if background:  # the child takes it (and the other units of its dtype)
            with _LOCK:
                _start_worker(units, dtype)
            _share_cores()
            return False
        _announce(unit, "compiling")
        _warm(unit)
        _READY.add(unit)
    return True


def compiled(group: str, dtype: str | torch.dtype, kernel: Any, first: Any = None) -> Any | None:
    """``kernel`` (a compiled kernel of ``group``) where the result must come from compiled code
    (the sensor's noise draws): compiled here first if need be, whatever the mode but ``"off"``;
    ``None`` where numba is missing or the mode is ``"off"`` (the torch path).

    ``first``: a kernel of the same results, bit for bit, that compiles in seconds: in the
    ``"background"`` mode, what runs (compiled here, once per installation) while ``kernel``'s
    unit is still to compile, which the background child then takes."""
    if first is None or mode() != "background":
        return kernel if ready(group, dtype, wait=True) else None
    if ready(group, dtype):
        return kernel
    if not kernels.available():
        return None
    return _announcing(first, _units(group, dtype)[-1], "compiling the plain version (seconds) of")


def _announcing(kernel: Callable, unit: str, doing: str) -> Callable:
    """``kernel``, announcing ``doing`` ``unit`` once should a call of it compile (not where it
    loads from the cache)."""
    from numba.core import event

    class Announce(event.Listener):
        def on_start(self, ev: event.Event) -> None:
            _announce(unit, doing)

        def on_end(self, ev: event.Event) -> None:
            pass

    def run(*args: Any) -> Any:
        with event.install_listener("numba:compile", Announce()):
            return kernel(*args)

    return run


def status() -> dict[str, str]:
    """Each unit's state in this process: ``"ready"`` (loaded), ``"in cache"`` (compiled, not yet
    loaded), ``"compiling"`` (this process's background child has it to do), ``"not compiled"``
    or ``"no numba"``. The calling thread's torch shares the cores with the background child as
    at any layoutwarp call (`_share_cores`): one thread fewer while the child compiles, its
    thread back once the child is done."""
    _share_cores()
    out = {}
    for unit in UNITS:
        if not kernels.available():
            out[unit] = "no numba"
        elif unit in _READY:
            out[unit] = "ready"
        elif _WORKER is not None and _WORKER.has(unit):
            out[unit] = "compiling"
        else:
            out[unit] = "in cache" if _loads(unit) else "not compiled"
    return out


_CHILDREN_LOCK = threading.Lock()  # a compile's children: started, or stopped, one at a time


def compile_all(
    progress: Callable[[str, float, float], None] | None = None,
    units: tuple[str, ...] = UNITS,
    processes: int = 1,
) -> None:
    """Compile (or load) ``units`` (names from ``UNITS``; all by default), telling
    ``progress(unit, seconds, cpu_seconds)`` after each (its warm-up's wall and CPU time): in this
    process, or with ``processes > 1`` in that many child processes at a time, each a unit
    (numba compiles one kernel at a time in a process; ``mesh`` first, before the units that load
    its kernels): what ``layoutwarp doctor --compile`` runs."""
    if processes <= 1:
        for unit in units:
            start, cpu = time.perf_counter(), time.process_time()
            _warm(unit)
            _READY.add(unit)
            if progress is not None:
                progress(unit, time.perf_counter() - start, time.process_time() - cpu)
        return

    pool = ThreadPoolExecutor(processes)
    mesh = pool.submit(lambda: None)  # done at once unless mesh is compiled below
    code = (
        "import json, sys; from layoutwarp.jit import compile_all; "
        "compile_all(lambda *a: print(json.dumps(a)), units=(sys.argv[1],))"
    )

    children: list[subprocess.Popen] = []
    stop = threading.Event()

    def one(unit: str) -> None:
        if unit.startswith("learn/"):  # a learnable step's warm-up runs mostly the mesh's kernels:
            mesh.result()  # after them, not beside them (compiling them twice)
        with _CHILDREN_LOCK:
            if stop.is_set():
                return
            child = subprocess.Popen(
                [sys.executable, "-c", code, unit], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
            )
            children.append(child)
        out, err = child.communicate()
        if stop.is_set():
            return
        if child.returncode != 0:
            raise RuntimeError(f"compiling {unit} failed:\n{err[-2000:]}")
        if progress is not None:
            progress(*json.loads(out.strip().splitlines()[-1]))

    try:
        if "mesh" in units:
            mesh = pool.submit(one, "mesh")
        later = [u for u in units if u.startswith("learn/")]
        futures = [pool.submit(one, u) for u in units if u != "mesh" and u not in later]
        futures += [pool.submit(one, u) for u in later]
        for f in [mesh, *futures]:
            f.result()
    except BaseException:  # Ctrl-C, or a unit failed: the units not begun are not begun, and the
        with _CHILDREN_LOCK:  # compiles under way stop with the command (none outlives it)
            stop.set()
            for child in children:
                child.kill()
        raise
    finally:
        pool.shutdown(wait=True, cancel_futures=True)
    for unit in units:
        if _loads(unit):
            _READY.add(unit)


def compile_missing(
    processes: int = 2, say: Callable[[str], None] | None = None, units: tuple[str, ...] = UNITS
) -> tuple[str, ...]:
    """Compile those of ``units`` (all by default) missing from the cache, ``processes`` at a time
    ([`compile_all`][]), and return their names (none where the mode is ``"off"`` or numba is
    missing), telling ``say`` first: for a program about to need most of them (the test suite)."""
    if unknown := [u for u in units if u not in UNITS]:
        raise ValueError(f"units must be of {', '.join(UNITS)}, got {unknown[0]!r}")
    if not kernels.available() or mode() == "off":
        return ()
    missing = tuple(u for u, state in status().items() if state == "not compiled" and u in units)
    if missing:
        if say is not None:
            say(f"compiling {', '.join(missing)} ({processes} at a time; once per installation)")
        compile_all(units=missing, processes=processes)
    return missing


@functools.lru_cache(maxsize=64)  # asked on every call (a small one's route): the answer kept
def _units(group: str, dtype: str | torch.dtype) -> tuple[str, ...]:
    """The units a group of one dtype needs (the learnable layouts' mesh, then the group's own)."""
    name = str(dtype).removeprefix("torch.")
    if group not in GROUPS and group != "mesh":
        raise ValueError(f"group must be one of {', '.join(GROUPS)} or mesh, got {group!r}")
    if name not in DTYPES:
        raise ValueError(f"dtype must be one of {', '.join(DTYPES)}, got {dtype!r}")
    if group == "mesh":
        return ("mesh",)
    return ("mesh", f"learn/{name}") if group == "learn" else (f"{group}/{name}",)


# ----------------------------------------------------------------------------------------
# Is a unit in the cache? Run its warm-up with numba allowed to load, not to compile.
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
    keeps what it loaded). A look within a look (a warm-up that asks [`load`][]) leaves the
    outer one looking."""
    before = getattr(_CHECKING, "on", False)
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
        _CHECKING.on = before


def _warm(unit: str) -> None:
    """Run ``unit``'s warm-up, every [`ready`][] within it answering ``True``."""
    import torch

    group, _, dtype = unit.partition("/")
    if group not in _WARMUPS:  # registered when the warm-ups' module loads
        importlib.import_module(f"{__package__}.warmups")
    before = getattr(_WARMING, "on", False)
    _WARMING.on = True
    try:  # whatever the caller's grad mode, inside an operator too (the warm-up sees to it)
        _WARMUPS[group](getattr(torch, dtype or "float64"))
    finally:
        _WARMING.on = before  # a warm-up within a warm-up leaves the outer one warming


def _announce(unit: str, doing: str) -> None:
    if (unit, doing) not in _ANNOUNCED:
        _ANNOUNCED.add((unit, doing))
        group, _, dtype = unit.partition("/")
        what = _WHAT[group] + (f", {dtype}" if dtype else "")
        once = "once per installation; see layoutwarp doctor"
        print(f"layoutwarp: {doing} {what} ({once})", file=sys.stderr, flush=True)


#: Each unit's warm-up (by its group, or ``mesh``): its public paths on tiny inputs of one dtype, in
#: every type the library calls its kernels with (registered by [`layoutwarp.warmups`][]).
_WARMUPS: dict[str, Callable[[torch.dtype], None]] = {}


def register_warmup(group: str, fn: Callable[[torch.dtype], None]) -> None:
    """Make ``fn(dtype)`` the warm-up of ``group`` (one of [`GROUPS`][], or ``"mesh"``)."""
    if group not in GROUPS and group != "mesh":
        raise ValueError(f"group must be one of {', '.join(GROUPS)} or mesh, got {group!r}")
    _WARMUPS[group] = fn


# ----------------------------------------------------------------------------------------
# The background compile: one child process, a unit at a time, ended with its parent
# ----------------------------------------------------------------------------------------
class _Worker:
    """A ``python -c "...serve()"`` child compiling the units it was given, in order, answering
    ``done UNIT`` (or ``failed UNIT``) on its stdout after each, at normal priority, with this
    process's ``sys.path`` (so it compiles the package this process imported). It ends when they
    are done, when this process ends (killed at exit; on Linux by the kernel should it die: the
    thread that starts it lives as long as it), or at [`stop_worker`][]; ``OSError`` if it can't."""

    def __init__(self, units: list[str]) -> None:
        self.todo = list(units)
        self.done: set[str] = set()
        self.changed = threading.Condition(_LOCK)
        self.proc: subprocess.Popen | None = None
        self._error: BaseException | None = None
        started = threading.Event()
        threading.Thread(target=self._run, args=(started,), daemon=True, name="layoutwarp-compile").start()
        started.wait()
        if self._error is not None:
            raise OSError(f"{type(self._error).__name__}: {self._error}")

    def has(self, unit: str) -> bool:
        """Whether ``unit`` is still to come from the child."""
        return unit in self.todo and self.proc is not None and self.proc.poll() is None

    def busy(self) -> bool:
        """Whether the child is still at work."""
        return bool(self.todo) and self.proc is not None and self.proc.poll() is None

    def current(self) -> str | None:
        """The unit the child is on."""
        return self.todo[0] if self.busy() else None

    def wait_for(self, unit: str) -> None:
        with self.changed:
            while self.has(unit):
                self.changed.wait(0.5)

    def _run(self, started: threading.Event) -> None:
        env = {
            **os.environ,
            ENV: "wait",
            "OMP_NUM_THREADS": "1",
            "LAYOUTWARP_PARENT": str(os.getpid()),
            "PYTHONPATH": os.pathsep.join(p for p in sys.path if p),
        }
        try:
            self.proc = subprocess.Popen(
                [sys.executable, "-c", "from layoutwarp.jit import _serve; _serve()"],
                stdin=subprocess.PIPE,
                stdout=subprocess.PIPE,
                stderr=subprocess.DEVNULL,
                text=True,
                env=env,
            )
            self.proc.stdin.write("".join(u + "\n" for u in self.todo))
            self.proc.stdin.close()
        except (OSError, ValueError) as err:  # no Python to start (an embedded interpreter), no pipe
            self._error = err
            if self.proc is not None:
                self.proc.kill()
        started.set()
        if self._error is not None:
            return
        for line in self.proc.stdout:
            word, _, unit = line.strip().partition(" ")
            if word in ("done", "failed"):
                with self.changed:
                    if unit in self.todo:
                        self.todo.remove(unit)
                        (self.done if word == "done" else _FAILED).add(unit)
                    self.changed.notify_all()
        self.proc.wait()  # reaped here, by the thread that started it
        with self.changed:
            _FAILED.update(self.todo)  # ended before them: not to be started again
            self.todo = []
            self.changed.notify_all()

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.kill()


#: Units the background child failed on (or compiled into another cache): the torch path answers.
_FAILED: set[str] = set()


def _start_worker(units: tuple[str, ...], dtype: str | torch.dtype) -> bool:
    """Start this process's background child on ``units``, then the other units of ``dtype`` not
    loaded here (one child a process: a later start waits for the first to end); ``False`` where
    none starts (a forked child of a process that compiles, a unit the child failed on before, no
    Python to start: its call takes the torch path)."""
    global _WORKER
    if _WORKER is not None and _WORKER.busy():
        return True  # on other units: this one's call takes the torch path until it is free
    if _FORKED or any(u in _FAILED for u in units):
        return False
    name = str(dtype).removeprefix("torch.")
    todo = [u for u in units if u not in _READY]
    todo += [u for u in UNITS if u.endswith("/" + name) and u not in todo and u not in _READY | _FAILED]
    try:
        worker = _Worker(todo)
    except OSError as err:
        _FAILED.update(todo)
        _announce(todo[0], f"no background compile ({err}); the torch path answers:")
        return False
    _WORKER = worker
    _announce(todo[0], "compiling in the background (the torch path answers meanwhile):")
    return True


#: Whether this process is a forked child (a DataLoader's worker) of one whose background compile ran:
#: it starts none (its parent's fills the cache) and looks again at most every [`LOOK_AGAIN_S`][] s.
_FORKED = False
#: Seconds before a unit found missing from the disk cache is looked for again ([`load`][], and a
#: forked child's [`ready`][]).
LOOK_AGAIN_S = 5.0
_LOOKED: dict[str, float] = {}  # unit: when it was last looked for (a forked child's, load's)


def _looked_lately(unit: str) -> bool:
    """Whether ``unit`` was looked for in the disk cache less than [`LOOK_AGAIN_S`][] ago; else
    ``False``, the look about to be made noted."""
    now = time.monotonic()
    if now - _LOOKED.get(unit, -LOOK_AGAIN_S) < LOOK_AGAIN_S:
        return True
    _LOOKED[unit] = now
    return False


def _after_fork_in_child() -> None:
    global _WORKER, _FORKED, _LOCK
    _FORKED = _FORKED or (_WORKER is not None and bool(_WORKER.todo))  # (not poll(): not its child)
    _WORKER = None  # its parent's, not its own
    _LOCK = threading.RLock()  # another thread may have held it at the fork
    _SHARED.__dict__.clear()


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_after_fork_in_child)


def stop_worker() -> None:
    """Stop this process's background compile, if any, leaving what it has not finished for a
    later process (it stops by itself when the process ends)."""
    global _WORKER
    with _LOCK:
        worker, _WORKER = _WORKER, None
    if worker is not None:
        worker.stop()
    _share_cores()  # this thread's torch threads as they were


atexit.register(stop_worker)


_SHARED = threading.local()  # per thread: torch's thread count before the background compile took one


def _share_cores() -> None:
    """While this process's background compile runs, the calling thread's torch ops run one thread
    fewer (at least one; torch's count is per thread), and after it as many as before: with both
    at full width on 2 cores, torch's threads kept waiting for each other (the README's example
    took twice as long). A count the user changed meanwhile stays theirs."""
    worker = _WORKER
    before = getattr(_SHARED, "before", None)
    if worker is None and before is None:
        return
    busy = worker is not None and worker.busy()
    if busy == (before is not None):
        return
    import torch

    if busy:
        n = torch.get_num_threads()
        if n > 1:
            torch.set_num_threads(n - 1)
            _SHARED.before = n
    else:
        if torch.get_num_threads() == before - 1:
            torch.set_num_threads(before)
        _SHARED.before = None


def cache_folder() -> str | None:
    """Where numba keeps this installation's compiled kernels (``None`` without numba):
    ``kernels.cache_folder()``'s answer: the kernels package's ``__pycache__`` (the mesh's in
    ``mesh/__pycache__`` beneath it), or their places under ``NUMBA_CACHE_DIR``."""
    return kernels.cache_folder()


def _end_with_parent() -> None:
    """In the background child: end when the process that started it ends. On Linux the kernel
    sends SIGKILL when the parent thread dies; elsewhere the child checks its parent between
    units."""
    parent = int(os.environ.get("LAYOUTWARP_PARENT", "0"))
    with contextlib.suppress(Exception):
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        pr_set_pdeathsig = 1
        libc.prctl(pr_set_pdeathsig, signal.SIGKILL)
    if parent and os.getppid() != parent:  # the parent ended before the line above
        os._exit(0)


def _serve() -> None:
    """The background child's loop: compile each unit named on stdin, answer ``done UNIT`` (or
    ``failed UNIT``)."""
    _end_with_parent()
    parent = int(os.environ.get("LAYOUTWARP_PARENT", "0"))
    for line in sys.stdin:
        unit = line.strip()
        try:
            _warm(unit)
            said = "done"
        except Exception:  # its calls take the torch path in the parent (a call that needs the
            said = "failed"  # compiled kernels compiles them there, and reports the error)
        if parent and os.getppid() != parent:
            return
        print(f"{said} {unit}", flush=True)
