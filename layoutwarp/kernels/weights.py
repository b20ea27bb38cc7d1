"""A fixed layout's area weights built as [`Runs`][layoutwarp.kernels.runs.Runs] straight from its
pixel mesh: each sensor pixel on its own, its boundary walked through the source cells.

Green's theorem gives a pixel's integral as ``Σ ΔY · (Σ_{c' < c} L[r, c'] + f · L[r, c])`` over
the single-cell pieces ``(r, c, ΔY, f)`` of its boundary (the pieces of
[`layoutwarp.kernels.exact`][], cut by the same functions). As weights of the cells of row ``r``
that is a step function of the column: ``ΔY (f − 1)`` added at ``c`` and ``−ΔY f`` at ``c + 1``
(the pieces of a closed boundary in one row sum to ``ΔY = 0``, so the constant parts cancel). A
pixel's steps are added into a dense buffer over its bounding box of cells, and a running sum
along each row gives every cell's weight; cells whose weight is within [`ZERO`][] of 0 lie
outside the pixel. Weights within [`WHOLE`][layoutwarp.kernels.runs.WHOLE] of ``1 / area`` mark
whole cells; the others are cut, and the runs are cut as
[`Runs.of`][layoutwarp.kernels.runs.Runs.of] cuts them, so both give the same runs from the same
weights.

Three passes over the pixels, block by block of sensor rows, each thread taking a contiguous range
of a block: the first finds each pixel's box of cells, the second counts its runs and cut cells,
the third writes them where the counts' prefix sums put them. Nothing is held besides the result
but the boxes and one box of float64 per thread. Computed in float64; the cut weights are kept in
float32.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator

import numpy as np

from .base import inline, own, per_thread, run_shares, serial
from .exact import cell_piece, row_piece, row_span
from .runs import WHOLE, Runs

__all__ = ["BLOCK_PIXELS", "EDGE_SLACK", "ZERO", "build_runs"]

#: A cell whose weight (unnormalised, in source cells) is at most this far from 0 is outside the
#: pixel: the steps of a pixel's boundary cancel there to rounding.
ZERO = 1e-12
#: How far (relative to ``X``) a piece's interpolated ``X`` may round past its segment's ends.
EDGE_SLACK = 1e-12


@inline
def _edge(k: int, side: int, h: int, w: int) -> tuple[int, float]:
    """Pixel ``k``'s edge on ``side`` (0 top, 1 right, 2 bottom, 3 left) and its sign: the top
    and right edges add their integral, the bottom and left ones subtract it
    ([`MeshTopology`][layoutwarp.topology.MeshTopology]'s numbering)."""
    i, j = k // w, k % w
    if side == 0:
        return i * w + j, 1.0
    if side == 2:
        return (i + 1) * w + j, -1.0
    return (h + 1) * w + i * (w + 1) + j + (1 if side == 1 else 0), (1.0 if side == 1 else -1.0)


@inline
def _box(
    k: int, h: int, w: int, hs: int, ws: int, verts: np.ndarray, seg_start: np.ndarray, seg_end: np.ndarray,
    edge_offsets: np.ndarray,
) -> tuple[int, int, int, int]:  # fmt: skip
    """Pixel ``k``'s rows ``rlo .. rhi`` and columns ``clo .. chi`` of source cells: the rows its
    segments' walks take ([`row_span`][layoutwarp.kernels.exact.row_span] of their ends, exactly),
    and the columns of its vertices' extent widened by [`EDGE_SLACK`][] each way (a piece's ``X``,
    interpolated, can round past an end's into the next column)."""
    xlo, xhi = math.inf, -math.inf
    rlo, rhi = hs, 0
    for side in range(4):
        e = _edge(k, side, h, w)[0]
        for s in range(edge_offsets[e], edge_offsets[e + 1]):
            x0, y0 = verts[seg_start[s], 0], verts[seg_start[s], 1]
            x1, y1 = verts[seg_end[s], 0], verts[seg_end[s], 1]
            r0, r1 = row_span(y0, y1, hs)
            rlo, rhi = min(rlo, r0), max(rhi, r1)
            xlo, xhi = min(xlo, x0, x1), max(xhi, x0, x1)
    slack = EDGE_SLACK * max(1.0, abs(xlo), abs(xhi))
    clo = min(max(math.floor(xlo - slack), 0), ws - 1)
    chi = max(min(math.ceil(xhi + slack) - 1, ws - 1), clo)
    return min(rlo, rhi), rhi, clo, chi


@inline
def _add_steps(
    k: int, h: int, w: int, hs: int, ws: int, verts: np.ndarray, seg_start: np.ndarray, seg_end: np.ndarray,
    edge_offsets: np.ndarray, buf: np.ndarray, rlo: int, rhi: int, clo: int, chi: int,
) -> None:  # fmt: skip
    """Add pixel ``k``'s steps into ``buf``, its box ``rlo .. rhi`` × ``clo .. chi + 1`` row by
    row (the column past ``chi`` takes the last cells' ``−ΔY f``)."""
    width = chi - clo + 2
    for side in range(4):
        e, sign = _edge(k, side, h, w)
        for s in range(edge_offsets[e], edge_offsets[e + 1]):
            x0, y0 = verts[seg_start[s], 0], verts[seg_start[s], 1]
            x1, y1 = verts[seg_end[s], 0], verts[seg_end[s], 1]
            if y1 == y0:
                continue  # ΔY = 0 adds nothing
            dxv, dyv = x1 - x0, y1 - y0
            inv_dy = 1.0 / dyv
            ylo, yhi = min(y0, y1), max(y0, y1)
            r0, r1 = row_span(y0, y1, hs)
            for row in range(r0, r1 + 1):
                t_lo, t_hi, c0, c1, inv_dx = row_piece(row, x0, y0, dxv, inv_dy, ylo, yhi, False, ws)
                at_row = (min(max(row, rlo), rhi) - rlo) * width
                for col in range(c0, c1 + 1):
                    t0, t1 = cell_piece(col, x0, inv_dx, t_lo, t_hi, c0, c1)
                    v = sign * (t1 - t0) * dyv
                    frac = min(max(x0 + (t0 + t1) / 2 * dxv - col, 0.0), 1.0)
                    at = at_row + min(max(col, clo), chi) - clo
                    buf[at] += v * (frac - 1.0)
                    buf[at + 1] -= v * frac


@inline
def _close(j: int, length: int, head: int, wholes: int, run_len: np.ndarray, run_head: np.ndarray,
           run_tail: np.ndarray) -> None:  # fmt: skip
    """Run ``j``'s length and its cut cells at each end: all head where it has no whole cell."""
    run_len[j] = length
    run_head[j] = head if wholes > 0 else length
    run_tail[j] = length - head - wholes if wholes > 0 else 0


@inline
def _pixel_runs(
    k: int, buf: np.ndarray, rlo: int, rhi: int, clo: int, chi: int, ws: int, inv_area: float, cells: float,
    fill: bool, r_at: int, c_at: int, run_start: np.ndarray, run_len: np.ndarray, run_head: np.ndarray,
    run_tail: np.ndarray, cut_weight: np.ndarray,
) -> tuple[int, int]:  # fmt: skip
    """Sum pixel ``k``'s steps along each row of its box (zeroing ``buf`` for the next pixel) and
    cut its cells into runs; with ``fill``, write them from run ``r_at`` and cut cell ``c_at``.
    Returns the pixel's number of runs and of cut cells."""
    width = chi - clo + 2
    runs = cuts = 0
    length = head = wholes = 0
    for rr in range(rhi - rlo + 1):
        cum = 0.0
        span = seen = prev_whole = False  # in a span of contiguous cells; a whole cell in it
        for cc in range(width):
            cum += buf[rr * width + cc]
            buf[rr * width + cc] = 0.0
            col = clo + cc
            if col >= ws or abs(cum) <= ZERO:
                span = False  # outside the pixel: a gap
                continue
            wv = cum * inv_area
            whole = abs(wv * cells - 1.0) <= WHOLE
            if not span or (whole and not prev_whole and seen):  # a new run
                if runs > 0 and fill:
                    _close(r_at + runs - 1, length, head, wholes, run_len, run_head, run_tail)
                if fill:
                    run_start[r_at + runs] = (rlo + rr) * ws + col
                runs += 1
                length = head = wholes = 0
                seen = seen and span
                span = True
            length += 1
            if whole:
                wholes += 1
                seen = True
            else:
                if wholes == 0:
                    head += 1
                if fill:
                    cut_weight[c_at + cuts] = wv
                cuts += 1
            prev_whole = whole
    if runs > 0 and fill:
        _close(r_at + runs - 1, length, head, wholes, run_len, run_head, run_tail)
    return runs, cuts


@serial
def _box_share(
    t: int, nt: int, k0: int, k1: int, h: int, w: int, hs: int, ws: int, verts: np.ndarray,
    seg_start: np.ndarray, seg_end: np.ndarray, edge_offsets: np.ndarray, box: np.ndarray,
) -> int:  # fmt: skip
    """The boxes ``(R, 4)`` of thread ``t``'s share of pixels ``k0 .. k1 - 1``; returns the
    largest one's cells."""
    most = 0
    for k in range(k0 + t * (k1 - k0) // nt, k0 + (t + 1) * (k1 - k0) // nt):
        rlo, rhi, clo, chi = _box(k, h, w, hs, ws, verts, seg_start, seg_end, edge_offsets)
        box[k, 0], box[k, 1], box[k, 2], box[k, 3] = rlo, rhi, clo, chi
        most = max(most, (rhi - rlo + 1) * (chi - clo + 2))
    return most


@serial
def _runs_share(
    t: int, nt: int, k0: int, k1: int, h: int, w: int, hs: int, ws: int, verts: np.ndarray,
    seg_start: np.ndarray, seg_end: np.ndarray, edge_offsets: np.ndarray, box: np.ndarray,
    inv_area: np.ndarray, cells: np.ndarray, scratch: np.ndarray, fill: bool, pix_runs: np.ndarray,
    pix_cuts: np.ndarray, run_start: np.ndarray, run_len: np.ndarray, run_head: np.ndarray,
    run_tail: np.ndarray, cut_weight: np.ndarray,
) -> None:  # fmt: skip
    """Thread ``t``'s share of pixels ``k0 .. k1 - 1``: their runs counted into ``pix_runs[k + 1]``
    and ``pix_cuts[k + 1]``, or, with ``fill``, written where the prefix sums ``pix_runs[k]``,
    ``pix_cuts[k]`` put them."""
    buf = own(scratch, t, nt)
    for k in range(k0 + t * (k1 - k0) // nt, k0 + (t + 1) * (k1 - k0) // nt):
        rlo, rhi, clo, chi = box[k, 0], box[k, 1], box[k, 2], box[k, 3]
        _add_steps(k, h, w, hs, ws, verts, seg_start, seg_end, edge_offsets, buf, rlo, rhi, clo, chi)
        r_at, c_at = (pix_runs[k], pix_cuts[k]) if fill else (0, 0)
        runs, cuts = _pixel_runs(
            k, buf, rlo, rhi, clo, chi, ws, inv_area[k], cells[k], fill, r_at, c_at, run_start, run_len,
            run_head, run_tail, cut_weight,
        )  # fmt: skip
        if not fill:
            pix_runs[k + 1], pix_cuts[k + 1] = runs, cuts


#: Pixels a call of the walk takes at a time (whole sensor rows): between two, the caller hears of
#: the rows done.
BLOCK_PIXELS = 1 << 16


def build_runs(
    verts: np.ndarray,
    seg_start: np.ndarray,
    seg_end: np.ndarray,
    edge_offsets: np.ndarray,
    size: tuple[int, int],
    src_size: tuple[int, int],
    area: np.ndarray,
    cells: np.ndarray,
    threads: int,
    progress: Callable[[int], object] | None = None,
) -> Runs:
    """The [`Runs`][layoutwarp.kernels.runs.Runs] of an ``(h, w)`` sensor's pixel mesh over an
    ``(H, W)`` source: ``verts`` ``(V, 2)`` float64 in source pixel units, clamped to the image
    ([`PixelMesh.pixel_vertices`][layoutwarp.mesh.PixelMesh.pixel_vertices]), the mesh's segments and
    edge offsets (int64); ``area`` ``(h · w,)`` the pixels' areas from those vertices (what the
    weights are normalised by) and ``cells`` their areas in source cells from the sensor's own
    units (what a whole cell's weight is ``1 / cells`` of, as in
    [`Runs.of`][layoutwarp.kernels.runs.Runs.of]); on ``threads`` threads. ``progress(rows)`` is
    called after each block of sensor rows ([`BLOCK_PIXELS`][]) of each of the three passes (the
    pixels' boxes, the counts, the runs)."""
    (h, w), (hs, ws) = size, src_size
    rows, nt = h * w, max(1, min(threads, h * w))
    box = np.empty((rows, 4), np.int64)
    args = (h, w, hs, ws, verts, seg_start, seg_end, edge_offsets)
    step = max(1, BLOCK_PIXELS // max(w, 1))

    def blocks() -> Iterator[tuple[int, int]]:  # pixels k0 .. k1 - 1 of each block, told when done
        for i0 in range(0, h, step):
            i1 = min(h, i0 + step)
            yield i0 * w, i1 * w
            if progress is not None:
                progress(i1 - i0)

    most = max(max(run_shares(_box_share, nt, k0, k1, *args, box)) for k0, k1 in blocks())
    scratch = per_thread(nt, (max(most, 1),))
    apart = scratch.shape[0] // (nt + 2)  # the threads' rows (own): zeroed once, each pixel leaves
    scratch[apart : (nt + 1) * apart : apart] = 0.0  # its box zeroed again; the rows between untouched
    pix_runs, pix_cuts = np.zeros(rows + 1, np.int64), np.zeros(rows + 1, np.int64)
    with np.errstate(divide="ignore"):  # a pixel of no area has no cell either
        inv_area = 1.0 / area

    def walk(fill: bool, *out: np.ndarray) -> None:
        for k0, k1 in blocks():
            run_shares(_runs_share, nt, k0, k1, *args, box, inv_area, cells, scratch, fill, *out)

    none, empty = np.empty(0, np.int64), np.empty(0, np.int32)
    walk(False, pix_runs, pix_cuts, none, empty, empty, empty, np.empty(0, np.float32))
    np.cumsum(pix_runs, out=pix_runs)
    np.cumsum(pix_cuts, out=pix_cuts)
    start = np.empty(int(pix_runs[-1]), np.int64)
    length, head, tail = (np.empty(start.size, np.int32) for _ in range(3))
    cut_weight = np.empty(int(pix_cuts[-1]), np.float32)
    walk(True, pix_runs, pix_cuts, start, length, head, tail, cut_weight)
    index = np.int32 if hs * ws < 2**31 else np.int64
    with np.errstate(divide="ignore"):
        whole = 1.0 / cells
    shape = (rows, hs * ws)
    return Runs(pix_runs, start.astype(index), length, head, tail, whole, pix_cuts, cut_weight, shape)
