"""The sensor's measurement in one fused pass over the sensor image: photon (shot) noise drawn
from counter-based streams (Poisson, exact; a normal ziggurat: [`layoutwarp.kernels.samplers`][]),
fixed-pattern noise, read noise, full well and the ADC ([`sensor_measure`][]), for
[`layoutwarp.measurement`][]."""

from __future__ import annotations

import math

import numpy as np

from .base import inline, own, per_thread, run_shares, serial
from .device import cuda_launch
from .samplers import ELEMENT_G, STREAM_G, first_tries, normal, poisson, stream_origin

try:  # numba's own code generator, present wherever numba is
    from llvmlite import ir as llvm_ir
    from numba import types as numba_types
    from numba.extending import intrinsic
except ImportError:  # pragma: no cover - depends on the environment
    llvm_ir = numba_types = intrinsic = None

__all__ = [
    "CUDA_KERNELS",
    "MEASURE_CHUNK",
    "measure_on_device",
    "measured_value",
    "sensor_measure",
    "sensor_measure_plain",
]

#: Pixels per work item of `sensor_measure` (a run of pixels through every plane).
MEASURE_CHUNK = 512


if intrinsic is not None:

    @intrinsic
    def _prefetch(typingctx, array, index):
        """A hint to fetch the cache line of ``array[index]`` (a 1-d array) ahead of its use:
        LLVM's ``prefetch`` (a read, kept in every cache level), which loads nothing into a register
        and never faults, so an index past the end is harmless."""
        if not (isinstance(array, numba_types.Array) and array.ndim == 1):
            return None

        def codegen(context, builder, signature, args):
            view = context.make_array(signature.args[0])(context, builder, args[0])
            offset = builder.mul(args[1], builder.extract_value(view.strides, 0))  # in bytes
            ptr = builder.gep(builder.bitcast(view.data, llvm_ir.IntType(8).as_pointer()), [offset])
            i32 = llvm_ir.IntType(32)
            fnty = llvm_ir.FunctionType(llvm_ir.VoidType(), [ptr.type, i32, i32, i32])
            fn = builder.module.declare_intrinsic("llvm.prefetch", [ptr.type], fnty)
            builder.call(fn, [ptr, i32(0), i32(3), i32(1)])  # read, all levels, data
            return context.get_dummy_value()

        return numba_types.void(array, numba_types.intp), codegen

else:  # pragma: no cover - without numba the kernels are not compiled

    def _prefetch(array: np.ndarray, index: int) -> None:
        pass


@inline
def _prefetch_span(array: np.ndarray, lo: int, hi: int) -> None:
    """[`_prefetch`][] of every 64-byte line of ``array[lo:hi]``."""
    for i in range(lo, hi, max(1, 64 // array.itemsize)):
        _prefetch(array, i)


@inline
def _recorded(e: float, full: float, zero: float, inv: float, params: np.ndarray, output: int) -> float:
    """Electrons ``e`` of a pixel after its full well ``full``, as ``output`` asks (0: the ISP's
    radiance ``(DN − zero)·inv``, 1: electrons, 2: DN), the ADC rounding half to even like
    ``torch.round``."""
    gain, black, top = params[7], params[8], params[9]
    e = min(e, full)
    dn = gain * e + black
    dn = min(max(np.rint(dn), 0.0), top) if top < np.inf else dn
    return e if output == 1 else (dn if output == 2 else (dn - zero) * inv)


@inline
def _pixel_constants(a: float, params: np.ndarray) -> tuple[float, float, float, float, float]:
    """A pixel of ``a`` µm²'s electrons per unit mean, dark electrons and full well, and the ISP's
    offset and reciprocal gain (before the fixed patterns): the one formula of the main loop and
    the rescan of `sensor_measure`."""
    light, eta, dark_um2 = params[0], params[1], params[4]
    full_um2, gain, black = params[6], params[7], params[8]
    zero = black + gain * dark_um2 * a  # the ISP subtracts the mean dark signal ...
    inv = 1.0 / (gain * eta * light * a)  # ... and divides by the nominal response
    return eta * light * a, dark_um2 * a, full_um2 * a, zero, inv


@inline
def _noisy_run(
    row: np.ndarray, flags: np.ndarray, pix: np.ndarray, params: np.ndarray, key: np.uint64, poisson: bool,
    read: float, output: int,
) -> None:  # fmt: skip
    """[`_measure_run`][] with noise, Poisson or Gaussian: each draw's first try
    ([`first_tries`][]), ``flags[j]`` set where one was rejected and that element's mean left
    in ``row`` for the rescan. Called with ``poisson`` a constant, so each kind of noise gets a
    loop of its own with no test of it inside."""
    scale, dark, full, zero, inv = pix[0], pix[1], pix[2], pix[3], pix[4]
    for j in range(row.size):
        mean = row[j]
        e = mean * scale[j] + dark[j]
        shot_key = key + np.uint64(j) * ELEMENT_G
        mu = max(e, 0.0)
        k, g, z2, ok_z1, ok_k, ok_z2 = first_tries(mu, shot_key, shot_key + STREAM_G)
        shot = k if poisson else (g if e >= 0.0 else e)  # Gaussian: e + √max(e, 0)·z, bit for bit
        flag = (not (ok_z1 and (ok_k or not poisson))) | (not ok_z2 and read != 0.0)
        flags[j] = flag
        value = _recorded(shot + read * z2, full[j], zero[j], inv[j], params, output)
        row[j] = mean if flag else value


@inline
def _measure_run(
    row: np.ndarray, flags: np.ndarray, pix: np.ndarray, params: np.ndarray, key: np.uint64, noise: int,
    read: float, output: int,
) -> None:  # fmt: skip
    """One plane of a run of `sensor_measure`: the means ``row`` measured in place, ``pix`` the
    run's pixel constants ``(5, ≥ len(row))`` (scale, dark, full well, zero, reciprocal gain:
    [`_pixel_constants`][]), ``key`` the first element's shot stream. Without noise a loop with
    no draws; with noise [`_noisy_run`][]. Each loop is branch-free and vectorises."""
    if noise == 0:
        scale, dark, full, zero, inv = pix[0], pix[1], pix[2], pix[3], pix[4]
        for j in range(row.size):
            e = row[j] * scale[j] + dark[j]
            row[j] = _recorded(e, full[j], zero[j], inv[j], params, output)
    elif noise == 1:
        _noisy_run(row, flags, pix, params, key, True, read, output)
    else:
        _noisy_run(row, flags, pix, params, key, False, read, output)


@inline
def measured_value(
    mean: float, i: int, j: int, area_um2: np.ndarray, prnu: np.ndarray, dsnu: np.ndarray, params: np.ndarray,
    origin: np.uint64, noise: int, output: int,
) -> float:  # fmt: skip
    """Element ``i`` (row-major over planes × pixels) of [`sensor_measure`][], of mean ``mean``
    at pixel ``j`` (its area ``area_um2[j]``, its fixed patterns ``prnu[j]``/``dsnu[j]``, read only
    where their gains are not 0), by the full samplers alone: the CPU kernel's rescan of the
    elements whose first tries were rejected (the first tries are the full samplers' first steps:
    the same draws) and the CUDA kernels' every element (the arithmetic is the same; the device's
    ``exp``/``log`` may round a rare rejection test's last digit otherwise)."""
    sc, dk, fw, zr, iv = _pixel_constants(area_um2[j], params)
    if params[2] != 0.0:
        sc = sc * (1.0 + params[2] * prnu[j])
    if params[3] != 0.0:
        dk = dk + params[3] * dsnu[j]
    e = mean * sc + dk
    if noise == 0:
        return _recorded(e, fw, zr, iv, params, output)
    key = origin + np.uint64(i) * ELEMENT_G
    mu = max(e, 0.0)
    if noise == 1:
        shot, _ = poisson(mu, key)
    else:
        z, _ = normal(key)
        shot = e + math.sqrt(mu) * z
    read = params[5]
    z2 = 0.0
    if read != 0.0:
        z2, _ = normal(key + STREAM_G)
    return _recorded(shot + read * z2, fw, zr, iv, params, output)


@serial
def _prefetch_inputs(
    mean: np.ndarray,
    area_um2: np.ndarray,
    prnu: np.ndarray,
    dsnu: np.ndarray,
    params: np.ndarray,
    lo: int,
    hi: int,
) -> None:
    """[`_prefetch_span`][] of `sensor_measure`'s inputs at the pixels ``[lo, hi)``: the
    means of every plane, the areas and the fixed patterns it reads."""
    _prefetch_span(area_um2, lo, hi)
    if params[2] != 0.0:
        _prefetch_span(prnu, lo, hi)
    if params[3] != 0.0:
        _prefetch_span(dsnu, lo, hi)
    for r in range(mean.shape[0]):
        _prefetch_span(mean[r], lo, hi)


@serial
def _measure_share(
    t: int, nt: int, mean: np.ndarray, area_um2: np.ndarray, prnu: np.ndarray, dsnu: np.ndarray,
    params: np.ndarray, seed: int, noise: int, output: int, out: np.ndarray, consts: np.ndarray,
    all_words: np.ndarray,
) -> None:  # fmt: skip
    """Share ``t`` of ``nt`` of [`sensor_measure`][], with its rows of the work space: a run's pixel
    constants ``consts`` ``(T, 5, MEASURE_CHUNK)`` and the flags ``all_words`` ``(T, ⌈N·share/8⌉)``
    (zeroed; none without noise)."""
    g_prnu, g_dsnu, read = params[2], params[3], params[5]
    n, p = mean.shape
    state0 = stream_origin(seed)
    in_place = out.ctypes.data == mean.ctypes.data
    c = MEASURE_CHUNK
    mine = own(consts, t, nt)
    scale, dark, full, zero, inv = mine[0], mine[1], mine[2], mine[3], mine[4]
    start, stop = t * p // nt, (t + 1) * p // nt
    share = stop - start
    words = own(all_words, t, nt)[: (n * share + 7) // 8 if noise != 0 else 0]
    redo = words.view(np.uint8)  # element (r, start + j)'s flag at r·share + j: 1 to rerun
    _prefetch_inputs(mean, area_um2, prnu, dsnu, params, start, min(stop, start + 2 * c))
    for lo in range(start, stop, MEASURE_CHUNK):
        m = min(stop, lo + MEASURE_CHUNK) - lo
        _prefetch_inputs(mean, area_um2, prnu, dsnu, params, lo + 2 * c, min(stop, lo + 3 * c))
        for j in range(m):  # the run's pixels' constants
            scale[j], dark[j], full[j], zero[j], inv[j] = _pixel_constants(area_um2[lo + j], params)
        if g_prnu != 0.0:  # the fixed patterns in loops of their own: the one above vectorises
            for j in range(m):
                scale[j] = scale[j] * (1.0 + g_prnu * prnu[lo + j])
        if g_dsnu != 0.0:
            for j in range(m):
                dark[j] = dark[j] + g_dsnu * dsnu[lo + j]
        for r in range(n):
            row = out[r, lo : lo + m]  # 1-d: 1.5x the 2-d stores
            if not in_place:  # measured where they are written: no overlap check, one loop
                for j in range(m):
                    row[j] = mean[r, lo + j]
            flags = redo[r * share + lo - start : r * share + lo - start + m]
            key = state0 + np.uint64(r * p + lo) * ELEMENT_G  # the run's first shot stream
            _measure_run(row, flags, mine, params, key, noise, read, output)
    for b in range(words.size):  # the rescan
        if words[b] == 0:
            continue
        for f in range(8 * b, min(n * share, 8 * b + 8)):
            if redo[f] == 0:
                continue
            r, i = f // share, start + f % share  # its mean was left where it was
            out[r, i] = measured_value(
                mean[r, i], r * p + i, i, area_um2, prnu, dsnu, params, state0, noise, output
            )


@serial
def _plain_share(
    t: int, nt: int, mean: np.ndarray, area_um2: np.ndarray, prnu: np.ndarray, dsnu: np.ndarray,
    params: np.ndarray, seed: int, noise: int, output: int, out: np.ndarray,
) -> None:  # fmt: skip
    """Pixels ``t·P/T ..`` of [`sensor_measure_plain`][] (its arguments), every plane."""
    n, p = mean.shape
    origin = stream_origin(seed)
    for r in range(n):
        for i in range(t * p // nt, (t + 1) * p // nt):
            out[r, i] = measured_value(
                mean[r, i], r * p + i, i, area_um2, prnu, dsnu, params, origin, noise, output
            )


def sensor_measure_plain(*args: object) -> None:
    """[`sensor_measure`][]'s values, bit for bit, element by element from the full samplers
    ([`measured_value`][], as the CUDA kernels draw them): no first tries in vectorised runs, no
    prefetching, so it compiles in a fraction of the time (2–3 s from an empty cache, where
    `sensor_measure` takes 10–15 s) and runs slower. What a process measures with while
    `sensor_measure` compiles (see [`layoutwarp.jit.compiled`][]). Its arguments are
    `sensor_measure`'s."""
    run_shares(_plain_share, int(args[-1]), *args[:-1])


def sensor_measure(
    mean: np.ndarray,
    area_um2: np.ndarray,
    prnu: np.ndarray,
    dsnu: np.ndarray,
    params: np.ndarray,
    seed: int,
    noise: int,
    output: int,
    out: np.ndarray,
    threads: int,
) -> None:
    """[`layoutwarp.measurement.measure`][] in one pass: means ``(N, P)`` to ``out`` ``(N, P)``, of
    their dtype, which may be ``mean`` itself (measured in place, one buffer less; no other
    overlap).

    ``params``: photons per µm² × fill factor, η, PRNU, DSNU, dark e⁻/µm², read noise, full well
    per µm² (``inf``: none), gain K, black level, ADC top (``inf``: no ADC); ``prnu``/``dsnu``
    are read only where their gains are not 0 (empty arrays will do). ``noise``: 0 none,
    1 Poisson, 2 Gaussian; ``output``: 0 radiance, 1 electrons, 2 DN. Element ``i`` (row-major)
    draws its shot noise and its read noise from two streams of its own, disjoint blocks of one
    SplitMix64 sequence seeded by ``seed``
    ([`ELEMENT_G`][layoutwarp.kernels.samplers.ELEMENT_G]), so the result does not depend on the
    thread count.

    Thread ``t`` of ``threads`` (see [`run_shares`][layoutwarp.kernels.base.run_shares]) takes the
    pixels ``[t·P/T, (t + 1)·P/T)``,
    the share of the rows that the same thread had in the forward just before, in
    runs of [`MEASURE_CHUNK`][] pixels through all ``N`` planes, with work space of its own. The
    forward's streams (tens of MB) push most of its output out of the caches, so the thread first
    hints its first two runs' inputs to the caches, and each run those of the run after next
    ([`_prefetch_inputs`][]). A run then derives its pixels' constants
    ([`_pixel_constants`][], then the fixed patterns). Per plane, its means copied to ``out``
    first where that is another buffer (so every loop works in place, with no overlap to test), a
    branch-free loop ([`_measure_run`][]) takes every draw's first try and flags the elements
    where one was rejected (about 0.4 % of the normals, a few tenths of a percent of the Poisson
    draws at large means, all of them below a mean of 10 electrons), which keep their means. After
    its last run the thread rescans its flags, eight a word, and measures those elements again with
    the full samplers from the start of their streams ([`measured_value`][]): the rare slow path
    in one tight loop, whose code and branch history stay warm (a rescan after every run made the
    kernel 5–25 % slower).
    """
    n, p = mean.shape
    consts = per_thread(threads, (5, MEASURE_CHUNK))
    words = per_thread(threads, ((n * -(-p // threads) + 7) // 8 if noise != 0 else 0,), np.uint64)
    words[:] = 0
    args = (mean, area_um2, prnu, dsnu, params, seed, noise, output, out, consts, words)
    run_shares(_measure_share, threads, *args)


# ----------------------------------------------------------------------------------------
# CUDA: one thread per element, the full samplers
# ----------------------------------------------------------------------------------------
cuda = None  # numba.cuda, bound by the first launch ([`layoutwarp.kernels.device.cuda_launch`][])


def _cuda_measure(
    mean: np.ndarray, area_um2: np.ndarray, prnu: np.ndarray, dsnu: np.ndarray, params: np.ndarray, seed: int,
    noise: int, output: int, out: np.ndarray,
) -> None:  # fmt: skip
    """One thread per element of ``mean`` ``(N, P)``: [`measured_value`][] into ``out`` (which may
    be ``mean``): [`sensor_measure`][] on a CUDA device, one launch."""
    i = cuda.grid(1)
    n, p = mean.shape
    if i < n * p:
        r, j = i // p, i % p
        origin = stream_origin(seed)
        out[r, j] = measured_value(mean[r, j], i, j, area_um2, prnu, dsnu, params, origin, noise, output)


_A1, _A2 = "float64[::1]", "float32[:, ::1]"
#: The CUDA kernels of this file with their argument types (for
#: [`cuda_ptx`][layoutwarp.kernels.device.cuda_ptx], float32 means).
CUDA_KERNELS = {
    "measure": (_cuda_measure, f"void({_A2}, {_A1}, {_A1}, {_A1}, {_A1}, int64, int64, int64, {_A2})"),
}


def measure_on_device(
    mean: object, area_um2: object, prnu: object, dsnu: object, params: object, seed: int, noise: int,
    output: int, out: object, stream: int,
) -> None:  # fmt: skip
    """[`sensor_measure`][] of ``mean`` ``(N, P)`` into ``out`` on a CUDA device (or in the
    simulator): one launch on ``stream``, one thread per element; the pixel inputs as tensors
    there (see [`layoutwarp.measurement.device_arguments`][])."""
    args = (mean, area_um2, prnu, dsnu, params, int(seed), int(noise), int(output), out)
    cuda_launch(_cuda_measure, mean.shape[0] * mean.shape[1], stream, *args)
