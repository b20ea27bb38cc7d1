"""The fixed-layout product: a CSR matrix of area weights times the image's planes, alone or with
the sensor's measurement fused after it."""

from __future__ import annotations

import math

import numpy as np

from .base import inline, run_shares, serial
from .device import cuda_launch, device_checks
from .noise import measured_value, sensor_measure, stream_origin

__all__ = ["CUDA_KERNELS", "csr_apply", "csr_apply_on_device", "measured_csr_apply"]


@inline
def _csr_row(lo: int, hi: int, indices: np.ndarray, data: np.ndarray, x: np.ndarray, k: int, m: int):
    """One CSR row's products with planes ``k .. k + m − 1`` (``m ≤ 4``) in one pass over the row,
    in float64 (a pixel's sum stays within an ulp or two of its values); unused sums are 0."""
    a0 = a1 = a2 = a3 = np.float64(0.0)  # float64 also as plain Python (numpy: 0.0 + float32 is float32)
    if m == 4:
        for j in range(lo, hi):
            w, c = data[j], indices[j]
            a0 += w * x[k, c]
            a1 += w * x[k + 1, c]
            a2 += w * x[k + 2, c]
            a3 += w * x[k + 3, c]
    elif m == 3:
        for j in range(lo, hi):
            w, c = data[j], indices[j]
            a0 += w * x[k, c]
            a1 += w * x[k + 1, c]
            a2 += w * x[k + 2, c]
    elif m == 2:
        for j in range(lo, hi):
            w, c = data[j], indices[j]
            a0 += w * x[k, c]
            a1 += w * x[k + 1, c]
    else:
        for j in range(lo, hi):
            a0 += data[j] * x[k, indices[j]]
    return a0, a1, a2, a3


@serial
def _csr_share(
    t: int, nt: int, indptr: np.ndarray, indices: np.ndarray, data: np.ndarray, x: np.ndarray, out: np.ndarray
) -> int:
    """Rows ``t·R/T ..`` of [`csr_apply`][]; returns how many of the values it wrote are not finite."""
    n, rows = x.shape[0], indptr.shape[0] - 1
    bad = 0
    for r in range(t * rows // nt, (t + 1) * rows // nt):
        lo, hi = indptr[r], indptr[r + 1]
        for k in range(0, n, 4):
            m = min(4, n - k)
            sums = _csr_row(lo, hi, indices, data, x, k, m)
            for q in range(m):
                out[k + q, r] = sums[q]
                if not np.isfinite(out[k + q, r]):
                    bad += 1
    return bad


def csr_apply(
    indptr: np.ndarray, indices: np.ndarray, data: np.ndarray, x: np.ndarray, out: np.ndarray,
    threads: int = 1,
) -> int:  # fmt: skip
    """``out[n] = W @ x[n]`` for a CSR matrix ``W`` (``(R, M)``) and planes ``x`` ``(N, M)`` (the
    fixed-layout area weights of [`AreaResampler`][layoutwarp.resampler.AreaResampler]), a band of rows
    to each of ``threads``: each row of ``W`` is read once for every four planes (RGB: once; 2.3x
    faster than once per plane at 2048x1024 → 257x129). Returns how many of the values written are
    not finite (NaN or ±inf): the finiteness check of [`simulate`][layoutwarp.sensor.simulate] while
    they are in registers (a pass over ``out`` afterwards cost about 3 % of the call)."""
    return sum(run_shares(_csr_share, threads, indptr, indices, data, x, out))


def measured_csr_apply(
    indptr: np.ndarray, indices: np.ndarray, data: np.ndarray, x: np.ndarray, mean: np.ndarray, *measure
) -> int:
    """[`csr_apply`][] into ``mean``, then
    [`sensor_measure`][layoutwarp.kernels.noise.sensor_measure] of ``mean`` with its other
    arguments ``measure`` (``area_um2, …, out, threads``): a fixed layout's exact forward with
    sensor physics. Returns [`csr_apply`][]'s count of non-finite means (the measurement passes
    NaN and ±inf through)."""
    bad = csr_apply(indptr, indices, data, x, mean, measure[-1])
    sensor_measure(mean, *measure)
    return bad


# ----------------------------------------------------------------------------------------
# CUDA: one thread per row, every plane, the measurement fused
# ----------------------------------------------------------------------------------------
cuda = None  # numba.cuda, bound by the first launch ([`layoutwarp.kernels.device.cuda_launch`][])


def _cuda_csr_apply(
    indptr: np.ndarray, indices: np.ndarray, data: np.ndarray, x: np.ndarray, out: np.ndarray,
    area_um2: np.ndarray, prnu: np.ndarray, dsnu: np.ndarray, params: np.ndarray, seed: int, noise: int,
    output: int, measure: bool, checks: np.ndarray, stamp: int,
) -> None:  # fmt: skip
    """One thread per row of ``W``: [`csr_apply`][]'s sums for every plane (read once per four
    planes), written to ``out`` ``(N, R)``, and with ``measure`` then measured
    ([`measured_value`][layoutwarp.kernels.noise.measured_value], from the value as ``out``'s
    dtype holds it, as [`measured_csr_apply`][] measures its buffer): a fixed layout's forward,
    with the sensor's measurement, in one launch on a CUDA device. ``area_um2``, ``prnu``,
    ``dsnu``, ``params``, ``seed``, ``noise``, ``output``: as
    [`sensor_measure`][layoutwarp.kernels.noise.sensor_measure] takes them (read only with
    ``measure``). A sum that is NaN or ±inf writes ``stamp`` to ``checks[0]`` (0: no check;
    [`DeviceChecks`][layoutwarp.kernels.device.DeviceChecks])."""
    r = cuda.grid(1)
    rows = indptr.shape[0] - 1
    if r < rows:
        n = x.shape[0]
        lo, hi = indptr[r], indptr[r + 1]
        for k in range(0, n, 4):
            m = min(4, n - k)
            sums = _csr_row(lo, hi, indices, data, x, k, m)
            for q in range(m):
                out[k + q, r] = sums[q]
                if stamp and not math.isfinite(sums[q]):
                    checks[0] = stamp
                if measure:  # from the mean as the buffer holds it, as the CPU measures its buffer
                    i, origin = (k + q) * rows + r, stream_origin(seed)
                    out[k + q, r] = measured_value(
                        out[k + q, r], i, r, area_um2, prnu, dsnu, params, origin, noise, output
                    )


_F1, _I1, _F2 = "float64[::1]", "int64[::1]", "float32[:, ::1]"
#: The CUDA kernels of this file with their argument types (for
#: [`cuda_ptx`][layoutwarp.kernels.device.cuda_ptx]: float32 weights and images).
CUDA_KERNELS = {
    "csr_apply": (
        _cuda_csr_apply,
        f"void({_I1}, {_I1}, float32[::1], {_F2}, {_F2}, {_F1}, {_F1}, {_F1}, {_F1}, int64, int64, int64, "
        f"boolean, {_I1}, int64)",
    ),
}


def csr_apply_on_device(
    indptr, indices, data, x, out, measured: tuple, measure: bool, stream: int, check: bool = False
) -> None:
    """[`csr_apply`][] on a CUDA device (or in the simulator), one launch on ``stream``: the CSR
    arrays, the planes ``x`` ``(N, M)`` and ``out`` ``(N, R)`` as tensors there; with
    ``measure``, the means then measured with ``measured`` ``(area_um2, prnu, dsnu, params, seed,
    noise, output)`` as [`measure_on_device`][layoutwarp.kernels.noise.measure_on_device] takes
    them (without, any arrays of float64 will do: they are not read). With ``check``, a sum that
    is NaN or ±inf raises when the host next looks
    ([`DeviceChecks`][layoutwarp.kernels.device.DeviceChecks]; look before the call)."""
    area_um2, prnu, dsnu, params, seed, noise, output = measured
    args = (indptr, indices, data, x, out, area_um2, prnu, dsnu, params, int(seed), int(noise), int(output))
    checks = device_checks(x.device)
    cuda_launch(_cuda_csr_apply, indptr.shape[0] - 1, stream, *args, bool(measure), checks.status,
                checks.take() if check else 0)  # fmt: skip
