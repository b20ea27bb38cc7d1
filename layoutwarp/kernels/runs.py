"""The fixed-layout product: a fixed layout's area weights stored as runs of source cells, applied
to an image in one pass over each pixel's cells, alone or with the sensor's measurement fused after
it.

A source cell wholly inside a sensor pixel weighs ``1 / area`` of that pixel; a cell that a pixel
boundary cuts weighs the share of the pixel's area inside it. A run is the cells of one pixel in
one source row, contiguous: its first ``head`` and last ``tail`` cells are cut (their weights
stored, in order), the cells between them whole (summed, then scaled once by ``1 / area``). At
2048x1024 → 257x129 a pixel spans about 8x8 cells: about 300 000 runs of 9 cells, 1.2 million of
their cells cut; the runs and weights take 1.24x the bytes of one float32 plane of the image (a
CSR matrix of the same weights: 2.6x).

The arrays, for ``R`` pixels (row-major sensor index):

- ``pix_runs`` ``(R + 1,)`` int64: pixel ``k``'s runs are ``pix_runs[k] .. pix_runs[k + 1]``;
- ``run_start``, ``run_len``, ``run_head``, ``run_tail`` ``(runs,)`` int32: a run's first cell
  (``row · W + col``), its length and its cut cells at each end;
- ``inv_area`` ``(R,)`` float64: a whole cell's weight in pixel ``k``;
- ``pix_cuts`` ``(R + 1,)`` int64 and ``cut_weight`` ``(cuts,)`` float32: the weights of pixel
  ``k``'s cut cells, run by run, head before tail.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from .base import inline, run_chunks, serial, take, tries
from .device import cuda_launch, device_checks
from .noise import measured_value, sensor_measure
from .samplers import stream_origin

if TYPE_CHECKING:
    import scipy.sparse

__all__ = ["CUDA_KERNELS", "WHOLE", "Runs", "measured_runs_apply", "runs_apply", "runs_apply_on_device"]

#: A cell whose weight is within this of ``1 / area`` (relatively) is whole (both builds of the
#: runs, [`Runs.of`][] and [`build_runs`][layoutwarp.kernels.weights.build_runs], tell them so).
WHOLE = 1e-9


@inline
def _cut_sums(xp, xq, xr, cut_weight, o, c, end, a0, a1, a2):
    """The cut cells ``c .. end`` of three planes' rows, their weights from ``cut_weight[o]`` on,
    added to the sums ``a0``, ``a1``, ``a2``; returns the sums and ``o`` and ``c`` moved past them."""
    one = np.uint64(1)
    while c < end:
        w = np.float64(cut_weight[o])
        a0 += w * xp[c]
        a1 += w * xq[c]
        a2 += w * xr[c]
        o, c = o + one, c + one
    return a0, a1, a2, o, c


def _pixel_sums(
    k, pix_runs, run_start, run_len, run_head, run_tail, inv_area, pix_cuts, cut_weight, x, p, q, r
):
    """Pixel ``k``'s means of planes ``p``, ``q`` and ``r`` (three planes at once: an RGB image's
    cells are read in one pass; a plane may repeat) in one pass over its runs, summed in float64.
    The planes are read as rows of their own by unsigned indices: no test for a negative index
    at each read (the product 1.2-1.3x faster than with ``x[p, c]`` and a signed ``c``)."""
    xp, xq, xr, one = x[p], x[q], x[r], np.uint64(1)
    a0 = a1 = a2 = np.float64(0.0)  # the cut cells' weighted sums
    b0 = b1 = b2 = np.float64(0.0)  # the whole cells' sums
    o = np.uint64(pix_cuts[k])
    for j in range(pix_runs[k], pix_runs[k + 1]):
        c = np.uint64(run_start[j])
        e = c + np.uint64(run_len[j])
        h, t = c + np.uint64(run_head[j]), e - np.uint64(run_tail[j])
        a0, a1, a2, o, c = _cut_sums(xp, xq, xr, cut_weight, o, c, h, a0, a1, a2)
        while c < t:
            b0 += xp[c]
            b1 += xq[c]
            b2 += xr[c]
            c += one
        a0, a1, a2, o, c = _cut_sums(xp, xq, xr, cut_weight, o, c, e, a0, a1, a2)
    v = inv_area[k]
    return a0 + b0 * v, a1 + b1 * v, a2 + b2 * v


_pixel_sums = inline(_pixel_sums)


@inline
def _pixel_out(
    k, pix_runs, run_start, run_len, run_head, run_tail, inv_area, pix_cuts, cut_weight, x, out, p
):
    """Pixel ``k``'s means of planes ``p .. p + 2`` of ``x`` (fewer where fewer are left), written to
    ``out[p:p + 3, k]``; returns how many of them are not finite. One or two planes left are read
    as three, the last again: the same sums bit for bit, in one loop for every plane count."""
    n = x.shape[0]
    q, r = min(p + 1, n - 1), min(p + 2, n - 1)
    sums = _pixel_sums(
        k, pix_runs, run_start, run_len, run_head, run_tail, inv_area, pix_cuts, cut_weight, x, p, q, r
    )
    bad = 0
    for i in range(min(3, n - p)):
        out[p + i, k] = sums[i]
        bad += not math.isfinite(out[p + i, k])
    return bad


#: Pixels a share takes at a time, every three planes in turn: about a sensor row of them, whose
#: source rows (three planes of them) stay in the core's cache for the next three planes.
BAND = 256
#: Chunks of pixels a product is cut into per thread ([`runs_apply`][]): a thread that finishes
#: its own takes what is left of the others'.
CHUNKS = 16


@inline
def _chunk_sums(
    i, chunks, pix_runs, run_start, run_len, run_head, run_tail, inv_area, pix_cuts, cut_weight, x, out
):
    """Chunk ``i`` of ``chunks`` (whole bands of [`BAND`][] pixels) of [`runs_apply`][]; returns how
    many of the values it wrote are not finite."""
    rows = pix_runs.shape[0] - 1
    bands = (rows + BAND - 1) // BAND
    lo, hi = i * bands // chunks * BAND, min((i + 1) * bands // chunks * BAND, rows)
    bad = 0
    for k0 in range(lo, hi, BAND):
        for p in range(0, x.shape[0], 3):
            for k in range(k0, min(k0 + BAND, hi)):
                bad += _pixel_out(k, pix_runs, run_start, run_len, run_head, run_tail, inv_area, pix_cuts,
                                  cut_weight, x, out, p)  # fmt: skip
    return bad


@serial
def _runs_share(
    t: int, nt: int, claims: np.ndarray, bad: np.ndarray, pix_runs: np.ndarray, run_start: np.ndarray,
    run_len: np.ndarray, run_head: np.ndarray, run_tail: np.ndarray, inv_area: np.ndarray,
    pix_cuts: np.ndarray, cut_weight: np.ndarray, x: np.ndarray, out: np.ndarray,
) -> None:  # fmt: skip
    """Thread ``t``'s chunks of [`runs_apply`][] ([`run_chunks`][layoutwarp.kernels.base.run_chunks]:
    its own, then the others' left), each chunk's count of non-finite values into ``bad``."""
    c = claims.shape[0]
    for m in range(tries(claims, nt)):
        i = take(claims, t, nt, m)
        if i >= 0:
            bad[i] = _chunk_sums(i, c, pix_runs, run_start, run_len, run_head, run_tail, inv_area, pix_cuts,
                                 cut_weight, x, out)  # fmt: skip


def runs_apply(runs: tuple[np.ndarray, ...], x: np.ndarray, out: np.ndarray, threads: int) -> int:
    """``out[n] = W @ x[n]`` for the area weights ``W`` of a fixed layout held as ``runs`` (the
    eight arrays of [`Runs.arrays`][layoutwarp.kernels.runs.Runs.arrays]), planes ``x``
    ``(N, M)`` float32 and ``out`` ``(N, R)``: chunks of pixels shared among ``threads`` (a thread
    done with its own takes the others' left), every pixel's cells read once for every three
    planes. Returns how many of the values written are not finite (NaN or ±inf):
    [`simulate`][layoutwarp.sensor.simulate]'s finiteness check while they are in registers."""
    nt = int(threads)
    chunks = CHUNKS * nt if nt > 1 else 1
    bad = np.zeros(chunks, np.int64)
    run_chunks(_runs_share, nt, chunks, bad, *runs, x, out)
    return int(bad.sum())


def measured_runs_apply(
    runs: tuple[np.ndarray, ...], x: np.ndarray, mean: np.ndarray, *measure: object
) -> int:
    """[`runs_apply`][] into ``mean``, then
    [`sensor_measure`][layoutwarp.kernels.noise.sensor_measure] of ``mean`` with its other
    arguments ``measure`` (``area_um2, …, out, threads``): a fixed layout's exact forward with
    sensor physics. Returns [`runs_apply`][]'s count of non-finite means (the measurement passes
    NaN and ±inf through)."""
    bad = runs_apply(runs, x, mean, int(measure[-1]))
    sensor_measure(mean, *measure)
    return bad


@dataclass(frozen=True)
class Runs:
    """A fixed layout's area weights as runs of source cells (the arrays of this
    module's kernels): the cells of one pixel in one source row, contiguous, whose
    first ``head`` and last ``tail`` cells a pixel boundary cuts (their weights kept in float32, in
    order) and whose cells between weigh ``inv_area`` of the pixel. At 2048x1024 → 257x129 they
    take 1.24x the bytes of one float32 plane of the image, against 2.6x for the same weights as a
    CSR matrix."""

    pix_runs: np.ndarray
    run_start: np.ndarray
    run_len: np.ndarray
    run_head: np.ndarray
    run_tail: np.ndarray
    inv_area: np.ndarray
    pix_cuts: np.ndarray
    cut_weight: np.ndarray
    shape: tuple[int, int]

    @classmethod
    def of(cls, weights: scipy.sparse.csr_matrix, area: np.ndarray, src_width: int) -> Runs:
        """The runs of float64 area ``weights`` (``(R, H · W)``,
        [`area_weights`][layoutwarp.weights.area_weights]) of pixels of ``area`` ``(R,)`` (in
        source cells): an entry within ``WHOLE`` (1e-9) of ``1 / area`` is a whole cell,
        every other a cut one. A run ends at a gap, at the end of a source row, and where a whole
        cell follows a cut cell that follows a whole cell (a pixel whose row crosses a boundary
        and back: two runs)."""
        indptr, cell, data = weights.indptr.astype(np.int64), weights.indices.astype(np.int64), weights.data
        rows, n = indptr.size - 1, cell.size
        pixel = np.repeat(np.arange(rows), np.diff(indptr))
        whole = np.abs(data * area[pixel] - 1.0) <= WHOLE
        span = np.ones(n, bool)  # a new span of contiguous cells of one pixel in one source row
        span[1:] = (pixel[1:] != pixel[:-1]) | (cell[1:] != cell[:-1] + 1) | (cell[1:] % src_width == 0)
        seen = np.cumsum(whole) - whole  # whole cells before each entry ...
        seen -= seen[np.flatnonzero(span)][np.cumsum(span) - 1]  # ... in its span
        first = span.copy()
        first[1:] |= whole[1:] & ~whole[:-1] & (seen[1:] > 0)
        run = np.cumsum(first) - 1
        starts = np.flatnonzero(first)
        length = np.diff(np.r_[starts, n])
        wholes = np.bincount(run, weights=whole, minlength=starts.size).astype(np.int64)
        first_whole = np.full(starts.size, n)
        np.minimum.at(first_whole, run[whole], np.flatnonzero(whole))
        head = np.where(wholes > 0, first_whole - starts, length)
        cut = ~whole
        index = np.int32 if weights.shape[1] < 2**31 else np.int64
        return cls(
            np.r_[0, np.cumsum(np.bincount(pixel[starts], minlength=rows))],
            cell[starts].astype(index),
            length.astype(np.int32),
            head.astype(np.int32),
            (length - head - wholes).astype(np.int32),
            1.0 / area,
            np.r_[0, np.cumsum(np.bincount(pixel[cut], minlength=rows))],
            data[cut].astype(np.float32),
            weights.shape,
        )

    def arrays(self) -> tuple[np.ndarray, ...]:
        """The eight arrays, in the order the kernels take them."""
        return (
            self.pix_runs, self.run_start, self.run_len, self.run_head, self.run_tail, self.inv_area,
            self.pix_cuts, self.cut_weight,
        )  # fmt: skip

    @property
    def nbytes(self) -> int:
        """The bytes the runs hold."""
        return sum(a.nbytes for a in self.arrays())

    def csr(self) -> scipy.sparse.csr_matrix:
        """The same weights as a float32 ``scipy.sparse.csr_matrix``."""
        import scipy.sparse

        rows = self.pix_runs.size - 1
        length = self.run_len.astype(np.int64)
        offset = np.cumsum(length) - length
        cell = np.repeat(self.run_start.astype(np.int64) - offset, length) + np.arange(int(length.sum()))
        pixel = np.repeat(np.repeat(np.arange(rows), np.diff(self.pix_runs)), length)
        # within a run: head cells, whole cells, tail cells
        at = np.arange(cell.size) - np.repeat(offset, length)
        cut = (at < np.repeat(self.run_head, length)) | (at >= np.repeat(length - self.run_tail, length))
        value = self.inv_area[pixel].astype(np.float32)
        value[cut] = self.cut_weight  # the cut cells in the order they are kept
        indptr = np.r_[0, np.cumsum(np.bincount(pixel, minlength=rows))]
        return scipy.sparse.csr_matrix((value, cell, indptr), shape=self.shape)


# ----------------------------------------------------------------------------------------
# CUDA: one thread per pixel, every plane, the measurement fused
# ----------------------------------------------------------------------------------------
cuda = None  # numba.cuda, bound by the first launch ([`layoutwarp.kernels.device.cuda_launch`][])


def _cuda_runs_apply(
    pix_runs: np.ndarray, run_start: np.ndarray, run_len: np.ndarray, run_head: np.ndarray,
    run_tail: np.ndarray, inv_area: np.ndarray, pix_cuts: np.ndarray, cut_weight: np.ndarray, x: np.ndarray,
    out: np.ndarray, area_um2: np.ndarray, prnu: np.ndarray, dsnu: np.ndarray, params: np.ndarray, seed: int,
    noise: int, output: int, measure: bool, checks: np.ndarray, stamp: int,
) -> None:  # fmt: skip
    """One thread per pixel: [`runs_apply`][]'s sums for every plane (the pixel's cells read once
    per three planes; neighbouring threads read neighbouring runs of a source row), written to
    ``out`` ``(N, R)``, and with ``measure`` then measured
    ([`measured_value`][layoutwarp.kernels.noise.measured_value], from the value as ``out``'s
    dtype holds it, as [`measured_runs_apply`][] measures its buffer): a fixed layout's forward,
    with the sensor's measurement, in one launch on a CUDA device. ``area_um2``, ``prnu``,
    ``dsnu``, ``params``, ``seed``, ``noise``, ``output``: as
    [`sensor_measure`][layoutwarp.kernels.noise.sensor_measure] takes them (read only with
    ``measure``). A sum that is NaN or ±inf writes ``stamp`` to ``checks[0]`` (0: no check;
    [`DeviceChecks`][layoutwarp.kernels.device.DeviceChecks])."""
    k = cuda.grid(1)
    rows = pix_runs.shape[0] - 1
    if k < rows:
        bad = 0
        for p in range(0, x.shape[0], 3):
            bad += _pixel_out(
                k, pix_runs, run_start, run_len, run_head, run_tail, inv_area, pix_cuts, cut_weight, x, out, p
            )
        if stamp and bad:
            checks[0] = stamp
        if measure:  # from the means as the buffer holds them, as the CPU measures its buffer
            origin = stream_origin(seed)
            for p in range(x.shape[0]):
                out[p, k] = measured_value(
                    out[p, k], p * rows + k, k, area_um2, prnu, dsnu, params, origin, noise, output
                )


_F1, _I1, _J1, _F2 = "float64[::1]", "int64[::1]", "int32[::1]", "float32[:, ::1]"
#: The CUDA kernels of this file with their argument types (for
#: [`cuda_ptx`][layoutwarp.kernels.device.cuda_ptx]: float32 images).
CUDA_KERNELS = {
    "runs_apply": (
        _cuda_runs_apply,
        f"void({_I1}, {_J1}, {_J1}, {_J1}, {_J1}, {_F1}, {_I1}, float32[::1], {_F2}, {_F2}, {_F1}, {_F1}, "
        f"{_F1}, {_F1}, int64, int64, int64, boolean, {_I1}, int64)",
    ),
}


def runs_apply_on_device(
    runs: tuple, x, out, measured: tuple, measure: bool, stream: int, check: bool = False
) -> None:
    """[`runs_apply`][] on a CUDA device (or in the simulator), one launch on ``stream``: the eight
    arrays ``runs`` and the planes ``x`` ``(N, M)`` and ``out`` ``(N, R)`` as tensors there; with
    ``measure``, the means then measured with ``measured`` ``(area_um2, prnu, dsnu, params, seed,
    noise, output)`` as [`measure_on_device`][layoutwarp.kernels.noise.measure_on_device] takes
    them (without, any arrays of float64 will do: they are not read). With ``check``, a sum that
    is NaN or ±inf raises when the host next looks
    ([`DeviceChecks`][layoutwarp.kernels.device.DeviceChecks]; look before the call)."""
    area_um2, prnu, dsnu, params, seed, noise, output = measured
    checks = device_checks(x.device)
    args = (*runs, x, out, area_um2, prnu, dsnu, params, int(seed), int(noise), int(output), bool(measure))
    cuda_launch(
        _cuda_runs_apply, runs[0].shape[0] - 1, stream, *args, checks.status, checks.take() if check else 0
    )
