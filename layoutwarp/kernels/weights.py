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

Two passes over the pixels, block by block of sensor rows, each thread taking a contiguous range
of a block: the first finds each pixel's box of cells, the second writes its runs and cut cells
into a row of the thread's own. A thread stops before a pixel whose box could overflow its row,
the rows are made longer, and it goes on where it stopped; the rows are joined in pixel order at
the end. Besides the result it holds the boxes, one box of float64 per thread and the threads'
rows. Computed in float64; the cut weights are kept in float32.
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
    r_at: int, c_at: int, run_start: np.ndarray, run_len: np.ndarray, run_head: np.ndarray,
    run_tail: np.ndarray, cut_weight: np.ndarray,
) -> tuple[int, int]:  # fmt: skip
    """Sum pixel ``k``'s steps along each row of its box (zeroing ``buf`` for the next pixel), cut
    its cells into runs and write them from run ``r_at`` and cut cell ``c_at``. Returns the
    pixel's number of runs and of cut cells."""
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
                if runs > 0:
                    _close(r_at + runs - 1, length, head, wholes, run_len, run_head, run_tail)
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
                cut_weight[c_at + cuts] = wv
                cuts += 1
            prev_whole = whole
    if runs > 0:
        _close(r_at + runs - 1, length, head, wholes, run_len, run_head, run_tail)
    return runs, cuts


@inline
def _box_cells(rlo: int, rhi: int, clo: int, chi: int) -> int:
    """The cells of a pixel's box ``rlo .. rhi`` × ``clo .. chi + 1`` (the column past ``chi``
    takes the last cells' steps): the most runs, and the most cut cells, the pixel can have."""
    return (rhi - rlo + 1) * (chi - clo + 2)


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
        most = max(most, _box_cells(rlo, rhi, clo, chi))
    return most


@serial
def _runs_share(
    t: int, nt: int, k0: int, k1: int, h: int, w: int, hs: int, ws: int, verts: np.ndarray,
    seg_start: np.ndarray, seg_end: np.ndarray, edge_offsets: np.ndarray, box: np.ndarray,
    inv_area: np.ndarray, cells: np.ndarray, scratch: np.ndarray, state: np.ndarray, pix_runs: np.ndarray,
    pix_cuts: np.ndarray, run_start: np.ndarray, run_len: np.ndarray, run_head: np.ndarray,
    run_tail: np.ndarray, cut_weight: np.ndarray,
) -> None:  # fmt: skip
    """Thread ``t``'s share of pixels ``k0 .. k1 - 1`` from pixel ``state[t, 0]`` on: their runs
    and cut cells written into row ``t`` of the run arrays and ``cut_weight`` after the
    ``state[t, 1]`` runs and ``state[t, 2]`` cut cells already there, each pixel's counts into
    ``pix_runs[k + 1]`` and ``pix_cuts[k + 1]``. It stops before a pixel whose box (a run and a cut
    cell at most per cell) could overflow a row: ``state[t]`` then holds that pixel, the counts so
    far and the room it needs (0 where the share is done)."""
    buf = own(scratch, t, nt)
    starts, lengths, heads, tails, cuts_w = run_start[t], run_len[t], run_head[t], run_tail[t], cut_weight[t]
    k, nr, nc, stop = state[t, 0], state[t, 1], state[t, 2], k0 + (t + 1) * (k1 - k0) // nt
    state[t, 3] = 0
    while k < stop:
        rlo, rhi, clo, chi = box[k, 0], box[k, 1], box[k, 2], box[k, 3]
        most = _box_cells(rlo, rhi, clo, chi)
        if nr + most > starts.shape[0] or nc + most > cuts_w.shape[0]:
            state[t, 3] = most
            break
        _add_steps(k, h, w, hs, ws, verts, seg_start, seg_end, edge_offsets, buf, rlo, rhi, clo, chi)
        runs, cuts = _pixel_runs(k, buf, rlo, rhi, clo, chi, ws, inv_area[k], cells[k], nr, nc, starts,
                                 lengths, heads, tails, cuts_w)  # fmt: skip
        pix_runs[k + 1], pix_cuts[k + 1] = runs, cuts
        k, nr, nc = k + 1, nr + runs, nc + cuts
    state[t, 0], state[t, 1], state[t, 2] = k, nr, nc


class _Rows:
    """The threads' rows of runs and cut cells for [`build_runs`][]: ``arrays`` (``run_start``,
    ``run_len``, ``run_head``, ``run_tail``, ``cut_weight``, a row a thread), made longer by
    ``grow``; ``joined`` copies out what the threads wrote."""

    def __init__(self, nt: int, runs: int) -> None:
        self.arrays = (
            np.empty((nt, runs), np.int64),
            *(np.empty((nt, runs), np.int32) for _ in range(3)),
            np.empty((nt, 4 * runs), np.float32),  # about four cut cells a run
        )

    def grow(self, runs: int, cuts: int) -> None:
        """Rows of at least ``runs`` runs and ``cuts`` cut cells (twice as long at least), what
        they held kept."""

        def longer(a: np.ndarray, n: int) -> np.ndarray:
            if n <= a.shape[1]:
                return a
            b = np.empty((a.shape[0], max(n, 2 * a.shape[1])), a.dtype)
            b[:, : a.shape[1]] = a
            return b

        *run_arrays, cut = self.arrays
        self.arrays = (*(longer(a, runs) for a in run_arrays), longer(cut, cuts))

    def joined(self, runs: np.ndarray, cuts: np.ndarray) -> tuple[np.ndarray, ...]:
        """What the threads wrote, one array each, thread after thread: thread ``t``'s first
        ``runs[t]`` runs and ``cuts[t]`` cut cells."""
        *run_arrays, cut = self.arrays
        nt = len(runs)
        return (
            *(np.concatenate([a[t, : runs[t]] for t in range(nt)]) for a in run_arrays),
            np.concatenate([cut[t, : cuts[t]] for t in range(nt)]),
        )


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
    called after each block of sensor rows ([`BLOCK_PIXELS`][]) of each of the two passes (the
    pixels' boxes, the runs)."""
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

    rows_of = box[:, 1] - box[:, 0] + 1  # about a run a row, the busiest block's; grown as needed
    block_rows = np.add.reduceat(rows_of, np.arange(0, rows, step * w)) if rows else np.zeros(1)
    room = _Rows(nt, int(block_rows.max() * 1.25) // nt + 64)
    parts = []
    state = np.zeros((nt, 4), np.int64)
    for k0, k1 in blocks():
        state[:] = 0
        state[:, 0] = [k0 + t * (k1 - k0) // nt for t in range(nt)]
        while True:
            walk = (box, inv_area, cells, scratch, state, pix_runs, pix_cuts, *room.arrays)
            run_shares(_runs_share, nt, k0, k1, *args, *walk)
            if not state[:, 3].any():
                break
            room.grow(int((state[:, 1] + state[:, 3]).max()), int((state[:, 2] + state[:, 3]).max()))
        parts.append(room.joined(state[:, 1], state[:, 2]))  # copied: the next block writes the rows
    np.cumsum(pix_runs, out=pix_runs)
    np.cumsum(pix_cuts, out=pix_cuts)
    joined = (
        parts[0] if len(parts) == 1 else tuple(np.concatenate(arrays) for arrays in zip(*parts, strict=True))
    )
    start, length, head, tail, cut_weight = joined
    index = np.int32 if hs * ws < 2**31 else np.int64
    with np.errstate(divide="ignore"):
        whole = 1.0 / cells
    shape = (rows, hs * ws)
    return Runs(pix_runs, start.astype(index), length, head, tail, whole, pix_cuts, cut_weight, shape)
