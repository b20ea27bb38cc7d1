"""numba's CUDA target: importing it on any numpy, compiling the kernels (to PTX without a GPU),
launching them on torch's stream, and checking once that they run.

Every CUDA kernel of the package is launched by [`cuda_launch`][]: the exact integrator's by
name ([`layoutwarp.kernels.exact_cuda.CUDA_SOURCES`][]), the device mesh's by their source function.
"""

from __future__ import annotations

import contextlib
import ctypes
import importlib
import os
import sys
import types
import warnings
from collections import Counter
from collections.abc import Callable, Iterator
from typing import TYPE_CHECKING

import numpy as np

from .base import njit, numba_config, without_ir_inlining
from .exact_cuda import CUDA_SOURCES, cuda_signature
from .prefix import BLOCK

if TYPE_CHECKING:
    import torch

__all__ = [
    "CUDA_THREADS",
    "DIRECT_OFF",
    "FAILED",
    "FAST_LAUNCH",
    "LAUNCHES",
    "REMOVED_NUMPY_ALIASES",
    "cuda_available",
    "cuda_checked",
    "cuda_launch",
    "cuda_ptx",
    "fall_back",
    "runs_on_device",
    "simulated",
    "stream_of",
    "usable",
]

cuda = None  # numba.cuda, imported by the first CUDA call (it costs a tenth of a second)
_CUDA_KERNELS: dict = {}
_CUDA_OK: dict = {}
_SOURCES: dict[Callable, Callable] = {}  # each kernel's source as compiled (_kernel_source)
#: Every launch [`cuda_launch`][] made in this process, by kernel name (a launch of no items
#: launches nothing and is not counted): what a count of a step's GPU launches reads, also in
#: numba's CUDA simulator, where no GPU is needed.
LAUNCHES: Counter[str] = Counter()


#: Device kernels that failed to compile or launch in this process, by name, with the reason:
#: their callers take the torch path instead (see [`fall_back`][]).
FAILED: dict[str, str] = {}


def usable(name: str) -> bool:
    """Whether the device kernel ``name`` has not failed in this process (see [`fall_back`][])."""
    return name not in FAILED


def fall_back(name: str, err: Exception) -> None:
    """Record that the device kernel ``name`` failed (numba-cuda could not compile or launch it)
    and say so once, in one warning; its caller then takes its torch path from now on."""
    if name not in FAILED:
        FAILED[name] = f"{type(err).__name__}: {' '.join(str(err).split())}"[:300]
        warnings.warn(
            f"layoutwarp: the CUDA kernel of {name} does not run here ({FAILED[name]}); its torch path runs",
            RuntimeWarning,
            stacklevel=3,
        )


def simulated() -> bool:
    """Whether numba's CUDA simulator stands in for a GPU (``NUMBA_ENABLE_CUDASIM=1``): the CUDA
    kernels then run as Python on CPU arrays, and the device paths take CPU tensors, so their
    launches and results can be checked where no GPU is."""
    return njit is not None and bool(numba_config.ENABLE_CUDASIM)


#: Threads per block of the CUDA kernels; 32 in numba's CUDA simulator ([`simulated`][]), where
#: every thread of a block is a Python thread (the same code, four times fewer threads to start).
CUDA_THREADS = 32 if simulated() else 128


def runs_on_device(tensor: torch.Tensor) -> bool:
    """Whether work on ``tensor`` takes the CUDA kernels: it is on a CUDA device, or on the CPU
    under numba's CUDA simulator ([`simulated`][]: how the device paths' values and launches are
    checked without a GPU)."""
    return tensor.is_cuda or (tensor.device.type == "cpu" and simulated())


def stream_of(tensor: torch.Tensor) -> int:
    """The handle of torch's current CUDA stream on ``tensor``'s device (0, the default stream,
    for a CPU tensor in the simulator): the stream [`cuda_launch`][] queues on, so the kernels run
    in order with torch's own work."""
    if tensor.device.type != "cuda":
        return 0
    import torch

    return torch.cuda.current_stream(tensor.device).cuda_stream


#: numpy's names that numpy removed and numba-cuda still registers overloads for when it first
#: compiles (0.30.4: ``np.row_stack``, gone in numpy 2.5), each with the function it aliased.
REMOVED_NUMPY_ALIASES = {"row_stack": "vstack"}


def _import_cuda() -> None:
    """Import numba's CUDA target, and its numpy overloads with numpy's removed aliases in place
    for that moment only (numba-cuda 0.30.4 reads ``np.row_stack`` while it registers them, and
    without it on numpy ≥ 2.5 no kernel compiles; numba's own CPU target checks the version)."""
    global cuda
    if cuda is None:
        missing = [name for name in REMOVED_NUMPY_ALIASES if not hasattr(np, name)]
        for name in missing:
            setattr(np, name, getattr(np, REMOVED_NUMPY_ALIASES[name]))
        try:
            from numba import cuda as numba_cuda

            with contextlib.suppress(ImportError):  # numba's own (older) CUDA target has no such module
                importlib.import_module("numba.cuda.np.arrayobj")
        finally:
            for name in missing:
                delattr(np, name)
        _complete_ufuncs()
        cuda = numba_cuda


def _complete_ufuncs() -> None:
    """Give numba-cuda's ufunc table the loops it types but lacks (0.30: ``np.floor`` and
    ``np.rint`` of float32 and float64, the device's ``floor`` and libdevice's ``rint``): so the
    noise's samplers, which round with them as the CPU kernels do, compile for the device from
    the same source. A numba-cuda with other internals is left as it is (its kernels then say so
    when they compile)."""
    try:
        from numba.cuda import libdevice, ufuncs
        from numba.cuda.np import npyfuncs
    except ImportError:  # numba's own older target, or another layout
        return

    def rint(context, builder, sig, args):  # NVVM rejects LLVM's rint: libdevice's
        fn = libdevice.rintf if str(sig.args[0]) == "float32" else libdevice.rint
        return context.compile_internal(builder, lambda x: fn(x), sig, args)

    table = ufuncs.ufunc_db()
    for uf, impl in ((np.floor, getattr(npyfuncs, "np_real_floor_impl", None)), (np.rint, rint)):
        if impl is not None and uf not in table:
            table[uf] = {"f->f": impl, "d->d": impl}


def _kernel_source(kernel: str | Callable) -> Callable:
    """The source CUDA kernel ``kernel`` (a name of
    [`CUDA_SOURCES`][layoutwarp.kernels.exact_cuda.CUDA_SOURCES], or a kernel function) compiles
    from: its module's ``cuda`` (a ``None`` placeholder there: importing numba.cuda costs a tenth
    of a second) bound to numba.cuda, and its compiled callees without numba's IR inlining
    ([`without_ir_inlining`][layoutwarp.kernels.base.without_ir_inlining]: NVVM inlines them, in
    a fifth of the compile time), made once per kernel."""
    _import_cuda()
    fn = CUDA_SOURCES[kernel] if isinstance(kernel, str) else kernel
    if fn not in _SOURCES:
        if fn.__globals__.get("cuda", cuda) is None:
            fn.__globals__["cuda"] = cuda
        _SOURCES[fn] = fn if simulated() else without_ir_inlining(fn)
    return _SOURCES[fn]


def cuda_ptx(
    kernel: str | Callable, dtype: str = "float32", cc: tuple[int, int] = (8, 0), signature: str | None = None
) -> str:
    """The PTX of CUDA kernel ``kernel`` for compute capability ``cc``, compiled without a GPU: a
    check that the kernels compile for the device, where no device is at hand. ``kernel``: a name
    of [`cuda_launch`][]'s (for images of ``dtype``, ``"float32"``/``"float64"``), or another
    module's kernel function with its argument types ``signature`` (numba's notation, e.g.
    ``"void(float64[:, ::1], int64)"``). Needs NVIDIA's numba-cuda target (``pip install
    "layoutwarp[cuda]"``; numba 0.68's built-in CUDA target does not type ``min``/``max`` of two
    floats in a kernel) with the CUDA toolkit's NVVM and NVRTC libraries."""
    if isinstance(kernel, str):
        if kernel not in CUDA_SOURCES:
            raise ValueError(f"kernel must be one of {', '.join(CUDA_SOURCES)}, got {kernel!r}")
        if dtype not in ("float32", "float64"):
            raise ValueError(f"dtype must be 'float32' or 'float64', got {dtype!r}")
        signature = cuda_signature(kernel, dtype)
    elif signature is None:
        raise ValueError("signature: a kernel function needs its argument types, e.g. 'void(float64[::1])'")
    source = _kernel_source(kernel)
    with _compiling_for(cc):
        ptx, _ = cuda.compile_ptx(source, signature, cc=cc)
    return ptx


@contextlib.contextmanager
def _compiling_for(cc: tuple[int, int]) -> Iterator[None]:
    """While it lasts, numba-cuda compiles device functions for ``cc``: it asks the current
    device for their compute capability (0.30, ``numba.cuda.dispatcher``), which a machine
    without a GPU has not, and the kernel's own ``cc`` is the answer [`cuda_ptx`][] wants."""
    module = importlib.import_module("numba.cuda.dispatcher") if cuda is not None else None
    if module is None or not hasattr(module, "get_current_device"):
        yield
        return
    asked = module.get_current_device
    module.get_current_device = lambda: types.SimpleNamespace(compute_capability=cc)
    try:
        yield
    finally:
        module.get_current_device = asked


def cuda_launch(name: str | Callable, count: int, stream: int, *args) -> None:
    """Launch CUDA kernel ``name`` with one thread per item, ``count`` items, on the CUDA
    stream whose handle is ``stream`` (0: the default stream); ``name`` may also be another
    module's kernel source (a function of a source file, compiled on first use). The kernels, by
    name:
    ``"prefix_blocks"`` (items: row × block × channel) and ``"prefix_offsets"`` (row ×
    channel) build [`prefix_tables`][layoutwarp.kernels.prefix.prefix_tables]; ``"forward"``
    (segment) and ``"edge_sums"`` (pixel edge) do
    [`exact_forward`][layoutwarp.kernels.exact.exact_forward]; ``"backward"`` (segment) does
    [`exact_backward`][layoutwarp.kernels.exact.exact_backward], each step for step as on the
    CPU. Array arguments are torch CUDA tensors or numba device arrays (anything with
    ``__cuda_array_interface__``), read and written in place; the launch runs in the context of
    the device of the first torch tensor among them (a second GPU's tensors, as a ``torchrun``
    rank has them, launch on that GPU). Kernels compile on first use and are cached on disk. Each
    launch is counted in [`LAUNCHES`][]."""
    _import_cuda()
    if name not in _CUDA_KERNELS:
        _CUDA_KERNELS[name] = cuda.jit(cache=True)(_kernel_source(name))
        _announce_compile(_CUDA_KERNELS[name])
    if count == 0:
        return
    LAUNCHES[getattr(name, "__name__", name)] += 1
    index = next((a.device.index for a in args if getattr(a, "is_cuda", False)), None)
    blocks = (count + CUDA_THREADS - 1) // CUDA_THREADS
    key = _launch_key(name, index, args) if FAST_LAUNCH and not simulated() else None
    with cuda.gpus[index] if index and not simulated() else contextlib.nullcontext():
        if key is not None and key in _DIRECT:
            try:
                _direct_launch(_DIRECT[key], blocks, stream, args)
                return
            except Exception as err:  # marshalling refused before any launch: numba launches
                DIRECT_OFF.append(f"{type(err).__name__}: {err}"[:300])
                key = None
        arrays = [_device_array(a) for a in args]
        on = cuda.external_stream(stream) if stream else 0  # 0: the default stream, as numba takes it
        with warnings.catch_warnings():  # numba warns of low occupancy on small meshes
            warnings.filterwarnings("ignore", message=".*GPU under-utilization")
            _CUDA_KERNELS[name][blocks, CUDA_THREADS, on](*arrays)
        if key is not None:
            _remember_direct(key, _CUDA_KERNELS[name], arrays)


#: Whether [`cuda_launch`][] launches a kernel it has launched before with the same argument
#: types directly (the compiled function and its arguments' pointers, shapes and strides handed
#: to the driver), rather than through numba's dispatcher, which wraps every tensor in a device
#: array and types it again at every launch. ``LAYOUTWARP_CUDA_LAUNCH=numba`` turns it off.
FAST_LAUNCH = os.environ.get("LAYOUTWARP_CUDA_LAUNCH", "direct") != "numba"
_DIRECT: dict[tuple, object] = {}  # (kernel, device, argument kinds) → the compiled function
_STREAMS: dict[int, object] = {}  # stream handle → cuda.core's stream on it
_CONFIGS: dict[int, object] = {}  # blocks → cuda.core's launch configuration
#: Why the direct launch is off in this process (numba-cuda's internals differ); empty while on.
DIRECT_OFF: list[str] = []


def _launch_key(name: object, index: int | None, args: tuple) -> tuple | None:
    """What decides which compiled copy of kernel ``name`` its arguments launch, cheaply read:
    per argument, a tensor's dtype, rank and contiguity, a numba device array's dtype and rank,
    or the Python type of a number; ``None`` for any other argument (numba then launches it)."""
    if DIRECT_OFF:
        return None
    kinds: list[object] = [name, index]
    for a in args:
        if hasattr(a, "data_ptr"):
            kinds.append((a.dtype, a.dim(), a.is_contiguous()))
        elif getattr(a, "__cuda_ndarray__", False):
            kinds.append((a.dtype.str, a.ndim, "device array"))
        elif type(a) in (bool, int, float):
            kinds.append(type(a))
        else:
            return None
    return tuple(kinds)


def _remember_direct(key: tuple, dispatcher: object, arrays: list) -> None:
    """After numba launched ``dispatcher`` with ``arrays``: keep the compiled function it chose
    for launches of the same ``key`` ([`_launch_key`][]). Where numba-cuda's internals are not
    the ones this reads, the direct launch turns off for the process (numba launches as before)."""
    try:
        argtypes = tuple(dispatcher.typeof_pyval(a) for a in arrays)
        kernel = dispatcher.overloads.get(argtypes)
        if kernel is not None:
            _DIRECT[key] = kernel._codelibrary.get_cufunc().kernel
    except Exception as err:  # another numba-cuda: launch through its dispatcher
        DIRECT_OFF.append(f"{type(err).__name__}: {err}"[:300])


def _direct_params(args: tuple) -> list[object]:
    """Launch arguments marshalled as numba's dispatcher marshals them (numba-cuda 0.30,
    ``_Kernel._prepare_args``): an array as meminfo, parent, size, item size, data pointer,
    shape and strides in bytes; an integer as int64, a float as double, a bool as it is."""
    params: list[object] = []
    for a in args:
        if hasattr(a, "data_ptr"):
            size = a.element_size()
            params += (0, 0, a.numel(), size, a.data_ptr(), *a.shape, *(s * size for s in a.stride()))
        elif type(a) is bool:
            params.append(a)
        elif type(a) is int:
            params.append(ctypes.c_int64(a))
        elif type(a) is float:
            params.append(ctypes.c_double(a))
        else:  # a numba device array
            params += (0, 0, a.size, a.dtype.itemsize, a.device_ctypes_pointer.value, *a.shape, *a.strides)
    return params


def _direct_launch(function: object, blocks: int, stream: int, args: tuple) -> None:
    """Launch the compiled ``function`` on ``blocks`` blocks of [`CUDA_THREADS`][] threads on
    the stream with handle ``stream``, with ``args`` marshalled by [`_direct_params`][]."""
    from cuda.core import LaunchConfig, Stream, launch

    if stream not in _STREAMS:
        _STREAMS[stream] = Stream.from_handle(stream)
    if blocks not in _CONFIGS:
        _CONFIGS[blocks] = LaunchConfig(grid=blocks, block=CUDA_THREADS)
    launch(_STREAMS[stream], _CONFIGS[blocks], function, *_direct_params(args))


def host_mapped(n: int, device: torch.device) -> np.ndarray:
    """``n`` int64 zeros in page-locked host memory mapped into ``device``'s address space (in
    its context): a kernel there writes them directly (no copy launched; a CUDA graph's replays
    write them too), and the host reads them whenever it likes, without waiting (numba's
    simulator: a plain array). Kept for the life of the process by its callers."""
    _import_cuda()
    on_gpu = device.type == "cuda" and not simulated()
    with cuda.gpus[device.index or 0] if on_gpu else contextlib.nullcontext():
        out = cuda.mapped_array(n, dtype=np.int64)
    out[:] = 0
    return out


class Stamps:
    """Events that kernels report without the host waiting: each call that may report one takes
    a stamp ([`take`][layoutwarp.kernels.device.Stamps.take]), and a kernel that meets the event
    writes it to slot ``slot`` of ``status`` (page-locked host memory the device writes
    directly, [`host_mapped`][]). A captured CUDA graph's replays all write the stamp of the
    capture: [`news`][layoutwarp.kernels.device.Stamps.news] tells of the first,
    [`clear`][layoutwarp.kernels.device.Stamps.clear] of each."""

    def __init__(self, status: np.ndarray, slot: int) -> None:
        self.status, self.slot = status, slot
        self.taken = self.seen = 0

    def take(self) -> int:
        """The next call's stamp (0, which no call takes, is no report)."""
        self.taken += 1
        return self.taken

    def news(self) -> bool:
        """Whether a stamp not seen before was written, without waiting for the device."""
        stamp = int(self.status[self.slot])
        news, self.seen = stamp > self.seen, max(stamp, self.seen)
        return news

    def clear(self) -> bool:
        """Whether any stamp was written since the last clear; then clear it (once the device is
        idle: nothing writes it meanwhile)."""
        written = int(self.status[self.slot]) != 0
        self.status[self.slot] = self.seen = 0
        return written


class DeviceChecks(Stamps):
    """The NaN and Inf checks of one device's kernels, answered on the device: a checked launch
    takes a stamp and a kernel that meets a value that is not finite writes it ([`Stamps`][]);
    the next checked call raises ([`look`][layoutwarp.kernels.device.DeviceChecks.look]), or
    [`device_status`][layoutwarp.kernels.mesh.device_status] tells at once."""

    def __init__(self, device: torch.device) -> None:
        super().__init__(host_mapped(1, device), 0)

    def look(self) -> None:
        """Raise a one-line ``ValueError`` where a checked call met NaN or Inf since the host last
        looked."""
        if self.news():
            raise ValueError(
                "the input of an earlier call on the device held NaN or Inf (found there, read back now); "
                "clean it or pass allow_nonfinite=True"
            )


#: Every device's [`DeviceChecks`][], by device.
CHECKS: dict[str, DeviceChecks] = {}


def device_checks(device: torch.device) -> DeviceChecks:
    """``device``'s [`DeviceChecks`][] (made at its first checked call)."""
    key = str(device)
    if key not in CHECKS:
        CHECKS[key] = DeviceChecks(device)
    return CHECKS[key]


def _device_array(a: object) -> object:
    """A launch argument as numba takes it: a device array for anything with
    ``__cuda_array_interface__``, a CPU tensor's numpy view (the simulator's arrays), else as is.
    Tensors are detached first: a kernel reads and writes their memory, never their graph (torch
    refuses ``__cuda_array_interface__`` on a tensor that requires grad, such as an output saved
    for the backward)."""
    if hasattr(a, "detach"):  # a torch tensor (torch is imported only where it is used)
        a = a.detach()
        if a.device.type == "cpu":
            return a.numpy()
    return cuda.as_cuda_array(a) if hasattr(type(a), "__cuda_array_interface__") else a


_ANNOUNCED: list[bool] = []


def _announce_compile(kernel: object) -> None:
    """Say once per process, in one line, that the CUDA kernels compile, when the first kernel
    without a compiled copy in numba's disk cache is about to (a learnable step's kernels compile
    in about ten seconds, then load from the cache in any later process)."""
    if _ANNOUNCED or simulated():
        return
    index = getattr(getattr(getattr(kernel, "_cache", None), "_cache_file", None), "_index_path", None)
    if index is not None and not os.path.exists(index):
        _ANNOUNCED.append(True)
        print(
            "layoutwarp: compiling the CUDA kernels for this GPU (seconds; once per installation; "
            "see layoutwarp doctor)",
            file=sys.stderr,
            flush=True,
        )


def cuda_available(dtype: str = "float32") -> bool:
    """Whether the CUDA kernels run here for images of ``dtype`` (``"float32"``/``"float64"``):
    numba's CUDA target imports, sees a GPU, and compiles and runs all its kernels on a
    one-pixel mesh (checked once per dtype; a failure warns once, and the caller falls back to
    the torch reference)."""
    if dtype not in _CUDA_OK:
        _CUDA_OK[dtype] = _cuda_smoke_test(dtype)
    return _CUDA_OK[dtype]


def cuda_checked() -> dict[str, bool]:
    """What [`cuda_available`][] found so far in this process, per dtype (nothing compiled)."""
    return dict(_CUDA_OK)


def _cuda_smoke_test(dtype: str) -> bool:
    try:
        _import_cuda()
        if njit is None or not cuda.is_available():
            return False
        dev = cuda.to_device
        image = dev(np.full((1, 2, 2), 0.25, dtype=dtype))
        verts = dev(np.array([[0.5, 0.5], [1.5, 0.5], [1.5, 1.5], [0.5, 1.5]]))
        seg_start, seg_end = dev(np.arange(4)), dev((np.arange(4) + 1) % 4)
        seg_edge, edge_offsets = dev(np.zeros(4, dtype=np.int64)), dev(np.array([0, 4]))
        incl = cuda.device_array((2, 2, 1), dtype=dtype)
        offsets = cuda.device_array((2, 1, 1), dtype=np.float64)
        per_seg = dev(np.zeros((4, 2)))
        out, wa, wb = dev(np.zeros((2, 1))), dev(np.zeros(4)), dev(np.zeros(4))
        cuda_launch("prefix_blocks", 2, 0, image, BLOCK, incl)
        cuda_launch("prefix_offsets", 2, 0, BLOCK, incl, offsets)
        cuda_launch("forward", 4, 0, verts, seg_start, seg_end, incl, offsets, BLOCK, per_seg)
        cuda_launch("edge_sums", 1, 0, per_seg, edge_offsets, out)
        cuda_launch("backward", 4, 0, verts, seg_start, seg_end, seg_edge, incl, BLOCK, out, wa, wb)
        total = out.copy_to_host()
        if not np.allclose(total[:, 0], [0.25, 1.0]):  # ∮ P dY = ∬ L, ∮ X dY = the area
            raise RuntimeError(f"a one-pixel test integral came out {total[:, 0]}, not [0.25, 1]")
        return True
    except Exception as err:  # any failure of an optional accelerator means: use the fallback
        hint = ""
        if getattr(cuda, "implementation", "") == "Built-in":  # numba's own, deprecated target
            hint = "; NVIDIA's numba-cuda compiles them: pip install 'layoutwarp[cuda]'"
        warnings.warn(
            f"layoutwarp: numba's CUDA kernels do not run here ({type(err).__name__}: "
            f"{' '.join(str(err).split())}); "
            f"the exact integrator uses its torch path on CUDA{hint}",
            RuntimeWarning,
            stacklevel=3,
        )
        return False
