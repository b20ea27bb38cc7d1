"""The exact integrator's kernels: prefix tables, the segment walk of Green's
theorem, the forward and the backward.

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
pixel edge), launched by [`layoutwarp.kernels.device.cuda_launch`][] from the sources in
[`layoutwarp.kernels.exact_cuda`][].
"""

from __future__ import annotations

import math

import numpy as np

from .base import CHUNK, inline, run_shares, serial
from .prefix import band_prefix

__all__ = [
    "WHOLE_TABLE_BYTES",
    "band_rows",
    "cell_piece",
    "edge_sum",
    "exact_backward",
    "exact_forward",
    "exact_forward_banded",
    "row_piece",
    "row_span",
    "segment_forward",
    "segment_moments",
    "segment_moments_from_python",
    "segment_weights",
]


@inline
def row_span(y0: float, y1: float, h: int) -> tuple[int, int]:
    """The source rows a segment from ``y0`` to ``y1`` crosses, clamped to the image."""
    ylo, yhi = min(y0, y1), max(y0, y1)
    r0 = min(max(math.floor(ylo), 0), h - 1)
    return r0, max(min(max(math.ceil(yhi) - 1, 0), h - 1), r0)


@inline
def _cell(incl: np.ndarray, row: int, col: int, k: int, block: int) -> float:
    """The box image value ``I(c) − I(c − 1)`` of the prefix table at ``(row, col)``."""
    cur = np.float64(incl[row, col, k])
    return cur if col % block == 0 else cur - np.float64(incl[row, col - 1, k])


@inline
def row_piece(
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


@inline
def cell_piece(
    col: int, x0: float, inv_dx: float, t_lo: float, t_hi: float, c0: int, c1: int
) -> tuple[float, float]:
    """The parameter range inside column ``col`` of a row piece ([`row_piece`][]): from the
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


@inline
def _other_cell(row: int, col: int, x0: float, y0: float, flat: bool, vertical: bool) -> tuple[int, int]:
    """The cell across the line a piece in cell ``(row, col)`` lies on, or that cell itself: a
    flat segment on a row line (``y0 == row``) faces the row above, a vertical one on a column
    line (``x0 == col``) the column to its left (none beyond the image). Where the two differ,
    the backward's image value is the mean of both cells (the symmetric derivative)."""
    row2 = row - 1 if (flat and y0 == row and row > 0) else row
    col2 = col - 1 if (vertical and x0 == col and col > 0) else col
    return row2, col2


@inline
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
        t_lo, t_hi, c0, c1, inv_dx = row_piece(row, x0, y0, dxv, inv_dy, ylo, yhi, False, w)
        rr = row - ra
        for col in range(c0, c1 + 1):
            t0, t1 = cell_piece(col, x0, inv_dx, t_lo, t_hi, c0, c1)
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


@inline
def segment_forward(
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
    r0, r1 = row_span(y0, y1, h)
    _segment_rows(x0, y0, x1, y1, r0, r1, 0, incl, offsets, block, w, per_seg, s, False, per_seg, per_seg)


@inline
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
    function for other kernels ([`mesh_integrals`][layoutwarp.kernels.mesh.mesh_integrals]): the segment's
    weights in [`exact_backward`][] are ``grad[N, e]/2 + Σ_n grad[n, e]·m[n]``."""
    h, w, n = incl.shape
    acc[0, :] = 0.0
    ma[0, :] = 0.0
    mb[0, :] = 0.0
    if y1 == y0:  # no ∫ P dY, but moments along the row line
        _segment_moments(x0, y0, x1, y1, incl, block, ma, mb)
        return
    acc[0, n] = (y1 - y0) * (x0 + x1) / 2
    r0, r1 = row_span(y0, y1, h)
    _segment_rows(x0, y0, x1, y1, r0, r1, 0, incl, offsets, block, w, acc, 0, True, ma, mb)


@serial
def segment_moments_from_python(
    x0: float, y0: float, x1: float, y1: float, incl: np.ndarray, offsets: np.ndarray, block: int,
    acc: np.ndarray, ma: np.ndarray, mb: np.ndarray,
) -> None:  # fmt: skip
    """[`segment_moments`][] for calls from Python (``layoutwarp.kernels.segment_moments`` is this
    one): the kernels' helpers are compiled for kernels only, without a Python wrapper, and a
    function of their own is needed for one with it (numba's disk cache tells two builds of one
    function apart by their arguments' types only)."""
    segment_moments(x0, y0, x1, y1, incl, offsets, block, acc, ma, mb)


@inline
def edge_sum(e: int, per_seg: np.ndarray, edge_offsets: np.ndarray, out: np.ndarray) -> None:
    """Add edge ``e``'s segments ``per_seg[s, :]`` into ``out[:, e]``, in order."""
    for s in range(edge_offsets[e], edge_offsets[e + 1]):
        for k in range(per_seg.shape[1]):
            out[k, e] += per_seg[s, k]


@serial
def _edge_sums_share(t: int, nt: int, per_seg: np.ndarray, edge_offsets: np.ndarray, out: np.ndarray) -> None:
    e_count = edge_offsets.shape[0] - 1
    for e in range(t * e_count // nt, (t + 1) * e_count // nt):
        edge_sum(e, per_seg, edge_offsets, out)


@serial
def _forward_share(
    t: int, nt: int, verts: np.ndarray, seg_start: np.ndarray, seg_end: np.ndarray, incl: np.ndarray,
    offsets: np.ndarray, block: int, per_seg: np.ndarray,
) -> None:  # fmt: skip
    s_count = seg_start.shape[0]
    for chunk in range(t, (s_count + CHUNK - 1) // CHUNK, nt):
        for s in range(chunk * CHUNK, min((chunk + 1) * CHUNK, s_count)):
            segment_forward(s, verts, seg_start, seg_end, incl, offsets, block, per_seg)


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
    image's [`prefix_tables`][layoutwarp.kernels.prefix.prefix_tables]. Each segment is cut at
    source rows, then each row piece at columns; a piece in cell ``(r, c)`` with mid-``X``
    fraction ``f`` adds ``ΔY · P_r(c + f)``, where ``P_r`` interpolates the prefix table
    linearly inside the cell: ``P_r(c + f) = offset + I(c − 1) + f · (I(c) − I(c − 1))``, exact
    for the box image ``L(c) = I(c) − I(c − 1)``. Row ``N`` sums to the pixel areas.
    ``threads``: shares of the segments, dealt in chunks in turn (see
    [`run_shares`][layoutwarp.kernels.base.run_shares]); then each edge's
    segments are summed in order.
    """
    per_seg = np.zeros((seg_start.shape[0], incl.shape[2] + 1), dtype=np.float64)
    run_shares(_forward_share, threads, verts, seg_start, seg_end, incl, offsets, block, per_seg)
    out = np.zeros((per_seg.shape[1], edge_offsets.shape[0] - 1), dtype=np.float64)
    run_shares(_edge_sums_share, threads, per_seg, edge_offsets, out)
    return out


@serial
def _band_counts(
    verts: np.ndarray, seg_start: np.ndarray, seg_end: np.ndarray, h: int, band: int, first: np.ndarray
) -> None:
    """The first half of [`_bands`][]' counting sort: ``first[b + 1]`` the segments band ``b`` lists,
    then summed (``first`` zeroed)."""
    for s in range(seg_start.shape[0]):
        y0, y1 = verts[seg_start[s], 1], verts[seg_end[s], 1]
        if y1 != y0:
            r0, r1 = row_span(y0, y1, h)
            for b in range(r0 // band, r1 // band + 1):
                first[b + 1] += 1
    for b in range(first.shape[0] - 1):
        first[b + 1] += first[b]


@serial
def _band_lists(
    verts: np.ndarray, seg_start: np.ndarray, seg_end: np.ndarray, h: int, band: int, fill: np.ndarray,
    listed: np.ndarray,
) -> None:  # fmt: skip
    """The second half: each segment into the lists of its bands (``fill``: where each band's next
    goes, from ``first[:-1]``)."""
    for s in range(seg_start.shape[0]):
        y0, y1 = verts[seg_start[s], 1], verts[seg_end[s], 1]
        if y1 != y0:
            r0, r1 = row_span(y0, y1, h)
            for b in range(r0 // band, r1 // band + 1):
                listed[fill[b]] = s
                fill[b] += 1


def _bands(verts: np.ndarray, seg_start: np.ndarray, seg_end: np.ndarray, h: int, band: int) -> tuple:
    """The segments listed per band of ``band`` rows (a counting sort; a segment crossing several
    bands is listed in each): ``(first, listed)``, band ``b``'s at ``listed[first[b] .. first[b + 1]]``."""
    first = np.zeros((h + band - 1) // band + 1, dtype=np.int64)
    _band_counts(verts, seg_start, seg_end, h, band, first)
    listed = np.empty(first[-1], dtype=np.int64)
    _band_lists(verts, seg_start, seg_end, h, band, first[:-1].copy(), listed)
    return first, listed


@serial
def _banded_share(
    t: int, nt: int, verts: np.ndarray, seg_start: np.ndarray, seg_end: np.ndarray, seg_edge: np.ndarray,
    image: np.ndarray, block: int, band: int, first: np.ndarray, listed: np.ndarray, sums: np.ndarray,
    incls: np.ndarray, offsetss: np.ndarray,
) -> None:  # fmt: skip
    """Thread ``t``'s bands (in turn), each one's prefix table built in its buffers ``incls[t]``,
    ``offsetss[t]`` (``(T, band, W, N)``, ``(T, band, ⌈W/block⌉, N)``) and every piece in those
    rows added to its own per-edge sums ``sums[t]``."""
    h, w = image.shape[1], image.shape[2]
    incl, offsets = incls[t], offsetss[t]
    out_t = sums[t]
    for bi in range(t, first.shape[0] - 1, nt):
        ra = bi * band
        rb = min(h, ra + band)
        band_prefix(image, ra, rb, block, incl, offsets)
        for j in range(first[bi], first[bi + 1]):
            s = listed[j]
            x0, y0 = verts[seg_start[s], 0], verts[seg_start[s], 1]
            x1, y1 = verts[seg_end[s], 0], verts[seg_end[s], 1]
            r0, r1 = row_span(y0, y1, h)
            rlo, rhi = max(r0, ra), min(r1, rb - 1)
            e = seg_edge[s]
            _segment_rows(
                x0, y0, x1, y1, rlo, rhi, ra, incl, offsets, block, w, out_t, e, False, out_t, out_t
            )


@serial
def _banded_total_share(
    t: int, nt: int, verts: np.ndarray, seg_start: np.ndarray, seg_end: np.ndarray, edge_offsets: np.ndarray,
    sums: np.ndarray, out: np.ndarray,
) -> None:  # fmt: skip
    """Edges ``t·E/T ..``: the threads' sums in order, and each edge's ``∫ X dY``."""
    e_count, n = sums.shape[1], sums.shape[2]
    for e in range(t * e_count // nt, (t + 1) * e_count // nt):
        for k in range(n):
            for r in range(sums.shape[0]):
                out[k, e] += sums[r, e, k]
        for s in range(edge_offsets[e], edge_offsets[e + 1]):
            x0, y0 = verts[seg_start[s], 0], verts[seg_start[s], 1]
            x1, y1 = verts[seg_end[s], 0], verts[seg_end[s], 1]
            out[n, e] += (y1 - y0) * (x0 + x1) / 2


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
    e_count = edge_offsets.shape[0] - 1
    first, listed = _bands(verts, seg_start, seg_end, h, band)
    sums = np.zeros((threads, e_count, n), dtype=np.float64)
    tables = np.empty((threads, band, w, n), image.dtype), np.empty((threads, band, -(-w // block), n))
    segs = (verts, seg_start, seg_end)
    run_shares(_banded_share, threads, *segs, seg_edge, image, block, band, first, listed, sums, *tables)
    out = np.zeros((n + 1, e_count), dtype=np.float64)
    run_shares(_banded_total_share, threads, *segs, edge_offsets, sums, out)
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


@inline
def segment_weights(
    s: int,
    verts: np.ndarray,
    seg_start: np.ndarray,
    seg_end: np.ndarray,
    seg_edge: np.ndarray,
    incl: np.ndarray,
    block: int,
    grad: np.ndarray,
) -> tuple[float, float]:
    """Segment ``s``'s Reynolds weights ``(wa, wb)`` (see [`exact_backward`][]): a per-segment
    function for other kernels too (the device mesh's θ-gradient,
    [`layoutwarp.kernels.mesh`][])."""
    h, w, n = incl.shape
    e = seg_edge[s]
    x0, y0 = verts[seg_start[s], 0], verts[seg_start[s], 1]
    x1, y1 = verts[seg_end[s], 0], verts[seg_end[s], 1]
    dxv, dyv = x1 - x0, y1 - y0
    wa = wb = grad[n, e] / 2  # the area row: ∫ (1 − t) dt = ∫ t dt = 1/2
    flat, vertical = dyv == 0.0, dxv == 0.0
    inv_dy = 1.0 / dyv if not flat else 1.0
    ylo, yhi = min(y0, y1), max(y0, y1)
    r0, r1 = row_span(y0, y1, h)
    for row in range(r0, (r0 if flat else r1) + 1):
        t_lo, t_hi, c0, c1, inv_dx = row_piece(row, x0, y0, dxv, inv_dy, ylo, yhi, flat, w)
        for col in range(c0, c1 + 1):
            t0, t1 = cell_piece(col, x0, inv_dx, t_lo, t_hi, c0, c1)
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
            wa += gl * ((t1 - t0) - m1)
            wb += gl * m1
    return wa, wb


@inline
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
    [`segment_weights`][] before any gradient is known."""
    h, w, n = incl.shape
    dxv, dyv = x1 - x0, y1 - y0
    flat, vertical = dyv == 0.0, dxv == 0.0
    inv_dy = 1.0 / dyv if not flat else 1.0
    ylo, yhi = min(y0, y1), max(y0, y1)
    r0, r1 = row_span(y0, y1, h)
    for row in range(r0, (r0 if flat else r1) + 1):
        t_lo, t_hi, c0, c1, inv_dx = row_piece(row, x0, y0, dxv, inv_dy, ylo, yhi, flat, w)
        for col in range(c0, c1 + 1):
            t0, t1 = cell_piece(col, x0, inv_dx, t_lo, t_hi, c0, c1)
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


@serial
def _backward_share(
    t: int, nt: int, verts: np.ndarray, seg_start: np.ndarray, seg_end: np.ndarray, seg_edge: np.ndarray,
    incl: np.ndarray, block: int, grad: np.ndarray, wa: np.ndarray, wb: np.ndarray,
) -> None:  # fmt: skip
    s_count = seg_start.shape[0]
    for chunk in range(t, (s_count + CHUNK - 1) // CHUNK, nt):
        for s in range(chunk * CHUNK, min((chunk + 1) * CHUNK, s_count)):
            wa[s], wb[s] = segment_weights(s, verts, seg_start, seg_end, seg_edge, incl, block, grad)


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
    wa = np.zeros(seg_start.shape[0], dtype=np.float64)
    wb = np.zeros(seg_start.shape[0], dtype=np.float64)
    run_shares(_backward_share, threads, verts, seg_start, seg_end, seg_edge, incl, block, grad, wa, wb)
    return wa, wb
