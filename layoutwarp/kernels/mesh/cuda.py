"""The mesh on a CUDA device: the same steps as on the CPU, one GPU thread per corner, pixel,
edge or vertex running the same scalar functions ([`CUDA_KERNELS`][])."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from ..base import inline
from ..device import CUDA_THREADS
from ..exact import segment_weights
from ..prefix import prefix_block_item, prefix_offsets_item
from .build import (
    NS,
    add_moving,
    edge_bounds,
    edge_counts_item,
    edge_segments,
    piece_moves,
    piece_sagittas,
    piece_swept,
    pixel_vertex,
    sample_point,
)
from .phi import edge_pieces, phi_point

if TYPE_CHECKING:
    pass

cuda = None  # numba.cuda, bound by the first launch (kernels.cuda_launch)


#: The most θ entries a compiled map has (local arrays on the device have a fixed size).
P_MAX = 4


_DQ, _ROWS = P_MAX + 2, 2 + 2 * P_MAX  # local arrays' sizes must be constants of the module


F8 = np.float64


@inline
def _phi_at(
    kind: int, centred: bool, x: float, y: float, th: np.ndarray, c: np.ndarray, q: np.ndarray, dq: np.ndarray
) -> None:
    """[`phi_point`][] at ``(x, y)``, with ``dq`` ``(2, P_MAX + 2)`` work space whose first ``P``
    columns take ``∂φ/∂θ`` and the next two the Jacobian (the device's local arrays have one
    size for every ``P``)."""
    phi_point(kind, centred, x, y, th, c, q, dq[:, : th.shape[0] + 2])


@inline
def _edge_pieces(
    kind: int, centred: bool, e: int, ends: np.ndarray, th: np.ndarray, c: np.ndarray,
    piece_offsets: np.ndarray, scratch: np.ndarray, cuts: np.ndarray, dcuts: np.ndarray,
    lo: np.ndarray, dlo: np.ndarray, q: np.ndarray, dq: np.ndarray, rows: np.ndarray,
    bounds: np.ndarray, dbounds: np.ndarray, sag: np.ndarray, length: np.ndarray, swept: np.ndarray,
) -> None:  # fmt: skip
    """Edge ``e``'s part of [`_pieces_share`][] (always ``with_grad``): its pieces' bounds,
    sagitta bounds and chord lengths, and its swept area into ``swept[e]``; ``rows``
    ``(2 + 2 P_MAX, NS)`` (a piece's samples): work space."""
    p = th.shape[0]
    base = piece_offsets[e]
    n = edge_bounds(
        kind, centred, e, ends, th, c, piece_offsets, scratch, cuts, dcuts, lo, dlo, bounds, dbounds
    )
    ax, ay = ends[e, 0], ends[e, 1]
    dx, dy = ends[e, 2] - ax, ends[e, 3] - ay
    acc = 0.0
    for i in range(n):
        for s in range(NS):
            x, y = sample_point(ax, ay, dx, dy, lo[i], lo[i + 1], s)
            _phi_at(kind, centred, x, y, th, c, q, dq)
            rows[0, s], rows[1, s] = q[0], q[1]
            for r in range(p):
                rows[2 + r, s], rows[2 + p + r, s] = dq[0, r], dq[1, r]
        # piece by piece: little work space a thread
        piece_sagittas(rows, 1, True, p, sag[base + i :], length[base + i :])
        acc += piece_swept(rows, 0)
    swept[e] = acc


@inline
def _edge_vertices(
    kind: int, centred: bool, e: int, ends: np.ndarray, ea: np.ndarray, eb: np.ndarray, th: np.ndarray,
    c: np.ndarray, piece_offsets: np.ndarray, bounds: np.ndarray, dbounds: np.ndarray,
    counts: np.ndarray, first: int, chords: bool, ncorner: int, q: np.ndarray, dq: np.ndarray,
    verts: np.ndarray, dverts: np.ndarray, seg_start: np.ndarray, seg_end: np.ndarray, seg_edge: np.ndarray,
) -> int:  # fmt: skip
    """Edge ``e``'s part of [`_place_share`][]: its segments from ``first`` on and its new
    vertices, numbered as there, each vertex's ``∂v/∂θ`` with the term of a piece whose ends move
    with θ; with ``chords``, one segment a piece (its chord) whatever ``counts`` says. Returns
    the end of its segments."""
    p = th.shape[0]
    ax, ay = ends[e, 0], ends[e, 1]
    dx, dy = ends[e, 2] - ax, ends[e, 3] - ay
    s = first
    for pc in range(piece_offsets[e], piece_offsets[e + 1]):
        m, lo, hi = 1 if chords else counts[pc], bounds[pc, 0], bounds[pc, 1]
        moves = piece_moves(dbounds, pc, p)
        for k in range(m):
            if s != first:
                f = k / m
                t = lo + (hi - lo) * f
                v = ncorner + s - e - 1
                _phi_at(kind, centred, ax + t * dx, ay + t * dy, th, c, q, dq)
                verts[v, 0], verts[v, 1] = q[0], q[1]
                for r in range(p):
                    dverts[v, 0, r], dverts[v, 1, r] = dq[0, r], dq[1, r]
                if moves:  # the piece's ends move with a learned centre: its vertices too
                    add_moving(dverts, v, dq, p, dx, dy, dbounds, pc, f)
            s += 1
    edge_segments(e, first, s, ea, eb, ncorner, seg_start, seg_end, seg_edge)
    return s


@inline
def _theta_entry(param: np.ndarray, bounds: np.ndarray, r: int) -> tuple[float, float]:
    """θ's entry ``r`` from its parameter, in float64, and its derivative: ``bounds[r] ·
    tanh(param[r])`` (a bounded family's θ from its ρ), or ``param[r]`` itself where ``bounds``
    is empty."""
    x = float(param[r])
    if bounds.shape[0] == 0:
        return x, 1.0
    t = math.tanh(x)
    return bounds[r] * t, bounds[r] * (1 - t * t)


def _cuda_corners(
    kind: int, centred: bool, corners: np.ndarray, ends: np.ndarray, param: np.ndarray, bounds: np.ndarray,
    c: np.ndarray, theta: np.ndarray, slope: np.ndarray, q: np.ndarray, dq: np.ndarray, npieces: np.ndarray,
    image: np.ndarray, block: int, incl: np.ndarray,
) -> None:  # fmt: skip
    """Four independent steps in one launch: every thread makes θ from its parameter
    ([`_theta_entry`][]: ``param`` and ``bounds``), thread 0 writing it and its derivative into
    ``theta`` and ``slope`` (``(P,)``, float64) for the kernels after; thread ``i`` maps uniform
    corner ``i`` (φ and ``∂φ/∂θ`` into ``q``/``dq``), counts edge ``i``'s smooth pieces
    ([`edge_pieces`][]) into ``npieces[i + 1]``, thread 0 setting ``npieces[0] = 0``, so that
    a cumulative sum of ``npieces`` in place gives the pieces' offsets (a mesh has at least as
    many edges as corners), and sums block ``i`` (row × block × channel) of the source
    ``image`` ``(N, H, W)`` into the prefix table ``incl``
    ([`prefix_block_item`][layoutwarp.kernels.prefix.prefix_block_item])."""
    i = cuda.grid(1)
    prefix_block_item(image, i, block, incl)
    own = cuda.local.array(P_MAX, F8)
    for r in range(param.shape[0]):
        own[r], d = _theta_entry(param, bounds, r)
        if i == 0:
            theta[r], slope[r] = own[r], d
    if i == 0:
        npieces[0] = 0
    th = own[: param.shape[0]]
    if i < corners.shape[0]:
        qi, work = cuda.local.array(2, F8), cuda.local.array((2, _DQ), F8)
        _phi_at(kind, centred, corners[i, 0], corners[i, 1], th, c, qi, work)
        q[i, 0], q[i, 1] = qi[0], qi[1]
        for r in range(th.shape[0]):
            dq[i, 0, r], dq[i, 1, r] = work[0, r], work[1, r]
    if i < ends.shape[0]:
        scratch, cuts = cuda.local.array((8, P_MAX), F8), cuda.local.array(8, F8)
        dcuts = cuda.local.array((8, P_MAX), F8)
        lo, dlo = cuda.local.array(10, F8), cuda.local.array((10, P_MAX), F8)
        npieces[i + 1] = edge_pieces(kind, centred, i, ends, th, c, scratch, cuts, dcuts, lo, dlo, False)


#: The slots of a [`MeshRoom`][]'s status, in page-locked host memory its kernels write directly:
#: the pieces and the segments the newest mesh needed, the stamp of the last mesh that outgrew
#: its room (0: none since the host looked), and the cap a piece's segments reached
#: (``max_subdiv``; 0: none since the host looked).
PIECES, SEGMENTS, OVERFLOW, CAPPED = range(4)


def _cuda_pieces(
    kind: int, centred: bool, ends: np.ndarray, th: np.ndarray, c: np.ndarray,
    piece_offsets: np.ndarray, bounds: np.ndarray, dbounds: np.ndarray, sag: np.ndarray,
    length: np.ndarray, swept: np.ndarray, block: int, incl: np.ndarray, offsets: np.ndarray,
) -> None:  # fmt: skip
    """Two independent steps in one launch: thread ``e`` takes edge ``e``'s part of the pieces
    ([`_edge_pieces`][]), into room for ``bounds.shape[0]`` pieces (none where the mesh has
    more, ``piece_offsets[-1]``: [`_cuda_counts`][] then makes every edge its chord), and the
    block offsets of row × channel ``e`` of the prefix table ``incl``
    ([`prefix_offsets_item`][layoutwarp.kernels.prefix.prefix_offsets_item])."""
    e = cuda.grid(1)
    prefix_offsets_item(e, block, incl, offsets)
    ne = ends.shape[0]
    if e < ne and piece_offsets[ne] <= bounds.shape[0]:
        scratch, cuts = cuda.local.array((8, P_MAX), F8), cuda.local.array(8, F8)
        dcuts = cuda.local.array((8, P_MAX), F8)
        lo, dlo = cuda.local.array(10, F8), cuda.local.array((10, P_MAX), F8)
        q, dq = cuda.local.array(2, F8), cuda.local.array((2, _DQ), F8)
        rows = cuda.local.array((_ROWS, NS), F8)
        _edge_pieces(
            kind, centred, e, ends, th, c, piece_offsets, scratch, cuts, dcuts, lo, dlo, q, dq, rows,
            bounds, dbounds, sag, length, swept,
        )  # fmt: skip


def _cuda_counts(
    h: int, w: int, q: np.ndarray, swept: np.ndarray, piece_offsets: np.ndarray, sag: np.ndarray,
    length: np.ndarray, tol: float, max_subdiv: int, counts: np.ndarray, edge_counts: np.ndarray,
    status: np.ndarray, stamp: int,
) -> None:  # fmt: skip
    """One thread per edge: its pieces' segment counts ([`edge_counts_item`][], from the pixels'
    areas beside it, which need every edge's swept area: a launch after [`_cuda_pieces`][]) and
    its segments into ``edge_counts[e + 1]``. Where the pieces outgrew their room
    (``piece_offsets[-1]`` over ``counts.shape[0]``, read by every thread alike) every edge is one
    straight segment instead (its chord); thread 0 writes the pieces needed to the ``status``
    and, where they outgrew their room, the mesh's ``stamp``; a piece whose segments reach
    ``max_subdiv`` writes it to the status' slot ``CAPPED``."""
    e = cuda.grid(1)
    ne = swept.shape[0]
    over = piece_offsets[ne] > counts.shape[0]
    if e == 0:
        edge_counts[0] = 0  # the offsets' leading zero: no zeroed buffer to launch for
        status[PIECES] = piece_offsets[ne]
        if over:
            status[OVERFLOW] = stamp
    if e < ne and over:
        edge_counts[e + 1] = 1
    elif e < ne:
        edge_counts[e + 1] = edge_counts_item(
            e, h, w, q, swept, piece_offsets, sag, length, tol, max_subdiv, counts
        )
        for pc in range(piece_offsets[e], piece_offsets[e + 1]):
            if counts[pc] >= max_subdiv:  # every thread that sees it writes the same value
                status[CAPPED] = max_subdiv


def _cuda_place(
    kind: int, centred: bool, ends: np.ndarray, ea: np.ndarray, eb: np.ndarray, th: np.ndarray,
    c: np.ndarray, piece_offsets: np.ndarray, bounds: np.ndarray, dbounds: np.ndarray,
    counts: np.ndarray, edge_offsets: np.ndarray, q: np.ndarray, dq: np.ndarray, ws: float, hs: float,
    verts: np.ndarray, dverts: np.ndarray, seg_start: np.ndarray, seg_end: np.ndarray, seg_edge: np.ndarray,
    pv: np.ndarray, seg_offsets: np.ndarray, status: np.ndarray, stamp: int,
) -> None:  # fmt: skip
    """One thread per edge: [`_edge_vertices`][], then its new vertices in pixel units of a
    ``ws`` x ``hs`` source ([`pixel_vertex`][]) into ``pv``; thread ``e`` also copies corner
    ``e`` in from ``q``/``dq`` (where the corners' kernel left them; a mesh has at least as many
    edges as corners) with its pixel units. One launch where placing and converting took two.

    The mesh is built in room for ``seg_start.shape[0]`` segments (at least as many as edges):
    where it needs more (``edge_offsets[-1]``), each piece is one segment, its chord; where its
    pieces outgrew their room ([`_cuda_counts`][]) or this one, each edge is.
    Either way the ``status`` gets the mesh's ``stamp``, and ``seg_offsets`` ``(E + 1,)`` holds
    the segments' offsets the mesh has. The room left over holds segments of no length (at vertex 0, which add
    nothing), so a kernel may run over all of it."""
    e = cuda.grid(1)
    nc, ne, room = q.shape[0], ends.shape[0], seg_start.shape[0]
    counted = piece_offsets[ne] <= bounds.shape[0]  # the counts' kernel counted the segments
    pieces_over = not counted or piece_offsets[ne] > room
    over = not pieces_over and edge_offsets[ne] > room
    used = ne if pieces_over else piece_offsets[ne] if over else edge_offsets[ne]
    if e == 0:
        seg_offsets[0] = 0
        if counted:
            status[SEGMENTS] = edge_offsets[ne]
            if over or pieces_over:
                status[OVERFLOW] = stamp
    if e < nc:
        verts[e, 0], verts[e, 1] = q[e, 0], q[e, 1]
        for i in range(2):
            for p in range(dq.shape[2]):
                dverts[e, i, p] = dq[e, i, p]
        pv[e, 0], pv[e, 1] = pixel_vertex(q[e, 0], q[e, 1], ws, hs)
    if e < ne:
        if pieces_over:  # the edge's chord, from corner to corner
            edge_segments(e, e, e + 1, ea, eb, nc, seg_start, seg_end, seg_edge)
            seg_offsets[e + 1] = e + 1
        else:
            qi, dqi = cuda.local.array(2, F8), cuda.local.array((2, _DQ), F8)
            first = piece_offsets[e] if over else edge_offsets[e]
            seg_offsets[e + 1] = _edge_vertices(
                kind, centred, e, ends, ea, eb, th, c, piece_offsets, bounds, dbounds, counts, first, over,
                nc, qi, dqi, verts, dverts, seg_start, seg_end, seg_edge,
            )  # fmt: skip
            for v in range(nc + first - e, nc + seg_offsets[e + 1] - e - 1):  # its new vertices
                pv[v, 0], pv[v, 1] = pixel_vertex(verts[v, 0], verts[v, 1], ws, hs)
        for s in range(used + e, room, ne):  # the room left over: segments of no length
            seg_start[s], seg_end[s], seg_edge[s] = 0, 0, 0


@inline
def _edge_total(per_seg: np.ndarray, edge_offsets: np.ndarray, e: int, k: int) -> float:
    """Edge ``e``'s integral ``k``: its segments' values summed in order, as
    [`exact_forward`][layoutwarp.kernels.exact.exact_forward] sums them."""
    acc = 0.0
    for s in range(edge_offsets[e], edge_offsets[e + 1]):
        acc += per_seg[s, k]
    return acc


@inline
def _pixel_integral(
    per_seg: np.ndarray, edge_offsets: np.ndarray, r: int, c: int, w: int, nh: int, k: int
) -> float:
    """Pixel ``(r, c)``'s boundary integral ``k`` from its edges (top, bottom, left, right in
    [`MeshTopology`][]'s numbering; ``nh`` horizontal edges), combined as
    [`MeshTopology.combine`][layoutwarp.mesh.MeshTopology.combine] does."""
    top = _edge_total(per_seg, edge_offsets, r * w + c, k)
    bottom = _edge_total(per_seg, edge_offsets, r * w + w + c, k)
    left = _edge_total(per_seg, edge_offsets, nh + r * (w + 1) + c, k)
    right = _edge_total(per_seg, edge_offsets, nh + r * (w + 1) + c + 1, k)
    return (top - bottom) + (right - left)


def cuda_pixel_means(
    per_seg: np.ndarray, edge_offsets: np.ndarray, unit: float, means: np.ndarray, area: np.ndarray,
    area_units: np.ndarray, checks: np.ndarray, stamp: int, zero: np.ndarray,
) -> None:  # fmt: skip
    """One thread per pixel: its boundary integrals from its four edges' segments (each edge's
    sum in order, combined as [`MeshTopology.combine`][layoutwarp.mesh.MeshTopology.combine]
    does), its means ``(N, h, w)`` (the integrals over the last, the area, in float64, rounded
    once into ``means``' dtype) and the area, as it is and in sensor units (times ``unit``): the
    edge sums, the combination and the division in one pass. A mean that is NaN or ±inf (once
    rounded) writes ``stamp`` to ``checks[0]`` (the finiteness check, on the device,
    [`DeviceChecks`][layoutwarp.kernels.device.DeviceChecks]; a ``stamp`` of 0 checks nothing).
    Thread 0 also sets ``zero[0] = 0`` (a flag the caller returns: no fill launched for it)."""
    i = cuda.grid(1)
    n, h, w = means.shape
    if i == 0:
        zero[0] = 0
    if i < h * w:
        r, c = i // w, i % w
        a = _pixel_integral(per_seg, edge_offsets, r, c, w, (h + 1) * w, n)
        area[r, c], area_units[r, c] = a, a * unit
        for k in range(n):
            means[k, r, c] = _pixel_integral(per_seg, edge_offsets, r, c, w, (h + 1) * w, k) / a
            if stamp and not math.isfinite(means[k, r, c]):
                checks[0] = stamp


@inline
def _pixel_gradient(
    g: np.ndarray, means: np.ndarray, area: np.ndarray, g_area: np.ndarray, unit: float, r: int, c: int,
    k: int,
) -> float:  # fmt: skip
    """The gradient of pixel ``(r, c)``'s boundary integral ``k`` (the area for ``k = N``) from
    those of its means ``g`` and of its area in sensor units ``g_area`` (empty: none): the quotient
    rule of ``mean = integral / area``."""
    n = means.shape[0]
    if k < n:
        return g[k, r, c] / area[r, c]
    acc = 0.0
    for j in range(n):
        acc += g[j, r, c] * means[j, r, c]
    out = -acc / area[r, c]
    if g_area.shape[0] > 0:
        out += g_area[r, c] * unit
    return out


def cuda_edge_gradient(
    g: np.ndarray, means: np.ndarray, area: np.ndarray, g_area: np.ndarray, unit: float, g_edge: np.ndarray,
    sums: np.ndarray, done: np.ndarray,
) -> None:  # fmt: skip
    """One thread per pixel edge: the gradient ``(N + 1, E)`` of the edge integrals from the
    means' and the areas' (the adjoint of [`cuda_pixel_means`][]: the quotient rule and
    [`MeshTopology.combine_adjoint`][layoutwarp.mesh.MeshTopology.combine_adjoint] in one
    pass; ``g`` and ``means`` in the means' dtype, the sums in float64). An edge adds to the
    pixel before it (above, or to its left) and takes from the one after. Thread 0 also zeroes
    ``sums`` and ``done``, which [`cuda_theta_gradient`][] adds to next."""
    e = cuda.grid(1)
    if e == 0:
        done[0] = 0
        for p in range(sums.shape[0]):
            sums[p] = 0.0
    n, h, w = means.shape
    nh = (h + 1) * w
    if e < g_edge.shape[1]:
        for k in range(n + 1):
            v = 0.0
            if e < nh:  # horizontal: the top edge of pixel (r, c), the bottom of (r - 1, c)
                r, c = e // w, e % w
                if r < h:
                    v = _pixel_gradient(g, means, area, g_area, unit, r, c, k)
                if r > 0:
                    v -= _pixel_gradient(g, means, area, g_area, unit, r - 1, c, k)
            else:  # vertical: the right edge of pixel (r, c - 1), the left of (r, c)
                r, c = (e - nh) // (w + 1), (e - nh) % (w + 1)
                if c > 0:
                    v = _pixel_gradient(g, means, area, g_area, unit, r, c - 1, k)
                if c < w:
                    v -= _pixel_gradient(g, means, area, g_area, unit, r, c, k)
            g_edge[k, e] = v


def cuda_theta_gradient(
    verts: np.ndarray, seg_start: np.ndarray, seg_end: np.ndarray, seg_edge: np.ndarray, incl: np.ndarray,
    block: int, g_edge: np.ndarray, dverts: np.ndarray, sx: float, sy: float, sums: np.ndarray,
    done: np.ndarray, slope: np.ndarray, g_param: np.ndarray,
) -> None:  # fmt: skip
    """One thread per segment: its Reynolds weights ([`segment_weights`][]) times its normal line
    element ``(ΔY, −ΔX)`` (pixel units, ``verts``) at its two vertices, carried to θ by their
    derivatives ``dverts`` ``(V, 2, P)`` (sensor units, so scaled by ``(sx, sy)``, a pixel unit's
    size in sensor units' reciprocal); the block's sums reduced in shared memory and added to
    ``sums`` ``(P,)`` (float64, zeroed with ``done`` by [`cuda_edge_gradient`][]), one atomic
    addition per block and entry. The vertex gradient, its scaling and the contraction with
    ``dverts`` in one pass: no value per segment or vertex is written. The block that finishes
    last (counted in ``done``) writes the gradient of θ's parameter, ``sums`` times θ's
    derivative ``slope`` ([`_cuda_corners`][]), into ``g_param`` in its dtype: no launch after."""
    s = cuda.grid(1)
    t = cuda.threadIdx.x
    p_count = dverts.shape[2]
    part = cuda.shared.array((CUDA_THREADS, P_MAX), F8)
    for p in range(P_MAX):
        part[t, p] = 0.0
    if s < seg_start.shape[0]:
        wa, wb = segment_weights(s, verts, seg_start, seg_end, seg_edge, incl, block, g_edge)
        a, b = seg_start[s], seg_end[s]
        nx, ny = (verts[b, 1] - verts[a, 1]) * sx, (verts[a, 0] - verts[b, 0]) * sy
        for p in range(p_count):
            part[t, p] = wa * (nx * dverts[a, 0, p] + ny * dverts[a, 1, p]) + wb * (
                nx * dverts[b, 0, p] + ny * dverts[b, 1, p]
            )
    cuda.syncthreads()
    stride = CUDA_THREADS // 2
    while stride > 0:
        if t < stride:
            for p in range(P_MAX):
                part[t, p] += part[t + stride, p]
        cuda.syncthreads()
        stride //= 2
    if t == 0:
        for p in range(p_count):
            cuda.atomic.add(sums, p, part[0, p])
        cuda.threadfence()  # the sums seen by every block before the count is
        if cuda.atomic.add(done, 0, 1) == cuda.gridDim.x - 1:  # the last block: every sum is in
            cuda.threadfence()  # nothing read before the count said so
            for p in range(p_count):
                g_param[p] = cuda.atomic.add(sums, p, 0.0) * slope[p]  # read where the sums are


_A1, _A2, _A3, _I1 = "float64[::1]", "float64[:, ::1]", "float64[:, :, ::1]", "int64[::1]"


_F3 = "float32[:, :, ::1]"  # a float32 image and its prefix table


#: The device kernels of [`build_mesh_device`][], by name, with their argument types for a
#: float32 image and ρ (what [`cuda_ptx`][layoutwarp.kernels.cuda_ptx] compiles them with, without a
#: GPU; a float64 image compiles its own on first use).
CUDA_KERNELS = {
    "corners": (
        _cuda_corners,
        f"void(int64, boolean, {_A2}, {_A2}, float32[::1], {_A1}, {_A1}, {_A1}, {_A1}, {_A2}, {_A3}, {_I1}, "
        f"{_F3}, int64, {_F3})",
    ),
    "pieces": (
        _cuda_pieces,
        f"void(int64, boolean, {_A2}, {_A1}, {_A1}, {_I1}, {_A2}, {_A3}, {_A1}, {_A1}, {_A1}, int64, {_F3}, "
        f"{_A3})",
    ),
    "counts": (
        _cuda_counts,
        f"void(int64, int64, {_A2}, {_A1}, {_I1}, {_A1}, {_A1}, float64, int64, {_I1}, {_I1}, {_I1}, int64)",
    ),
    "place": (
        _cuda_place,
        f"void(int64, boolean, {_A2}, {_I1}, {_I1}, {_A1}, {_A1}, {_I1}, {_A2}, {_A3}, {_I1}, {_I1}, {_A2}, "
        f"{_A3}, float64, float64, {_A2}, {_A3}, {_I1}, {_I1}, {_I1}, {_A2}, {_I1}, {_I1}, int64)",
    ),
    "pixel_means": (
        cuda_pixel_means,
        f"void({_A2}, {_I1}, float64, {_F3}, {_A2}, {_A2}, {_I1}, int64, int8[::1])",
    ),
    "edge_gradient": (  # the means' gradient as a sum's backward gives it: strided (broadcast)
        cuda_edge_gradient,
        f"void(float32[:, :, :], {_F3}, {_A2}, {_A2}, float64, {_A2}, {_A1}, {_I1})",
    ),
    "theta_gradient": (
        cuda_theta_gradient,
        f"void({_A2}, {_I1}, {_I1}, {_I1}, {_F3}, int64, {_A2}, {_A3}, float64, float64, {_A1}, {_I1}, "
        f"{_A1}, float32[::1])",
    ),
}
