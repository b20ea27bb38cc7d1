"""Compiled kernels of the exact integrator, CPU and CUDA, and of the sensor's measurement (numba;
no compiler needed on the user's machine).

Each kernel fuses what the torch reference in [`layoutwarp.integrators`][] does in some
forty vectorised passes: cutting every pixel-boundary segment into single-cell pieces, the
prefix-table look-ups of Green's theorem and the accumulation. For an image up to
[`WHOLE_TABLE_BYTES`][] the forward builds the whole prefix table once (kept for the
backward) and runs over chunks of segments dealt to the threads in turn (curved edges, which
have many segments often all of one orientation, are shared out evenly); a larger image is
integrated in bands of rows, each thread building one band's table at a time in a buffer of
its own, adding every piece straight into per-edge sums of its own, so neither a whole table
nor a value per segment and channel is held (the backward builds the table when it is called). The
whole-table forward writes one value per segment and a last pass sums each pixel edge's
segments (contiguous in a [`PixelMesh`][layoutwarp.mesh.PixelMesh]). The
arithmetic mirrors the reference step for step, so both agree to rounding.

The per-segment steps are ``@njit`` functions that numba also compiles for CUDA: there the
whole-table forward runs one GPU thread per segment (and per table row × block × channel, per
pixel edge), launched by [`cuda_launch`][]; [`cuda_available`][] says whether that target
works here.

Compiled code is cached on disk (``cache=True``): a second process loads it instead of
compiling again. numba invalidates a cache only when the function's own file changes, and
[`layoutwarp.meshkernels`][] inlines functions of this one: after editing this file, delete
the package's ``*.nbi``/``*.nbc`` caches. [`available`][] says whether numba is installed;
without it the torch reference runs.
"""

from __future__ import annotations

import contextlib
import importlib
import math
import threading
import warnings
from collections.abc import Callable

import numpy as np

try:  # numba is a dependency, but the torch reference keeps working without it
    from numba import config as numba_config
    from numba import get_num_threads, njit, prange, set_num_threads
    from numba import types as numba_types
    from numba.extending import intrinsic
except ImportError:  # pragma: no cover - depends on the environment
    njit = prange = get_num_threads = set_num_threads = numba_config = numba_types = intrinsic = None
try:  # numba's own code generator, present wherever numba is
    from llvmlite import ir as llvm_ir
except ImportError:  # pragma: no cover - depends on the environment
    llvm_ir = None

__all__ = [
    "BLOCK",
    "CUDA_THREADS",
    "LOCK",
    "WHOLE_TABLE_BYTES",
    "available",
    "band_rows",
    "csr_apply",
    "cuda_available",
    "cuda_checked",
    "cuda_launch",
    "cuda_ptx",
    "exact_backward",
    "exact_forward",
    "exact_forward_banded",
    "measured_csr_apply",
    "prefix_tables",
    "retain_freed_memory",
    "segment_moments",
    "sensor_measure",
    "threads",
]

#: Columns per block of the prefix tables (see [`prefix_tables`][]).
BLOCK = 16
#: Segments per work chunk; chunks go to the threads in turn.
CHUNK = 256
#: Held around every launch of a parallel kernel: numba's ``workqueue`` threading layer (used
#: where no OpenMP or TBB runtime is installed) aborts the process on concurrent launches from
#: several Python threads. Each launch uses every core anyway.
LOCK = threading.Lock()


def available() -> bool:
    """Whether the compiled kernels can run (numba is importable)."""
    return njit is not None


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


def _jit(fn):  # numpy's error model: a division by zero gives inf, unchecked, so loops with one vectorise
    return njit(parallel=True, cache=True, nogil=True, error_model="numpy")(fn) if njit is not None else fn


def _serial(fn):  # a serial driver of parallel kernels: one call from Python
    return njit(cache=True, nogil=True, error_model="numpy")(fn) if njit is not None else fn


def _inline(fn):
    return njit(inline="always", cache=True)(fn) if njit is not None else fn


@_inline
def _block_prefix(image: np.ndarray, r: int, rr: int, b: int, k: int, block: int, incl: np.ndarray) -> None:
    """Inclusive sums of block ``b`` of row ``r``, channel ``k``, into ``incl[rr, :, k]``."""
    w = image.shape[2]
    acc = image[k, r, b * block] * 0  # zero in the image's dtype
    for c in range(b * block, min(w, (b + 1) * block)):
        acc += image[k, r, c]
        incl[rr, c, k] = acc


@_inline
def _row_offsets(rr: int, k: int, block: int, incl: np.ndarray, offsets: np.ndarray) -> None:
    """The float64 sums of the whole blocks before each block of ``incl[rr, :, k]``."""
    w = incl.shape[1]
    total = 0.0
    for b in range(offsets.shape[1]):
        offsets[rr, b, k] = total
        total += incl[rr, min(w, (b + 1) * block) - 1, k]


@_inline
def _band_prefix(
    image: np.ndarray, ra: int, rb: int, block: int, incl: np.ndarray, offsets: np.ndarray
) -> None:
    """The prefix tables (see [`prefix_tables`][]) of rows ``ra .. rb − 1`` into ``incl``/
    ``offsets`` (row ``ra`` at index 0); [`_block_prefix`][] and [`_row_offsets`][] are
    the one home of their arithmetic."""
    n, _, w = image.shape
    nb = (w + block - 1) // block
    for rr in range(rb - ra):
        for k in range(n):
            for b in range(nb):
                _block_prefix(image, ra + rr, rr, b, k, block, incl)
            _row_offsets(rr, k, block, incl, offsets)


@_jit
def prefix_tables(image: np.ndarray, block: int) -> tuple[np.ndarray, np.ndarray]:
    """Row prefix sums of ``image (N, H, W)``, safe in float32, channels last.

    Returns ``(incl, offsets)``: ``incl[r, c, n]`` is the inclusive prefix sum of row ``r`` of
    channel ``n`` within the ``block``-column block of ``c`` (in the image's dtype) and
    ``offsets[r, k, n]`` the float64 sum of the whole blocks before block ``k``, so a prefix
    never carries more than one block's rounding. Channels last puts everything one piece
    reads in one or two cache lines.
    """
    n, h, w = image.shape
    nb = (w + block - 1) // block
    incl = np.empty((h, w, n), dtype=image.dtype)
    offsets = np.empty((h, nb, n), dtype=np.float64)
    for r in prange(h):
        _band_prefix(image, r, r + 1, block, incl[r : r + 1], offsets[r : r + 1])
    return incl, offsets


@_inline
def _row_span(y0: float, y1: float, h: int) -> tuple[int, int]:
    """The source rows a segment from ``y0`` to ``y1`` crosses, clamped to the image."""
    ylo, yhi = min(y0, y1), max(y0, y1)
    r0 = min(max(math.floor(ylo), 0), h - 1)
    return r0, max(min(max(math.ceil(yhi) - 1, 0), h - 1), r0)


@_inline
def _cell(incl: np.ndarray, row: int, col: int, k: int, block: int) -> float:
    """The box image value ``I(c) − I(c − 1)`` of the prefix table at ``(row, col)``."""
    cur = np.float64(incl[row, col, k])
    return cur if col % block == 0 else cur - np.float64(incl[row, col - 1, k])


@_inline
def _row_piece(
    row: int, x0: float, y0: float, dxv: float, inv_dy: float, ylo: float, yhi: float, flat: bool, w: int
) -> tuple[float, float, int, int, float]:
    """The piece in source row ``row`` of the segment from ``(x0, y0)`` by ``(dxv, 1/inv_dy)``,
    ``Y`` from ``ylo`` to ``yhi`` (a flat segment: all of it): its parameter range
    ``t_lo .. t_hi``, the columns ``c0 .. c1`` it crosses (one for a vertical segment) and
    ``1/dxv`` where it crosses more than one."""
    if flat:
        t_lo, t_hi = 0.0, 1.0
    else:
        ta = min(max((max(ylo, row) - y0) * inv_dy, 0.0), 1.0)
        tb = min(max((min(yhi, row + 1.0) - y0) * inv_dy, 0.0), 1.0)
        t_lo, t_hi = min(ta, tb), max(ta, tb)
    xa, xb = x0 + t_lo * dxv, x0 + t_hi * dxv
    xlo, xhi = min(xa, xb), max(xa, xb)
    c0 = min(max(math.floor(xlo), 0), w - 1)
    c1 = max(min(max(math.ceil(xhi) - 1, 0), w - 1), c0)
    if dxv == 0.0:
        c1 = c0
    return t_lo, t_hi, c0, c1, (1.0 / dxv if c1 != c0 else 1.0)


@_inline
def _cell_piece(
    col: int, x0: float, inv_dx: float, t_lo: float, t_hi: float, c0: int, c1: int
) -> tuple[float, float]:
    """The parameter range inside column ``col`` of a row piece ([`_row_piece`][]): from the
    crossing of one of the column's lines to the next, ``t = (X − x0) / ΔX``, and the piece's own
    ends in place of the outer lines of its first and last columns. The columns so tile
    ``t_lo .. t_hi`` exactly, however few ulps ``ΔX`` spans (``X → t`` is ill-conditioned
    there: ranges taken from the piece's rounded ``X`` ends could leave a gap or overlap)."""
    if c1 == c0:  # one column: the row piece's range
        return t_lo, t_hi
    forward = inv_dx > 0.0  # X grows with t
    ua = t_lo if forward else t_hi
    ub = t_hi if forward else t_lo
    if col != c0:
        ua = min(max((col - x0) * inv_dx, t_lo), t_hi)
    if col != c1:
        ub = min(max((col + 1.0 - x0) * inv_dx, t_lo), t_hi)
    return min(ua, ub), max(ua, ub)


@_inline
def _other_cell(row: int, col: int, x0: float, y0: float, flat: bool, vertical: bool) -> tuple[int, int]:
    """The cell across the line a piece in cell ``(row, col)`` lies on, or that cell itself: a
    flat segment on a row line (``y0 == row``) faces the row above, a vertical one on a column
    line (``x0 == col``) the column to its left (none beyond the image). Where the two differ,
    the backward's image value is the mean of both cells (the symmetric derivative)."""
    row2 = row - 1 if (flat and y0 == row and row > 0) else row
    col2 = col - 1 if (vertical and x0 == col and col > 0) else col
    return row2, col2


@_inline
def _segment_rows(
    x0: float,
    y0: float,
    x1: float,
    y1: float,
    rlo: int,
    rhi: int,
    ra: int,
    incl: np.ndarray,
    offsets: np.ndarray,
    block: int,
    w: int,
    out: np.ndarray,
    at: int,
    moments: bool,
    ma: np.ndarray,
    mb: np.ndarray,
) -> None:
    """Add segment ``(x0, y0) → (x1, y1)``'s ``∫ P dY`` over source rows ``rlo .. rhi`` to
    ``out[at, :]``; the tables hold rows from ``ra`` on (see [`exact_forward`][]). With
    ``moments``, also its Reynolds moments to ``ma[at, :]``, ``mb[at, :]`` from the same pieces
    and look-ups ([`_segment_moments`][] gives them for a flat segment)."""
    n = incl.shape[2]
    dxv, dyv = x1 - x0, y1 - y0
    inv_dy = 1.0 / dyv
    ylo, yhi = min(y0, y1), max(y0, y1)
    for row in range(rlo, rhi + 1):
        t_lo, t_hi, c0, c1, inv_dx = _row_piece(row, x0, y0, dxv, inv_dy, ylo, yhi, False, w)
        rr = row - ra
        for col in range(c0, c1 + 1):
            t0, t1 = _cell_piece(col, x0, inv_dx, t_lo, t_hi, c0, c1)
            dy = (t1 - t0) * dyv
            frac = min(max(x0 + (t0 + t1) / 2 * dxv - col, 0.0), 1.0)
            blk = col // block
            at_start = col % block == 0
            m1 = (t1 * t1 - t0 * t0) / 2
            m0 = (t1 - t0) - m1
            on_line = _other_cell(row, col, x0, y0, False, dxv == 0.0)[1] != col  # the two cells' mean
            for k in range(n):
                cur = np.float64(incl[rr, col, k])
                prev = 0.0 if at_start else np.float64(incl[rr, col - 1, k])
                out[at, k] += dy * (offsets[rr, blk, k] + prev + frac * (cur - prev))
                if moments:
                    lv = cur - prev  # the cell's value, as _cell gives it
                    if on_line:
                        lv = 0.5 * (lv + _cell(incl, rr, col - 1, k, block))
                    ma[at, k] += lv * m0
                    mb[at, k] += lv * m1


@_inline
def _segment_forward(
    s: int,
    verts: np.ndarray,
    seg_start: np.ndarray,
    seg_end: np.ndarray,
    incl: np.ndarray,
    offsets: np.ndarray,
    block: int,
    per_seg: np.ndarray,
) -> None:
    """Segment ``s``'s ``∫ P dY`` per channel and its ``∫ X dY`` into ``per_seg[s, :]``, from
    the whole image's tables (see [`exact_forward`][])."""
    h, w, n = incl.shape
    x0, y0 = verts[seg_start[s], 0], verts[seg_start[s], 1]
    x1, y1 = verts[seg_end[s], 0], verts[seg_end[s], 1]
    if y1 == y0:
        return  # ΔY = 0 adds nothing
    per_seg[s, n] = (y1 - y0) * (x0 + x1) / 2
    r0, r1 = _row_span(y0, y1, h)
    _segment_rows(x0, y0, x1, y1, r0, r1, 0, incl, offsets, block, w, per_seg, s, False, per_seg, per_seg)


@_inline
def segment_moments(
    x0: float,
    y0: float,
    x1: float,
    y1: float,
    incl: np.ndarray,
    offsets: np.ndarray,
    block: int,
    acc: np.ndarray,
    ma: np.ndarray,
    mb: np.ndarray,
) -> None:
    """Segment ``(x0, y0) → (x1, y1)``'s ``∫ P dY`` per channel and its ``∫ X dY`` into
    ``acc[0, :]`` (as [`exact_forward`][] integrates a segment), and its Reynolds moments
    ``∫ (1 − t) L_n dt`` and ``∫ t L_n dt`` into ``ma[0, :]``, ``mb[0, :]`` (``(1, N)`` each),
    from the same pieces and look-ups; all three set here, none need be zeroed. A scalar
    function for other kernels ([`mesh_integrals`][layoutwarp.meshkernels.mesh_integrals]): the segment's
    weights in [`exact_backward`][] are ``grad[N, e]/2 + Σ_n grad[n, e]·m[n]``."""
    h, w, n = incl.shape
    acc[0, :] = 0.0
    ma[0, :] = 0.0
    mb[0, :] = 0.0
    if y1 == y0:  # no ∫ P dY, but moments along the row line
        _segment_moments(x0, y0, x1, y1, incl, block, ma, mb)
        return
    acc[0, n] = (y1 - y0) * (x0 + x1) / 2
    r0, r1 = _row_span(y0, y1, h)
    _segment_rows(x0, y0, x1, y1, r0, r1, 0, incl, offsets, block, w, acc, 0, True, ma, mb)


@_inline
def _edge_sum(e: int, per_seg: np.ndarray, edge_offsets: np.ndarray, out: np.ndarray) -> None:
    """Add edge ``e``'s segments ``per_seg[s, :]`` into ``out[:, e]``, in order."""
    for s in range(edge_offsets[e], edge_offsets[e + 1]):
        for k in range(per_seg.shape[1]):
            out[k, e] += per_seg[s, k]


@_jit
def _edge_sums(per_seg: np.ndarray, edge_offsets: np.ndarray) -> np.ndarray:
    """Sum each edge's segments: ``(S, N + 1)`` → ``(N + 1, E)``."""
    e_count = edge_offsets.shape[0] - 1
    out = np.zeros((per_seg.shape[1], e_count), dtype=np.float64)
    for e in prange(e_count):
        _edge_sum(e, per_seg, edge_offsets, out)
    return out


@_jit
def exact_forward(
    verts: np.ndarray,
    seg_start: np.ndarray,
    seg_end: np.ndarray,
    edge_offsets: np.ndarray,
    incl: np.ndarray,
    offsets: np.ndarray,
    block: int,
    threads: int,
) -> np.ndarray:
    """``∫ P dY`` along every edge for every channel, and the edge's ``∫ X dY``: ``(N + 1, E)``.

    ``verts`` are ``(V, 2)`` float64 in source pixel units (inside the image); segment ``s``
    runs from ``verts[seg_start[s]]`` to ``verts[seg_end[s]]`` and edge ``e`` is made of the
    segments ``edge_offsets[e] .. edge_offsets[e + 1] − 1``; ``incl``/``offsets`` are the
    image's [`prefix_tables`][]. Each segment is cut at source rows, then each row piece at
    columns; a piece in cell ``(r, c)`` with mid-``X`` fraction ``f`` adds ``ΔY · P_r(c + f)``,
    where ``P_r`` interpolates the prefix table linearly inside the cell: ``P_r(c + f) =
    offset + I(c − 1) + f · (I(c) − I(c − 1))``, exact for the box image ``L(c) = I(c) −
    I(c − 1)``. Row ``N`` sums to the pixel areas. ``threads``: see [`threads`][].
    """
    s_count = seg_start.shape[0]
    per_seg = np.zeros((s_count, incl.shape[2] + 1), dtype=np.float64)
    n_chunks = (s_count + CHUNK - 1) // CHUNK
    for thread in prange(threads):
        for chunk in range(thread, n_chunks, threads):
            for s in range(chunk * CHUNK, min((chunk + 1) * CHUNK, s_count)):
                _segment_forward(s, verts, seg_start, seg_end, incl, offsets, block, per_seg)
    return _edge_sums(per_seg, edge_offsets)


@_jit
def exact_forward_banded(
    verts: np.ndarray,
    seg_start: np.ndarray,
    seg_end: np.ndarray,
    edge_offsets: np.ndarray,
    seg_edge: np.ndarray,
    image: np.ndarray,
    block: int,
    band: int,
    threads: int,
) -> np.ndarray:
    """[`exact_forward`][] from the image ``(N, H, W)`` itself, in bands of ``band`` rows:
    each thread builds the prefix table of one band at a time in a buffer of its own (that
    stays in cache) and adds every segment piece in those rows to its own per-edge sums, so
    neither a table of the whole image nor anything per segment and channel is held (memory
    beyond the mesh: ``threads × E × N`` sums). Segments are first listed per band (a
    segment crossing several bands is listed in each, its rows split between them);
    ``seg_edge[s]`` is the edge of segment ``s``."""
    n, h, w = image.shape
    nb = (w + block - 1) // block
    s_count = seg_start.shape[0]
    e_count = edge_offsets.shape[0] - 1
    n_bands = (h + band - 1) // band
    first = np.zeros(n_bands + 1, dtype=np.int64)  # counting sort of the segments by band
    for s in range(s_count):
        y0, y1 = verts[seg_start[s], 1], verts[seg_end[s], 1]
        if y1 != y0:
            r0, r1 = _row_span(y0, y1, h)
            for b in range(r0 // band, r1 // band + 1):
                first[b + 1] += 1
    for b in range(n_bands):
        first[b + 1] += first[b]
    fill = first[:-1].copy()
    listed = np.empty(first[n_bands], dtype=np.int64)
    for s in range(s_count):
        y0, y1 = verts[seg_start[s], 1], verts[seg_end[s], 1]
        if y1 != y0:
            r0, r1 = _row_span(y0, y1, h)
            for b in range(r0 // band, r1 // band + 1):
                listed[fill[b]] = s
                fill[b] += 1
    sums = np.zeros((threads, e_count, n), dtype=np.float64)
    for thread in prange(threads):
        incl = np.empty((band, w, n), dtype=image.dtype)
        offsets = np.empty((band, nb, n), dtype=np.float64)
        for bi in range(thread, n_bands, threads):
            ra = bi * band
            rb = min(h, ra + band)
            _band_prefix(image, ra, rb, block, incl, offsets)
            for j in range(first[bi], first[bi + 1]):
                s = listed[j]
                x0, y0 = verts[seg_start[s], 0], verts[seg_start[s], 1]
                x1, y1 = verts[seg_end[s], 0], verts[seg_end[s], 1]
                r0, r1 = _row_span(y0, y1, h)
                rlo, rhi = max(r0, ra), min(r1, rb - 1)
                e = seg_edge[s]
                out_t = sums[thread]
                _segment_rows(
                    x0, y0, x1, y1, rlo, rhi, ra, incl, offsets, block, w, out_t, e, False, out_t, out_t
                )
    out = np.zeros((n + 1, e_count), dtype=np.float64)
    for e in prange(e_count):
        for k in range(n):
            for t in range(threads):
                out[k, e] += sums[t, e, k]
        for s in range(edge_offsets[e], edge_offsets[e + 1]):
            x0, y0 = verts[seg_start[s], 0], verts[seg_start[s], 1]
            x1, y1 = verts[seg_end[s], 0], verts[seg_end[s], 1]
            out[n, e] += (y1 - y0) * (x0 + x1) / 2
    return out


#: Whole-image prefix tables up to this size are built once and kept for the backward; larger
#: images are integrated in bands ([`exact_forward_banded`][]), which holds no whole table.
WHOLE_TABLE_BYTES = 8 << 20


def band_rows(image: np.ndarray, workers: int, cache_bytes: int = 1 << 20) -> int:
    """Rows per band of [`exact_forward_banded`][]: a band's prefix table fills about
    ``cache_bytes``, and there are at least four bands per worker thread."""
    n, h, w = image.shape
    by_cache = cache_bytes // max(1, w * n * image.itemsize)
    return max(1, min(h, by_cache, -(-h // (4 * workers))))


@_inline
def _segment_weights(
    s: int,
    verts: np.ndarray,
    seg_start: np.ndarray,
    seg_end: np.ndarray,
    seg_edge: np.ndarray,
    incl: np.ndarray,
    block: int,
    grad: np.ndarray,
    wa: np.ndarray,
    wb: np.ndarray,
) -> None:
    """Segment ``s``'s Reynolds weights into ``wa[s]``/``wb[s]`` (see [`exact_backward`][])."""
    h, w, n = incl.shape
    e = seg_edge[s]
    x0, y0 = verts[seg_start[s], 0], verts[seg_start[s], 1]
    x1, y1 = verts[seg_end[s], 0], verts[seg_end[s], 1]
    dxv, dyv = x1 - x0, y1 - y0
    wa[s] = wb[s] = grad[n, e] / 2  # the area row: ∫ (1 − t) dt = ∫ t dt = 1/2
    flat, vertical = dyv == 0.0, dxv == 0.0
    inv_dy = 1.0 / dyv if not flat else 1.0
    ylo, yhi = min(y0, y1), max(y0, y1)
    r0, r1 = _row_span(y0, y1, h)
    for row in range(r0, (r0 if flat else r1) + 1):
        t_lo, t_hi, c0, c1, inv_dx = _row_piece(row, x0, y0, dxv, inv_dy, ylo, yhi, flat, w)
        for col in range(c0, c1 + 1):
            t0, t1 = _cell_piece(col, x0, inv_dx, t_lo, t_hi, c0, c1)
            row2, col2 = _other_cell(row, col, x0, y0, flat, vertical)
            gl = 0.0
            if row2 == row and col2 == col:  # inside the cell (nearly always): one look-up
                for k in range(n):
                    gl += grad[k, e] * _cell(incl, row, col, k, block)
            else:
                for k in range(n):
                    lv = 0.5 * (_cell(incl, row, col, k, block) + _cell(incl, row2, col2, k, block))
                    gl += grad[k, e] * lv
            m1 = (t1 * t1 - t0 * t0) / 2
            wa[s] += gl * ((t1 - t0) - m1)
            wb[s] += gl * m1


@_inline
def _segment_moments(
    x0: float,
    y0: float,
    x1: float,
    y1: float,
    incl: np.ndarray,
    block: int,
    ma: np.ndarray,
    mb: np.ndarray,
) -> None:
    """Add segment ``(x0, y0) → (x1, y1)``'s Reynolds moments per channel, ``∫ (1 − t) L_k dt``
    and ``∫ t L_k dt`` over its pieces, to ``ma[0, k]`` and ``mb[0, k]``: the walk of
    [`_segment_weights`][] before any gradient is known."""
    h, w, n = incl.shape
    dxv, dyv = x1 - x0, y1 - y0
    flat, vertical = dyv == 0.0, dxv == 0.0
    inv_dy = 1.0 / dyv if not flat else 1.0
    ylo, yhi = min(y0, y1), max(y0, y1)
    r0, r1 = _row_span(y0, y1, h)
    for row in range(r0, (r0 if flat else r1) + 1):
        t_lo, t_hi, c0, c1, inv_dx = _row_piece(row, x0, y0, dxv, inv_dy, ylo, yhi, flat, w)
        for col in range(c0, c1 + 1):
            t0, t1 = _cell_piece(col, x0, inv_dx, t_lo, t_hi, c0, c1)
            row2, col2 = _other_cell(row, col, x0, y0, flat, vertical)
            m1 = (t1 * t1 - t0 * t0) / 2
            m0 = (t1 - t0) - m1
            inside = row2 == row and col2 == col
            for k in range(n):
                lv = _cell(incl, row, col, k, block)
                if not inside:
                    lv = 0.5 * (lv + _cell(incl, row2, col2, k, block))
                ma[0, k] += lv * m0
                mb[0, k] += lv * m1


@_jit
def exact_backward(
    verts: np.ndarray,
    seg_start: np.ndarray,
    seg_end: np.ndarray,
    seg_edge: np.ndarray,
    incl: np.ndarray,
    block: int,
    grad: np.ndarray,
    threads: int,
) -> tuple[np.ndarray, np.ndarray]:
    """Reynolds weights of every segment's end points for the vertex gradient.

    ``grad`` is ``(N + 1, E)``, the gradient of [`exact_forward`][]'s output, and segment
    ``s`` belongs to edge ``seg_edge[s]``. For segment ``s`` of edge ``e`` with
    ``r(t) = a + t (b − a)``: ``wa = Σ_n grad[n, e] ∫ (1 − t) L_n dt`` and
    ``wb = Σ_n grad[n, e] ∫ t L_n dt`` over its pieces, with ``L`` the box image of the prefix
    table (see [`exact_forward`][]) and ``L ≡ 1`` for the area row ``n = N``; on a cell
    boundary line ``L`` is the mean of the two cells (the symmetric derivative). The caller
    multiplies by the segment's normal ``(ΔY, −ΔX)`` and adds to the vertices.
    """
    s_count = seg_start.shape[0]
    wa = np.zeros(s_count, dtype=np.float64)
    wb = np.zeros(s_count, dtype=np.float64)
    n_chunks = (s_count + CHUNK - 1) // CHUNK
    for thread in prange(threads):
        for chunk in range(thread, n_chunks, threads):
            for s in range(chunk * CHUNK, min((chunk + 1) * CHUNK, s_count)):
                _segment_weights(s, verts, seg_start, seg_end, seg_edge, incl, block, grad, wa, wb)
    return wa, wb


# ----------------------------------------------------------------------------------------
# CUDA: the same per-segment arithmetic, one GPU thread per segment (or row, or edge)
# ----------------------------------------------------------------------------------------
cuda = None  # numba.cuda, imported by the first CUDA call (it costs a tenth of a second)
_CUDA_KERNELS: dict = {}
_CUDA_OK: dict = {}


def _cuda_prefix_blocks(image: np.ndarray, block: int, incl: np.ndarray) -> None:
    """One thread per (row, block, channel): [`_block_prefix`][]."""
    i = cuda.grid(1)
    n, h, w = image.shape
    nb = (w + block - 1) // block
    if i < h * nb * n:
        r, b, k = i // (nb * n), (i // n) % nb, i % n
        _block_prefix(image, r, r, b, k, block, incl)


def _cuda_prefix_offsets(block: int, incl: np.ndarray, offsets: np.ndarray) -> None:
    """One thread per (row, channel): [`_row_offsets`][]."""
    i = cuda.grid(1)
    h, _, n = incl.shape
    if i < h * n:
        _row_offsets(i // n, i % n, block, incl, offsets)


def _cuda_forward(
    verts: np.ndarray,
    seg_start: np.ndarray,
    seg_end: np.ndarray,
    incl: np.ndarray,
    offsets: np.ndarray,
    block: int,
    per_seg: np.ndarray,
) -> None:
    """One thread per segment: [`_segment_forward`][]."""
    s = cuda.grid(1)
    if s < seg_start.shape[0]:
        _segment_forward(s, verts, seg_start, seg_end, incl, offsets, block, per_seg)


def _cuda_edge_sums(per_seg: np.ndarray, edge_offsets: np.ndarray, out: np.ndarray) -> None:
    """One thread per pixel edge: [`_edge_sum`][]."""
    e = cuda.grid(1)
    if e < edge_offsets.shape[0] - 1:
        _edge_sum(e, per_seg, edge_offsets, out)


def _cuda_backward(
    verts: np.ndarray,
    seg_start: np.ndarray,
    seg_end: np.ndarray,
    seg_edge: np.ndarray,
    incl: np.ndarray,
    block: int,
    grad: np.ndarray,
    wa: np.ndarray,
    wb: np.ndarray,
) -> None:
    """One thread per segment: [`_segment_weights`][]."""
    s = cuda.grid(1)
    if s < seg_start.shape[0]:
        _segment_weights(s, verts, seg_start, seg_end, seg_edge, incl, block, grad, wa, wb)


_CUDA_SOURCES = {
    "prefix_blocks": _cuda_prefix_blocks,
    "prefix_offsets": _cuda_prefix_offsets,
    "forward": _cuda_forward,
    "edge_sums": _cuda_edge_sums,
    "backward": _cuda_backward,
}
#: Threads per block of the CUDA kernels.
CUDA_THREADS = 128


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
        cuda = numba_cuda


def _kernel_source(kernel: str | Callable) -> Callable:
    """The source of CUDA kernel ``kernel`` (a name of this module's, or another module's kernel
    function), its module's ``cuda`` (a ``None`` placeholder there: importing numba.cuda costs a
    tenth of a second) bound to numba.cuda."""
    _import_cuda()
    fn = _CUDA_SOURCES[kernel] if isinstance(kernel, str) else kernel
    if fn.__globals__.get("cuda", cuda) is None:
        fn.__globals__["cuda"] = cuda
    return fn


def _cuda_signature(name: str, dtype: str) -> str:
    """Kernel ``name``'s argument types for images of ``dtype``, C-contiguous arrays, as
    [`cuda_launch`][] passes them."""
    img, idx, f64 = f"{dtype}[:, :, ::1]", "int64[::1]", "float64[::1]"
    f64_2, f64_3 = "float64[:, ::1]", "float64[:, :, ::1]"
    args = {
        "prefix_blocks": [img, "int64", img],
        "prefix_offsets": ["int64", img, f64_3],
        "forward": [f64_2, idx, idx, img, f64_3, "int64", f64_2],
        "edge_sums": [f64_2, idx, f64_2],
        "backward": [f64_2, idx, idx, idx, img, "int64", f64_2, f64, f64],
    }[name]
    return f"void({', '.join(args)})"


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
        if kernel not in _CUDA_SOURCES:
            raise ValueError(f"kernel must be one of {', '.join(_CUDA_SOURCES)}, got {kernel!r}")
        if dtype not in ("float32", "float64"):
            raise ValueError(f"dtype must be 'float32' or 'float64', got {dtype!r}")
        signature = _cuda_signature(kernel, dtype)
    elif signature is None:
        raise ValueError("signature: a kernel function needs its argument types, e.g. 'void(float64[::1])'")
    source = _kernel_source(kernel)
    ptx, _ = cuda.compile_ptx(source, signature, cc=cc)
    return ptx


def cuda_launch(name: str | Callable, count: int, stream: int, *args) -> None:
    """Launch CUDA kernel ``name`` with one thread per item, ``count`` items, on the CUDA
    stream whose handle is ``stream`` (0: the default stream); ``name`` may also be another
    module's kernel source (a function of a source file, compiled on first use). The kernels, by
    name:
    ``"prefix_blocks"`` (items: row × block × channel) and ``"prefix_offsets"`` (row ×
    channel) build [`prefix_tables`][]; ``"forward"`` (segment) and ``"edge_sums"`` (pixel
    edge) do [`exact_forward`][]; ``"backward"`` (segment) does [`exact_backward`][],
    each step for step as on the CPU. Array arguments are torch CUDA tensors or numba device
    arrays (anything with ``__cuda_array_interface__``), read and written in place. Kernels
    compile on first use and are cached on disk."""
    _import_cuda()
    if name not in _CUDA_KERNELS:
        _CUDA_KERNELS[name] = cuda.jit(cache=True)(_kernel_source(name))
    if count == 0:
        return
    arrays = [cuda.as_cuda_array(a) if hasattr(type(a), "__cuda_array_interface__") else a for a in args]
    on = cuda.external_stream(stream) if stream else 0  # 0: the default stream, as numba takes it
    with warnings.catch_warnings():  # numba warns of low occupancy on small meshes: not the user's concern
        warnings.filterwarnings("ignore", message=".*GPU under-utilization")
        _CUDA_KERNELS[name][(count + CUDA_THREADS - 1) // CUDA_THREADS, CUDA_THREADS, on](*arrays)


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


# ----------------------------------------------------------------------------------------
# The sensor's measurement (physics): one fused pass over the sensor image
# ----------------------------------------------------------------------------------------
_GOLDEN = np.uint64(0x9E3779B97F4A7C15)
#: Element ``i``'s noise streams are disjoint blocks of one SplitMix64 sequence: its shot stream
#: from the state ``state0 + i·2³³·G``, its read stream ``2³²·G`` on (2³² draws each, so up to
#: 2³¹ elements a call never share a state).
_STREAM_G = np.uint64((0x9E3779B97F4A7C15 << 32) % 2**64)
_ELEMENT_G = np.uint64((0x9E3779B97F4A7C15 << 33) % 2**64)
_U53 = 1.0 / 9007199254740992.0
#: Pixels per work item of `sensor_measure` (a run of pixels through every plane).
MEASURE_CHUNK = 512


def _ziggurat_tables(layers: int = 1024) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The normal ziggurat's layer edges ``x`` (``layers + 1``; ``x[0]`` the base strip's
    equivalent width, ``x[1]`` the tail's start ``R``, ``x[layers] = 0``), ratios
    ``x[i+1] / x[i]`` and heights ``exp(−x²/2)``: Marsaglia and Tsang's construction for 1024
    equal-area layers of area ``V`` (``R`` and ``V`` solved in 40-digit arithmetic so the top
    layer closes; the same solve gives their published 128-layer and Doornik's 256-layer
    values). A first try is accepted 99.6 % of the time."""
    r, v = 4.038849846109505, 0.001226324646353088
    x = np.zeros(layers + 1)
    x[0], x[1] = v / math.exp(-0.5 * r * r), r
    for i in range(1, layers - 1):
        x[i + 1] = math.sqrt(-2.0 * math.log(v / x[i] + math.exp(-0.5 * x[i] * x[i])))
    return x, x[1:] / x[:-1], np.exp(-0.5 * x * x)


_ZIG_X, _ZIG_R, _ZIG_Y = _ziggurat_tables()
#: The first try's table ([`_first_try_table`][]): its bases and masks.
_X_BASE = np.float64(0.125).view(np.uint64)
_X_MASK = np.uint64((1 << 55) - 1)
_D_BASE = np.float64(2.0**-11).view(np.uint64)
_D_MASK = np.uint64(0x1FF << 47)


def _first_try_table() -> np.ndarray:
    """Each layer's edge ``x[i]`` and a lower bound of its ratio ``x[i+1]/x[i]`` in one 64-bit
    word, so a first try gathers one value instead of two: the edge's bits exactly, less those of
    0.125 (its six binades, 0.135 to 4.27, need 55 bits), and in the top 9 bits ``c`` with
    ``1 − d`` at most the ratio, ``d`` the double of bits ``bits(2⁻¹¹) + c·2⁴⁷`` (four exponent
    and five mantissa bits: ``1 − ratio`` rounded up by at most 1/32 of itself). A try between the
    bound and the ratio is flagged and rerun by the full sampler, which tests the exact ratio, so
    every draw is unchanged; the bound costs four tries in 10⁵ such a rerun (the ziggurat rejects
    430)."""
    x, ratio = _ZIG_X[:1024], _ZIG_R[:1024]
    edge = x.view(np.uint64) - _X_BASE
    gap = np.maximum(1.0 - ratio, 2.0**-11).view(np.uint64) - _D_BASE
    code = (gap + np.uint64((1 << 47) - 1)) >> np.uint64(47)  # rounded up
    while True:  # and up again where 1 − d rounds above the ratio
        over = 1.0 - ((code << np.uint64(47)) + _D_BASE).view(np.float64) > ratio
        if not over.any():
            break
        code[over] += np.uint64(1)
    assert (edge >> np.uint64(55) == 0).all() and (code < 512).all()
    return edge | (code << np.uint64(55))


_ZIG_P = _first_try_table()

if intrinsic is not None:

    @intrinsic
    def _as_float(typingctx, bits):
        """The float64 whose bits are the uint64 ``bits`` (a bit cast: free in a vector)."""

        def codegen(context, builder, signature, args):
            return builder.bitcast(args[0], context.get_value_type(numba_types.float64))

        return numba_types.float64(numba_types.uint64), codegen

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

    def _as_float(bits: np.uint64) -> float:
        return float(np.uint64(bits).view(np.float64))

    def _prefetch(array: np.ndarray, index: int) -> None:
        pass


@_inline
def _prefetch_span(array: np.ndarray, lo: int, hi: int) -> None:
    """[`_prefetch`][] of every 64-byte line of ``array[lo:hi]``."""
    for i in range(lo, hi, max(1, 64 // array.itemsize)):
        _prefetch(array, i)


@_inline
def _first_try_layer(i: int) -> tuple[float, float]:
    """Layer ``i``'s edge ``x[i]`` (exact) and a lower bound of its ratio, from one look-up of
    [`_first_try_table`][]."""
    word = _ZIG_P[i]
    edge = _as_float((word & _X_MASK) + _X_BASE)
    return edge, 1.0 - _as_float(((word >> np.uint64(8)) & _D_MASK) + _D_BASE)


@_inline
def _mix(z: np.uint64) -> np.uint64:
    """SplitMix64's finaliser: a counter to 64 well-mixed bits."""
    z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return z ^ (z >> np.uint64(31))


@_inline
def _uniform(state: np.uint64) -> tuple[float, np.uint64]:
    """The next double in ``(0, 1)`` of a SplitMix64 stream, and the advanced state."""
    state = state + _GOLDEN
    return ((_mix(state) >> np.uint64(11)) + 0.5) * _U53, state


@_inline
def _strip(bits: np.uint64) -> tuple[float, int]:
    """A ziggurat try from 64 bits: a uniform in ``(-1, 1)`` (the top 53 bits) and a layer
    (the lowest 10, which the uniform does not use)."""
    return ((bits >> np.uint64(11)) + 0.5) * (2.0 * _U53) - 1.0, np.int64(bits & np.uint64(1023))


@_inline
def _normal(state: np.uint64) -> tuple[float, np.uint64]:
    """A standard normal draw (the ziggurat: one 64-bit draw and a table look-up 99.6 % of the
    time; the wedges by rejection under the density, the tail beyond ``R`` by Marsaglia's
    exponential method), and the advanced state."""
    while True:
        state = state + _GOLDEN
        u, i = _strip(_mix(state))
        if abs(u) < _ZIG_R[i]:
            return u * _ZIG_X[i], state
        if i == 0:  # the tail |z| > R
            r = _ZIG_X[1]
            while True:
                a, state = _uniform(state)
                b, state = _uniform(state)
                t = -math.log(a) / r
                if -2.0 * math.log(b) > t * t:
                    return (r + t) if u > 0.0 else -(r + t), state
        z = u * _ZIG_X[i]
        v, state = _uniform(state)
        if _ZIG_Y[i] + v * (_ZIG_Y[i + 1] - _ZIG_Y[i]) < math.exp(-0.5 * z * z):
            return z, state


@_inline
def _log_poisson(mu: float, k: float) -> float:
    """``log p_k`` of a Poisson of mean ``mu`` (``k ≥ 0`` whole, a float: an integer's ``k⁵``
    overflows int64 above 6208, and wraps to 0 at multiples of 8192): ``lgamma`` below 10, above the
    cancellation-free Stirling form ``k·(log1p(v) − v) − δ(k) − ½·log(2πk)``, ``v = (mu − k)/k``,
    with ``δ`` to its ``k⁻⁵`` term (relative error below 1e-12 at ``k = 10``)."""
    if k < 10.0:
        return -mu + k * math.log(mu) - math.lgamma(k + 1.0)
    v = (mu - k) / k
    d = 1.0 / (12.0 * k)
    d = d - 4.8 * d * d * d + 1.0 / (1260.0 * k**5)
    return k * (math.log1p(v) - v) - d - 0.5 * math.log(2.0 * math.pi * k)


@_inline
def _modified_normal(mu: float, s: float, k: float) -> tuple[float, float]:
    """Ahrens and Dieter's modified normal at ``k`` (their procedure F): its exponent ``fx`` and
    factor ``fy`` (``fy·exp(fx)`` approximates ``p_k``)."""
    b1 = 0.041666666666666664 / mu
    b2 = 0.3 * b1 * b1
    c3 = 0.14285714285714285 * b1 * b2
    c2 = b2 - 15.0 * c3
    c1 = b1 - 6.0 * b2 + 45.0 * c3
    c0 = 1.0 - b1 + 3.0 * b2 - 15.0 * c3
    x = (k - mu + 0.5) / s
    x2 = x * x
    return -0.5 * x2, 0.3989422804014327 / s * (((c3 * x2 + c2) * x2 + c1) * x2 + c0)


@_inline
def _pd_step_i(mu: float, k: float) -> bool:
    """PD's immediate acceptance of the normal's ``k = ⌊mu + √mu z⌋`` (step I)."""
    return k >= np.floor(mu - 1.1484)


@_inline
def _pd_step_s(mu: float, k: float, u: float) -> bool:
    """PD's squeeze (step S) with the uniform ``u``: ``6 mu² u ≥ (mu − k)³``."""
    dm = mu - k
    return 6.0 * mu * mu * u >= dm * dm * dm


@_inline
def _poisson(mu: float, state: np.uint64) -> tuple[float, np.uint64]:
    """An exact Poisson draw, and the advanced state: multiplication of uniforms below 10, above
    Ahrens and Dieter's algorithm PD (1982; a normal draw accepted outright or by a squeeze
    about 99 % of the time at large means, else their exponential hat), its acceptance tests on
    the exact ``p_k`` of [`_log_poisson`][]."""
    if mu <= 0.0:
        return 0.0, state
    if not mu < math.inf:  # NaN or inf (allow_nonfinite): passed through, no count to draw
        return mu, state
    if mu < 10.0:
        limit, k = math.exp(-mu), 0.0
        prod, state = _uniform(state)
        while prod > limit:
            u, state = _uniform(state)
            prod *= u
            k += 1.0
        return k, state
    s = math.sqrt(mu)
    z, state = _normal(state)
    g = mu + s * z
    if g >= 0.0:
        k = np.floor(g)  # a float, as _log_poisson needs (numba's math.floor gives an integer)
        if _pd_step_i(mu, k):
            return k, state
        u, state = _uniform(state)
        if _pd_step_s(mu, k, u):
            return k, state
        fx, fy = _modified_normal(mu, s, k)
        if fy * (1.0 - u) <= math.exp(_log_poisson(mu, k) - fx):  # step Q
            return k, state
    while True:  # steps E and H
        u, state = _uniform(state)
        e = -math.log(u)
        u, state = _uniform(state)
        u = 2.0 * u - 1.0
        t = 1.8 + (e if u >= 0.0 else -e)
        if t <= -0.6744:
            continue
        k = np.floor(mu + s * t)
        fx, fy = _modified_normal(mu, s, k)
        if 0.1069 / mu * abs(u) <= math.exp(_log_poisson(mu, k) + e) - fy * math.exp(fx + e):
            return k, state


@_inline
def _first_tries(mu: float, shot: np.uint64, read: np.uint64) -> tuple[float, float, float, bool, bool, bool]:
    """What [`_poisson`][] and [`_normal`][] return when their first tries succeed, without a
    branch (so whole runs of pixels vectorise), for a mean ``mu ≥ 0``: the Poisson draw
    (steps N, I, S), the shot stream's normal draw scaled to ``mu + √mu·z``, the read stream's
    normal, and whether each is valid (the normals', the Poisson's given its normal's; never for
    an infinite mean, whose floor is no count; a normal's try tests a lower bound of its layer's
    ratio, [`_first_try_layer`][]); where one is not, the caller runs the full algorithms,
    which return exactly these values where they are."""
    u1, i1 = _strip(_mix(shot + _GOLDEN))
    x1, r1 = _first_try_layer(i1)
    g = mu + math.sqrt(mu) * (u1 * x1)
    k = np.floor(g)  # a float: no round trip through an integer
    u2, _ = _uniform(shot + _GOLDEN)  # the draw after the normal's
    ok_k = (mu >= 10.0) & (mu < math.inf) & (g >= 0.0) & (_pd_step_i(mu, k) | _pd_step_s(mu, k, u2))
    u3, i3 = _strip(_mix(read + _GOLDEN))
    x3, r3 = _first_try_layer(i3)
    return k, g, u3 * x3, abs(u1) < r1, ok_k, abs(u3) < r3


@_inline
def _recorded(e: float, full: float, zero: float, inv: float, params: np.ndarray, output: int) -> float:
    """Electrons ``e`` of a pixel after its full well ``full``, as ``output`` asks (0: the ISP's
    radiance ``(DN − zero)·inv``, 1: electrons, 2: DN), the ADC rounding half to even like
    ``torch.round``."""
    gain, black, top = params[7], params[8], params[9]
    e = min(e, full)
    dn = gain * e + black
    dn = min(max(np.rint(dn), 0.0), top) if top < np.inf else dn
    return e if output == 1 else (dn if output == 2 else (dn - zero) * inv)


@_inline
def _pixel_constants(a: float, params: np.ndarray) -> tuple[float, float, float, float, float]:
    """A pixel of ``a`` µm²'s electrons per unit mean, dark electrons and full well, and the ISP's
    offset and reciprocal gain (before the fixed patterns): the one formula of the main loop and
    the rescan of `sensor_measure`."""
    light, eta, dark_um2 = params[0], params[1], params[4]
    full_um2, gain, black = params[6], params[7], params[8]
    zero = black + gain * dark_um2 * a  # the ISP subtracts the mean dark signal ...
    inv = 1.0 / (gain * eta * light * a)  # ... and divides by the nominal response
    return eta * light * a, dark_um2 * a, full_um2 * a, zero, inv


@_inline
def _noisy_run(
    row: np.ndarray,
    flags: np.ndarray,
    scale: np.ndarray,
    dark: np.ndarray,
    full: np.ndarray,
    zero: np.ndarray,
    inv: np.ndarray,
    params: np.ndarray,
    key: np.uint64,
    poisson: bool,
    read: float,
    output: int,
) -> None:
    """[`_measure_run`][] with noise, Poisson or Gaussian: each draw's first try
    ([`_first_tries`][]), ``flags[j]`` set where one was rejected and that element's mean left
    in ``row`` for the rescan. Called with ``poisson`` a constant, so each kind of noise gets a
    loop of its own with no test of it inside."""
    for j in range(row.size):
        mean = row[j]
        e = mean * scale[j] + dark[j]
        shot_key = key + np.uint64(j) * _ELEMENT_G
        mu = max(e, 0.0)
        k, g, z2, ok_z1, ok_k, ok_z2 = _first_tries(mu, shot_key, shot_key + _STREAM_G)
        shot = k if poisson else g + (e - mu)  # Gaussian: e + √max(e, 0)·z, bit for bit
        flag = (not (ok_z1 and (ok_k or not poisson))) | (not ok_z2 and read != 0.0)
        flags[j] = flag
        value = _recorded(shot + read * z2, full[j], zero[j], inv[j], params, output)
        row[j] = mean if flag else value


@_inline
def _measure_run(
    row: np.ndarray,
    flags: np.ndarray,
    scale: np.ndarray,
    dark: np.ndarray,
    full: np.ndarray,
    zero: np.ndarray,
    inv: np.ndarray,
    params: np.ndarray,
    key: np.uint64,
    noise: int,
    read: float,
    output: int,
) -> None:
    """One plane of a run of `sensor_measure`: the means ``row`` measured in place, the pixel
    constants from [`_pixel_constants`][], ``key`` the first element's shot
    stream. Without noise a loop with no draws; with noise [`_noisy_run`][]. Each loop is
    branch-free and vectorises."""
    if noise == 0:
        for j in range(row.size):
            e = row[j] * scale[j] + dark[j]
            row[j] = _recorded(e, full[j], zero[j], inv[j], params, output)
    elif noise == 1:
        _noisy_run(row, flags, scale, dark, full, zero, inv, params, key, True, read, output)
    else:
        _noisy_run(row, flags, scale, dark, full, zero, inv, params, key, False, read, output)


@_serial
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


@_jit
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
    """[`layoutwarp.physics.measure`][] in one pass: means ``(N, P)`` to ``out`` ``(N, P)``, of
    their dtype, which may be ``mean`` itself (measured in place, one buffer less; no other
    overlap).

    ``params``: photons per µm² × fill factor, η, PRNU, DSNU, dark e⁻/µm², read noise, full well
    per µm² (``inf``: none), gain K, black level, ADC top (``inf``: no ADC); ``prnu``/``dsnu``
    are read only where their gains are not 0 (empty arrays will do). ``noise``: 0 none,
    1 Poisson, 2 Gaussian; ``output``: 0 radiance, 1 electrons, 2 DN. Element ``i`` (row-major)
    draws its shot noise and its read noise from two streams of its own, disjoint blocks of one
    SplitMix64 sequence seeded by ``seed`` ([`_ELEMENT_G`][]), so the result does not depend
    on the thread count.

    Thread ``t`` of ``threads`` (see [`threads`][]) takes the pixels ``[t·P/T, (t + 1)·P/T)``,
    the share of a ``prange`` over them that the same thread had in the forward just before, in
    runs of [`MEASURE_CHUNK`][] pixels through all ``N`` planes, with work space of its own. The
    forward's streams (tens of MB) push most of its output out of the caches, so the thread first
    hints its first two runs' inputs to the caches, and each run those of the run after next
    ([`_prefetch_inputs`][]). A run then derives its pixels' constants
    ([`_pixel_constants`][], then the fixed patterns). Per plane, its means copied to ``out``
    first where that is another buffer (so every loop works in place, with no overlap to test), a
    branch-free loop ([`_measure_run`][]) takes every draw's first try and flags the elements
    where one was rejected (about 0.4 % of the normals, a few tenths of a percent of the Poisson
    draws at large means, all of them below a mean of 10 electrons), which keep their means. After
    its last run the thread rescans its flags, eight a word, and reruns a full sampler there from
    the start of its stream: the rare slow path in one tight loop, whose code and branch history
    stay warm (a rescan after every run made the kernel 5–25 % slower).
    """
    g_prnu, g_dsnu, read = params[2], params[3], params[5]
    n, p = mean.shape
    state0 = _mix(np.uint64(seed) * _GOLDEN + np.uint64(0x632BE59BD9B4E019))
    poisson, in_place = noise == 1, out.ctypes.data == mean.ctypes.data
    for thread in prange(threads):  # each thread its work space, and its share of the pixels
        c = MEASURE_CHUNK
        scale, dark, full, zero, inv = np.empty(c), np.empty(c), np.empty(c), np.empty(c), np.empty(c)
        start, stop = thread * p // threads, (thread + 1) * p // threads
        share = stop - start
        words = np.zeros((n * share + 7) // 8 if noise != 0 else 0, dtype=np.uint64)
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
                    row[:] = mean[r, lo : lo + m]
                flags = redo[r * share + lo - start : r * share + lo - start + m]
                key = state0 + np.uint64(r * p + lo) * _ELEMENT_G  # the run's first shot stream
                _measure_run(row, flags, scale, dark, full, zero, inv, params, key, noise, read, output)
        for b in range(words.size):  # the rescan
            if words[b] == 0:
                continue
            for f in range(8 * b, min(n * share, 8 * b + 8)):
                if redo[f] == 0:
                    continue
                r, i = f // share, start + f % share
                sc, dk, fw, zr, iv = _pixel_constants(area_um2[i], params)
                if g_prnu != 0.0:
                    sc = sc * (1.0 + g_prnu * prnu[i])
                if g_dsnu != 0.0:
                    dk = dk + g_dsnu * dsnu[i]
                e = mean[r, i] * sc + dk
                key = state0 + np.uint64(r * p + i) * _ELEMENT_G
                mu = max(e, 0.0)
                k, g, z2, ok_z1, ok_k, ok_z2 = _first_tries(mu, key, key + _STREAM_G)
                shot = k if poisson else g + (e - mu)
                if not (ok_z1 and (ok_k or not poisson)):  # from the start of the shot stream
                    if poisson:
                        shot, _ = _poisson(mu, key)
                    else:
                        z, _ = _normal(key)
                        shot = e + math.sqrt(mu) * z
                if not ok_z2 and read != 0.0:
                    z2, _ = _normal(key + _STREAM_G)
                out[r, i] = _recorded(shot + read * z2, fw, zr, iv, params, output)


@_inline
def _csr_row(lo: int, hi: int, indices: np.ndarray, data: np.ndarray, x: np.ndarray, k: int, m: int):
    """One CSR row's products with planes ``k .. k + m − 1`` (``m ≤ 4``) in one pass over the row,
    in float64 (a pixel's sum stays within an ulp or two of its values); unused sums are 0."""
    a0 = a1 = a2 = a3 = 0.0
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


@_jit
def csr_apply(
    indptr: np.ndarray, indices: np.ndarray, data: np.ndarray, x: np.ndarray, out: np.ndarray
) -> int:
    """``out[n] = W @ x[n]`` for a CSR matrix ``W`` (``(R, M)``) and planes ``x`` ``(N, M)`` (the
    fixed-layout area weights of [`AreaResampler`][layoutwarp.resampler.AreaResampler]), rows dealt to
    the threads:
    each row of ``W`` is read once for every four planes (RGB: once; 2.3x faster than once per
    plane at 2048x1024 → 257x129). Returns how many of the values written are not finite (NaN
    or ±inf): the finiteness check of [`simulate`][layoutwarp.sensor.simulate] while they are in registers
    (a pass over ``out`` afterwards cost about 3 % of the call)."""
    n = x.shape[0]
    bad = 0
    for r in prange(indptr.shape[0] - 1):
        lo, hi = indptr[r], indptr[r + 1]
        for k in range(0, n, 4):
            m = min(4, n - k)
            sums = _csr_row(lo, hi, indices, data, x, k, m)
            for q in range(m):
                out[k + q, r] = sums[q]
                if not np.isfinite(out[k + q, r]):
                    bad += 1
    return bad


@_serial
def measured_csr_apply(
    indptr: np.ndarray, indices: np.ndarray, data: np.ndarray, x: np.ndarray, mean: np.ndarray, *measure
) -> int:
    """[`csr_apply`][] into ``mean``, then `sensor_measure` of ``mean`` with its other
    arguments ``measure`` (``area_um2, …, out, threads``): a fixed layout's exact forward with
    sensor physics in one call from Python, no interpreter between the two launches, each thread
    measuring the rows it has just summed. Returns [`csr_apply`][]'s count of non-finite
    means (the measurement passes NaN and ±inf through)."""
    bad = csr_apply(indptr, indices, data, x, mean)
    sensor_measure(mean, *measure)
    return bad
