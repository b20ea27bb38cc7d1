"""The compiled mesh on the CPU: pieces, segment counts and vertices with their θ-derivatives
([`build_mesh`][]), threads taking chunks of edges in turn, each with its own work space."""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import torch

from ...mesh import BENDS, MAX_SUBDIV, SAMPLES, warn_if_capped
from ...topology import MeshTopology
from ..base import CHUNK, inline, own, per_thread, run_shares, serial, threads
from .phi import edge_pieces, phi_point, phi_run, unpack_point
from .spec import CompiledMesh, MeshSpec

if TYPE_CHECKING:
    pass


@serial
def _count_share(
    t: int, nt: int, kind: int, centred: bool, ends: np.ndarray, th: np.ndarray, c: np.ndarray,
    out: np.ndarray, work: tuple, grad: bool,
) -> None:  # fmt: skip
    """Thread ``t``'s chunks of edges (in turn): each edge's smooth pieces into ``out``;
    ``work``: [`_edge_work`][]'s arrays; ``grad``: False, passed as a value (a constant would
    compile [`edge_pieces`][] a second time, beside [`edge_bounds`][]'s)."""
    ne = ends.shape[0]
    scratch, cuts = own(work[0], t, nt), own(work[1], t, nt)
    dcuts, lo, dlo = own(work[2], t, nt), own(work[3], t, nt), own(work[4], t, nt)
    for chunk in range(t, (ne + CHUNK - 1) // CHUNK, nt):
        for e in range(chunk * CHUNK, min((chunk + 1) * CHUNK, ne)):
            out[e] = edge_pieces(kind, centred, e, ends, th, c, scratch, cuts, dcuts, lo, dlo, grad)


#: Samples a piece in the count stage ([`SAMPLES`][layoutwarp.mesh.SAMPLES]).
NS = len(SAMPLES)


@inline
def sample_point(
    ax: float, ay: float, dx: float, dy: float, a: float, b: float, s: int
) -> tuple[float, float]:
    """Sample ``s`` of the count stage on the piece ``[a, b]`` of the edge ``a + t d``: the
    point at ``t = a + (b − a)·SAMPLES[s]``."""
    t = a + (b - a) * SAMPLES[s]
    return ax + t * dx, ay + t * dy


@inline
def segment_counts(
    sag: np.ndarray, length: np.ndarray, j0: int, n: int, base: int, amin_e: float, tol: float,
    max_subdiv: int, counts: np.ndarray,
) -> int:  # fmt: skip
    """The segment counts of an edge's ``n`` pieces ``base ..`` into ``counts`` (their sagitta
    bounds and chord lengths at ``sag[j0 + i]``, ``length[j0 + i]``; ``amin_e``: the edge's
    smaller pixel area), as [`layoutwarp.mesh._segment_counts`][] bounds them; returns their
    sum."""
    edge_len = 0.0
    for i in range(n):
        edge_len += length[j0 + i]
    budget = 3 * tol * amin_e / (8 * max(edge_len, 1e-300))
    total = 0
    for i in range(n):
        sg, ln = sag[j0 + i], length[j0 + i]
        m = min(max(math.ceil(math.sqrt(2 * sg / budget)), 1.0), float(max_subdiv))
        counts[base + i] = 1 if sg <= 1e-15 * ln else int(m)
        total += counts[base + i]
    return total


@inline
def edge_bounds(
    kind: int, centred: bool, e: int, ends: np.ndarray, th: np.ndarray, c: np.ndarray,
    piece_offsets: np.ndarray, scratch: np.ndarray, cuts: np.ndarray, dcuts: np.ndarray,
    lo: np.ndarray, dlo: np.ndarray, bounds: np.ndarray, dbounds: np.ndarray, grad: bool = True,
) -> int:  # fmt: skip
    """Edge ``e``'s smooth pieces with their θ-derivatives ([`edge_pieces`][]; one piece from
    0 to 1 where ``piece_offsets`` says it has no kink) into ``lo``, ``dlo`` and its rows of
    ``bounds``, ``dbounds``; returns their number. The other arrays: work space. ``grad``: True
    (the CPU kernel passes it as a value, see [`_count_share`][])."""
    p = th.shape[0]
    base = piece_offsets[e]
    n = piece_offsets[e + 1] - base
    if n == 1:  # no kink: one piece, from 0 to 1, whose ends stay
        lo[0], lo[1] = 0.0, 1.0
        for r in range(p):
            dlo[0, r], dlo[1, r] = 0.0, 0.0
    else:
        edge_pieces(kind, centred, e, ends, th, c, scratch, cuts, dcuts, lo, dlo, grad)
    for i in range(n):
        bounds[base + i, 0], bounds[base + i, 1] = lo[i], lo[i + 1]
        for r in range(p):
            dbounds[base + i, 0, r], dbounds[base + i, 1, r] = dlo[i, r], dlo[i + 1, r]
    return n


@inline
def _curvature(out: np.ndarray, row: int, k: int, s: int) -> float:
    """The second difference of row ``row`` of ``out`` at sample ``s`` of the piece whose samples
    start at column ``k`` ([`BENDS`][layoutwarp.mesh.BENDS], as in torch)."""
    up, down = BENDS[s - 1]
    f0, f1, f2 = out[row, k + s - 1], out[row, k + s], out[row, k + s + 1]
    return (f2 - f1) * up - (f1 - f0) * down


@inline
def piece_sagittas(
    out: np.ndarray, n: int, grad: bool, p: int, sag: np.ndarray, length: np.ndarray
) -> None:  # fmt: skip
    """Chord length and sagitta bound of each of ``n`` pieces whose ``NS`` samples are columns
    ``q·NS ..`` of [`phi_run`][]'s rows ``out``: the largest of the second differences of φ and,
    where ``grad``, of every ``∂φ/∂θ`` at the inner samples (it may jump at a kink), across the
    edge's direction at each (from its two neighbours), over 8."""
    for q in range(n):
        k = q * NS
        chx, chy = out[0, k + NS - 1] - out[0, k], out[1, k + NS - 1] - out[1, k]
        sg = 0.0
        for s in range(1, NS - 1):
            tnx, tny = out[0, k + s + 1] - out[0, k + s - 1], out[1, k + s + 1] - out[1, k + s - 1]
            span = max(math.sqrt(tnx * tnx + tny * tny), 1e-300)
            ux, uy = tnx / span, tny / span
            sg = max(sg, abs(ux * _curvature(out, 1, k, s) - uy * _curvature(out, 0, k, s)))
            if grad and 1 < s < NS - 2:  # the θ-velocity field bends the edge too
                for r in range(2, 2 + p):
                    sg = max(sg, abs(ux * _curvature(out, p + r, k, s) - uy * _curvature(out, r, k, s)))
        sag[q], length[q] = sg / 8, math.sqrt(chx * chx + chy * chy)


@inline
def piece_swept(out: np.ndarray, k: int) -> float:
    """The area ``∫ x dy`` along the polyline of a piece's ``NS`` samples, columns ``k ..`` of
    [`phi_run`][]'s rows ``out``, summed in order (as ``layoutwarp.mesh._chord_and_sagitta`` sums
    [`segment_area`][layoutwarp.mesh.segment_area])."""
    acc = 0.0
    for s in range(NS - 1):
        acc += (out[1, k + s + 1] - out[1, k + s]) * (out[0, k + s] + out[0, k + s + 1]) / 2
    return acc


@serial
def _pieces_share(
    t: int, nt: int, kind: int, centred: bool, ends: np.ndarray, th: np.ndarray, c: np.ndarray,
    piece_offsets: np.ndarray, with_grad: bool, bounds: np.ndarray, dbounds: np.ndarray,
    sag: np.ndarray, length: np.ndarray, swept: np.ndarray, work: tuple, phi_work: tuple,
    all_pts: np.ndarray, all_out: np.ndarray, kink_grad: bool,
) -> None:  # fmt: skip
    """Every smooth piece's parameter range (``bounds`` (pieces, 2), ``dbounds`` (pieces, 2, P)),
    sagitta bound and chord length (``sag``, ``length`` (pieces,)), as
    [`layoutwarp.mesh._segment_counts`][] bounds them, and every edge's swept area ``swept``
    ``(E,)`` ([`piece_swept`][], its pieces' in order). A chunk of edges places its sample points
    first, maps them in one loop ([`phi_run`][]), then bounds. Thread ``t`` of ``nt`` takes every
    ``nt``-th chunk, with its rows of the work space: [`_edge_work`][]'s, [`_phi_work`][]'s, the
    sample points ``(T, 2, NS·span)`` and their map ``(T, 2 + 2P, NS·span)`` (``span``: the most
    pieces a chunk has); ``kink_grad``: True, as a value (see [`_count_share`][])."""
    ne, p = ends.shape[0], th.shape[0]
    n_chunks = (ne + CHUNK - 1) // CHUNK
    scratch, cuts = own(work[0], t, nt), own(work[1], t, nt)
    dcuts, lo, dlo = own(work[2], t, nt), own(work[3], t, nt), own(work[4], t, nt)
    qi, dq = own(phi_work[0], t, nt), own(phi_work[1], t, nt)
    pts, out = own(all_pts, t, nt), own(all_out, t, nt)
    for chunk in range(t, n_chunks, nt):
        e0, e1 = chunk * CHUNK, min((chunk + 1) * CHUNK, ne)
        for e in range(e0, e1):
            base = piece_offsets[e]
            n = edge_bounds(
                kind, centred, e, ends, th, c, piece_offsets, scratch, cuts, dcuts, lo, dlo,
                bounds, dbounds, kink_grad,
            )  # fmt: skip
            ax, ay = ends[e, 0], ends[e, 1]
            dx, dy = ends[e, 2] - ax, ends[e, 3] - ay
            for i in range(n):
                a, b = lo[i], lo[i + 1]
                k = (base + i - piece_offsets[e0]) * NS
                for s in range(NS):
                    pts[0, k + s], pts[1, k + s] = sample_point(ax, ay, dx, dy, a, b, s)
        first = piece_offsets[e0]
        npc = piece_offsets[e1] - first
        phi_run(kind, centred, th, c, pts, npc * NS, out, qi, dq)
        sg, ln = sag[first:], length[first:]
        if with_grad and p == 4:  # θ's count a constant: the loop over pieces runs in SIMD lanes
            piece_sagittas(out, npc, True, 4, sg, ln)
        elif with_grad and p == 2:
            piece_sagittas(out, npc, True, 2, sg, ln)
        else:
            piece_sagittas(out, npc, with_grad, p, sg, ln)
        for e in range(e0, e1):
            acc = 0.0
            for pc in range(piece_offsets[e], piece_offsets[e + 1]):
                acc += piece_swept(out, (pc - first) * NS)
            swept[e] = acc


@inline
def pixel_area(q: np.ndarray, swept: np.ndarray, i: int, j: int, h: int, w: int) -> float:
    """Pixel ``(i, j)``'s area as the count stage takes it: the smaller of its corner quad's
    ([`quad_area`][]) and its sampled polygon's, from its edges' ``swept`` areas combined as
    [`MeshTopology.combine`][layoutwarp.topology.MeshTopology.combine] combines them."""
    v = (h + 1) * w + i * (w + 1) + j  # its left edge (after the horizontal ones)
    sampled = (swept[i * w + j] - swept[(i + 1) * w + j]) + (swept[v + 1] - swept[v])
    return min(quad_area(q, i, j, w), abs(sampled))


@inline
def edge_amin(q: np.ndarray, swept: np.ndarray, e: int, h: int, w: int) -> float:
    """The smaller [`pixel_area`][] of the two pixels beside edge ``e`` (horizontal edges, then
    vertical, numbered as [`MeshTopology`][layoutwarp.topology.MeshTopology] numbers them; the
    sensor's outside counts as infinite)."""
    nh = (h + 1) * w
    if e < nh:
        i, j = e // w, e % w
        up = pixel_area(q, swept, i - 1, j, h, w) if i > 0 else np.inf
        return min(up, pixel_area(q, swept, i, j, h, w) if i < h else np.inf)
    i, j = (e - nh) // (w + 1), (e - nh) % (w + 1)
    left = pixel_area(q, swept, i, j - 1, h, w) if j > 0 else np.inf
    return min(left, pixel_area(q, swept, i, j, h, w) if j < w else np.inf)


@inline
def edge_counts_item(
    e: int, h: int, w: int, q: np.ndarray, swept: np.ndarray, piece_offsets: np.ndarray,
    sag: np.ndarray, length: np.ndarray, tol: float, max_subdiv: int, counts: np.ndarray,
) -> int:  # fmt: skip
    """Edge ``e``'s pieces' segment counts into ``counts`` ([`segment_counts`][] with its
    [`edge_amin`][]); returns their sum."""
    first, amin = piece_offsets[e], edge_amin(q, swept, e, h, w)
    n = piece_offsets[e + 1] - first
    return segment_counts(sag, length, first, n, first, amin, tol, max_subdiv, counts)


@serial
def _counts_share(
    t: int, nt: int, h: int, w: int, q: np.ndarray, swept: np.ndarray, piece_offsets: np.ndarray,
    sag: np.ndarray, length: np.ndarray, tol: float, max_subdiv: int, counts: np.ndarray,
    edge_counts: np.ndarray,
) -> None:  # fmt: skip
    """Thread ``t``'s chunks of edges (in turn): [`edge_counts_item`][] into ``counts`` and each
    edge's segments into ``edge_counts[e + 1]`` (``edge_counts[0]`` is left alone)."""
    ne = swept.shape[0]
    for chunk in range(t, (ne + CHUNK - 1) // CHUNK, nt):
        for e in range(chunk * CHUNK, min((chunk + 1) * CHUNK, ne)):
            edge_counts[e + 1] = edge_counts_item(e, h, w, q, swept, piece_offsets, sag, length, tol,
                                                  max_subdiv, counts)  # fmt: skip


@functools.lru_cache(maxsize=16)
def mesh_topology(size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Uniform edge ends ``(E, 4)``, their corner indices and the uniform corners ``(V0, 2)`` of
    [`MeshTopology`][layoutwarp.topology.MeshTopology] as arrays (cached per size; do not modify)."""
    topo = MeshTopology(size)
    ua, ub = topo.edge_ends()
    ea, eb = topo.edge_corners()
    return (
        np.ascontiguousarray(torch.cat([ua, ub], 1).numpy()),
        ea.numpy(),
        eb.numpy(),
        topo.corners().numpy(),
    )


@inline
def quad_area(q: np.ndarray, i: int, j: int, w: int) -> float:
    """The area of pixel ``(i, j)``'s corner quad (``q``: the ``(h + 1)(w + 1)`` corners)."""
    a, b = i * (w + 1) + j, i * (w + 1) + j + 1
    d, e = (i + 1) * (w + 1) + j + 1, (i + 1) * (w + 1) + j
    s = (q[b, 1] - q[a, 1]) * (q[a, 0] + q[b, 0]) / 2
    s += (q[d, 1] - q[b, 1]) * (q[b, 0] + q[d, 0]) / 2
    s += (q[e, 1] - q[d, 1]) * (q[d, 0] + q[e, 0]) / 2
    s += (q[a, 1] - q[e, 1]) * (q[e, 0] + q[a, 0]) / 2
    return abs(s)


@serial
def _corners_share(
    t: int, nt: int, kind: int, centred: bool, corners: np.ndarray, th: np.ndarray, c: np.ndarray,
    q: np.ndarray, dq: np.ndarray, phi_work: tuple, all_pts: np.ndarray, all_out: np.ndarray,
) -> None:  # fmt: skip
    """Thread ``t``'s chunks of corners (in turn), deformed into ``q`` ``(V0, 2)`` with their
    θ-derivatives ``dq`` ``(V0, 2, P)``; work space: [`_phi_work`][]'s, the points
    ``(T, 2, CHUNK)`` and their map ``(T, 2 + 2P, CHUNK)``."""
    nc = corners.shape[0]
    qi, work = own(phi_work[0], t, nt), own(phi_work[1], t, nt)
    pts, out = own(all_pts, t, nt), own(all_out, t, nt)
    for chunk in range(t, (nc + CHUNK - 1) // CHUNK, nt):
        v0, n = chunk * CHUNK, min(CHUNK, nc - chunk * CHUNK)
        for i in range(n):
            pts[0, i], pts[1, i] = corners[v0 + i, 0], corners[v0 + i, 1]
        phi_run(kind, centred, th, c, pts, n, out, qi, work)
        unpack_point(out, n, q[v0:], dq[v0:])


def _corners(
    kind: int, centred: bool, corners: np.ndarray, th: np.ndarray, c: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Deformed corners ``(V0, 2)`` and their θ-derivatives ``(V0, 2, P)``."""
    nc, p = corners.shape[0], th.shape[0]
    q, dq = np.empty((nc, 2)), np.empty((nc, 2, p))
    nt = threads(nc)
    work = (_phi_work(nt, p), per_thread(nt, (2, CHUNK)), per_thread(nt, (2 + 2 * p, CHUNK)))
    run_shares(_corners_share, nt, kind, centred, corners, th, c, q, dq, *work)
    return q, dq


@inline
def edge_segments(
    e: int, first: int, end: int, ea: np.ndarray, eb: np.ndarray, ncorner: int,
    seg_start: np.ndarray, seg_end: np.ndarray, seg_edge: np.ndarray,
) -> None:  # fmt: skip
    """Edge ``e``'s segments ``first .. end − 1``: segment ``s`` starts at the new vertex
    ``V0 + s − e − 1`` unless it is the edge's first (then at its corner ``ea[e]``), and ends at
    the next unless it is the last (then at ``eb[e]``)."""
    last = end - 1
    for s in range(first, last + 1):
        seg_edge[s] = e
        seg_start[s] = ea[e] if s == first else ncorner + s - e - 1
        seg_end[s] = eb[e] if s == last else ncorner + s - e


@inline
def piece_moves(dbounds: np.ndarray, pc: int, p: int) -> bool:
    """Whether piece ``pc``'s ends move with θ (a learned centre, ``P = 4``, moves the kinks)."""
    moves = False
    if p == 4:
        for r in range(p):
            moves = moves or dbounds[pc, 0, r] != 0 or dbounds[pc, 1, r] != 0
    return moves


@inline
def add_moving(
    dverts: np.ndarray, v: int, dq: np.ndarray, p: int, dx: float, dy: float, dbounds: np.ndarray, pc: int,
    f: float,
) -> None:  # fmt: skip
    """Vertex ``v``'s share ``J (b − a) (∂lo/∂θ (1 − f) + ∂hi/∂θ f)`` of its piece's moving ends,
    added to ``dverts[v]`` (``dq[:, P:P + 2]``: φ's Jacobian there, ``(dx, dy)``: the edge)."""
    for r in range(p):
        dt = dbounds[pc, 0, r] * (1 - f) + dbounds[pc, 1, r] * f
        if dt != 0:
            dverts[v, 0, r] += (dq[0, p] * dx + dq[0, p + 1] * dy) * dt
            dverts[v, 1, r] += (dq[1, p] * dx + dq[1, p + 1] * dy) * dt


@inline
def pixel_vertex(x: float, y: float, ws: float, hs: float) -> tuple[float, float]:
    """A vertex in pixel units of a ``ws`` x ``hs`` source, clamped to it."""
    return min(max((x + 1) * (ws / 2), 0.0), ws), min(max((y + 1) * (hs / 2), 0.0), hs)


@serial
def place_chunk(
    kind: int, centred: bool, ends: np.ndarray, th: np.ndarray, c: np.ndarray, piece_offsets: np.ndarray,
    bounds: np.ndarray, dbounds: np.ndarray, counts: np.ndarray, edge_offsets: np.ndarray, e0: int, e1: int,
    pts: np.ndarray, out: np.ndarray, moving: np.ndarray, qi: np.ndarray, dq: np.ndarray,
    verts: np.ndarray, dverts: np.ndarray,
) -> None:  # fmt: skip
    """The new vertices of edges ``e0 .. e1 − 1`` into ``verts[i]`` ``(2,)`` and ``dverts[i]``
    ``(2, P)``, ``i`` counted from the chunk's first new vertex (segment ``s`` of edge ``e`` ends
    at new vertex ``s − e`` of the mesh unless it is the edge's last): their points first, then
    one loop of [`phi_run`][]; ``pts``, ``out``, ``moving``, ``qi``, ``dq``: work space."""
    p = th.shape[0]
    base = edge_offsets[e0] - e0
    nm = 0  # the chunk's pieces that move with a learned centre: (piece, edge, first segment)
    for e in range(e0, e1):  # each new vertex's point on its edge
        s = first = edge_offsets[e]
        ax, ay = ends[e, 0], ends[e, 1]
        dx, dy = ends[e, 2] - ax, ends[e, 3] - ay
        for pc in range(piece_offsets[e], piece_offsets[e + 1]):
            m = counts[pc]
            lo, hi = bounds[pc, 0], bounds[pc, 1]
            if piece_moves(dbounds, pc, p):
                moving[nm, 0], moving[nm, 1], moving[nm, 2] = pc, e, s
                nm += 1
            for k in range(m):
                if s != first:
                    t = lo + (hi - lo) * (k / m)
                    i = s - e - 1 - base
                    pts[0, i], pts[1, i] = ax + t * dx, ay + t * dy
                s += 1
    n = edge_offsets[e1] - e1 - base
    phi_run(kind, centred, th, c, pts, n, out, qi, dq)  # the chunk's new vertices in one loop
    unpack_point(out, n, verts, dverts)
    for j in range(nm):  # a piece's ends move with a learned centre: its vertices too
        pc, e, s = moving[j, 0], moving[j, 1], moving[j, 2]
        ax, ay = ends[e, 0], ends[e, 1]
        dx, dy = ends[e, 2] - ax, ends[e, 3] - ay
        m, lo, hi = counts[pc], bounds[pc, 0], bounds[pc, 1]
        for k in range(m):
            if s + k != edge_offsets[e]:
                f = k / m
                t = lo + (hi - lo) * f
                v = s + k - e - 1 - base
                phi_point(kind, centred, ax + t * dx, ay + t * dy, th, c, qi, dq)
                add_moving(dverts, v, dq, p, dx, dy, dbounds, pc, f)


@serial
def _place_share(
    t: int, nt: int, kind: int, centred: bool, ends: np.ndarray, ea: np.ndarray, eb: np.ndarray,
    th: np.ndarray, c: np.ndarray, piece_offsets: np.ndarray, bounds: np.ndarray, dbounds: np.ndarray,
    counts: np.ndarray, edge_offsets: np.ndarray, ncorner: int, span: int,
    verts: np.ndarray, dverts: np.ndarray, seg_start: np.ndarray, seg_end: np.ndarray, seg_edge: np.ndarray,
    work: tuple,
) -> None:  # fmt: skip
    """Segments and interior vertices of every edge, numbered as [`pixel_mesh`][layoutwarp.mesh.pixel_mesh]
    numbers them: segment ``s`` of edge ``e`` starts at the new vertex ``V0 + s − e − 1`` unless
    it is the edge's first. A chunk's new vertices are consecutive (``span``: the most a chunk
    has), placed by [`place_chunk`][]; thread ``t`` of ``nt`` takes every ``nt``-th chunk, with
    its rows of ``work`` ([`place_work`][])."""
    ne = ends.shape[0]
    n_chunks = (ne + CHUNK - 1) // CHUNK
    mesh = (kind, centred, ends, th, c, piece_offsets, bounds, dbounds, counts, edge_offsets)
    qi, dq = own(work[0], t, nt), own(work[1], t, nt)
    pts, out, moving = own(work[2], t, nt), own(work[3], t, nt), own(work[4], t, nt)
    for chunk in range(t, n_chunks, nt):
        e0, e1 = chunk * CHUNK, min((chunk + 1) * CHUNK, ne)
        for e in range(e0, e1):
            edge_segments(
                e, edge_offsets[e], edge_offsets[e + 1], ea, eb, ncorner, seg_start, seg_end, seg_edge
            )
        v0 = ncorner + edge_offsets[e0] - e0
        place_chunk(*mesh, e0, e1, pts, out, moving, qi, dq, verts[v0:], dverts[v0:])


@dataclass
class _Counted:
    """The count stage's results (see [`count_stage`][])."""

    th: np.ndarray
    c: np.ndarray
    corners: np.ndarray  # (V0, 2) deformed corners
    dcorners: np.ndarray  # (V0, 2, P) their θ-derivatives
    piece_offsets: np.ndarray  # (E + 1,) each edge's smooth pieces
    bounds: np.ndarray  # (pieces, 2) their parameter ranges
    dbounds: np.ndarray  # (pieces, 2, P) and their θ-derivatives
    counts: np.ndarray  # (pieces,) segments a piece
    edge_offsets: np.ndarray  # (E + 1,) segments an edge
    span: int  # the most new vertices a chunk of edges has


def count_stage(
    spec: MeshSpec, size: tuple[int, int], theta: np.ndarray, tol: float, max_subdiv: int, with_grad: bool
) -> _Counted:
    """Corners, every edge's smooth pieces and their segment counts: what the vertices' placement
    needs ([`build_mesh`][], [`mesh_integrals`][])."""
    h, w = size
    ends, _, _, uniform = mesh_topology(size)
    th = np.ascontiguousarray(theta, dtype=np.float64)
    c = np.array(spec.center, dtype=np.float64)
    args = (spec.kind, spec.centred)
    cq, cdq = _corners(*args, uniform, th, c)
    ne = len(ends)
    nt = threads(ne * EDGE_WORK)
    npieces = np.empty(ne, dtype=np.int64)
    work = _edge_work(nt, len(th))
    run_shares(_count_share, nt, *args, ends, th, c, npieces, work, False)
    piece_offsets = np.zeros(ne + 1, dtype=np.int64)
    np.cumsum(npieces, out=piece_offsets[1:])
    total = int(piece_offsets[-1])
    bounds, dbounds = np.empty((total, 2)), np.empty((total, 2, len(th)))
    counts, edge_offsets = np.empty(total, dtype=np.int64), np.empty(ne + 1, dtype=np.int64)
    chunk_ends = np.r_[0:ne:CHUNK, ne]
    span = int(np.diff(piece_offsets[chunk_ends]).max())  # the most pieces a chunk has
    sag, length, swept = np.empty(total), np.empty(total), np.empty(ne)
    p = len(th)
    points = (per_thread(nt, (2, NS * span)), per_thread(nt, (2 + 2 * p, NS * span)))
    work = (work, _phi_work(nt, p), *points)
    run_shares(
        _pieces_share, nt, *args, ends, th, c, piece_offsets, with_grad, bounds, dbounds, sag, length,
        swept, *work, True,
    )  # fmt: skip
    run_shares(
        _counts_share, nt, h, w, cq, swept, piece_offsets, sag, length, float(tol), int(max_subdiv),
        counts, edge_offsets,
    )  # fmt: skip
    edge_offsets[0] = 0
    np.cumsum(edge_offsets, out=edge_offsets)
    warn_if_capped(int(counts.max(initial=0)), max_subdiv)
    vspan = int(np.diff(edge_offsets[chunk_ends] - chunk_ends).max())  # the most new vertices a chunk has
    return _Counted(th, c, cq, cdq, piece_offsets, bounds, dbounds, counts, edge_offsets, vspan)


def build_mesh(
    spec: MeshSpec,
    size: tuple[int, int],
    theta: np.ndarray,
    tol: float,
    *,
    max_subdiv: int = MAX_SUBDIV,
    with_grad: bool = True,
) -> CompiledMesh:
    """The mesh [`pixel_mesh`][layoutwarp.mesh.pixel_mesh] builds for the layout of ``spec`` at ``theta``
    (``(P,)`` float64) with tolerance ``tol``, compiled, with every vertex's θ-derivative.

    ``with_grad`` bounds the polylines' error in ``∂φ/∂θ`` too (as ``pixel_mesh`` does when θ
    requires grad), as ``layoutwarp.mesh._edge_parameters`` says.
    """
    h, w = size
    ends, ea, eb, _ = mesh_topology(size)
    k = count_stage(spec, size, theta, tol, max_subdiv, with_grad)
    ne, nseg, ncorner = len(ends), int(k.edge_offsets[-1]), (h + 1) * (w + 1)
    verts, dverts = np.empty((ncorner + nseg - ne, 2)), np.empty((ncorner + nseg - ne, 2, len(k.th)))
    verts[:ncorner], dverts[:ncorner] = k.corners, k.dcorners
    seg_start, seg_end, seg_edge = (np.empty(nseg, dtype=np.int64) for _ in range(3))
    nt = threads(ne * EDGE_WORK)
    run_shares(
        _place_share, nt, spec.kind, spec.centred, ends, ea, eb, k.th, k.c, k.piece_offsets, k.bounds,
        k.dbounds, k.counts, k.edge_offsets, ncorner, k.span, verts, dverts, seg_start, seg_end, seg_edge,
        place_work(nt, len(k.th), k.span),
    )  # fmt: skip
    return CompiledMesh((h, w), verts, dverts, seg_start, seg_end, seg_edge, k.edge_offsets, k.counts)


def _phi_work(nt: int, p: int) -> tuple[np.ndarray, np.ndarray]:
    """Each of ``nt`` threads' work space for [`phi_point`][]: a point ``(2,)`` and its derivatives
    ``(2, P + 2)``."""
    return per_thread(nt, (2,)), per_thread(nt, (2, p + 2))


def _edge_work(nt: int, p: int) -> tuple[np.ndarray, ...]:
    """Each of ``nt`` threads' work space for [`edge_pieces`][]: ``scratch`` ``(8, P)``, ``cuts``
    ``(8,)``, ``dcuts`` ``(8, P)``, ``lo`` ``(10,)``, ``dlo`` ``(10, P)``."""
    cuts, los = per_thread(nt, (8,)), per_thread(nt, (10,))
    return per_thread(nt, (8, p)), cuts, per_thread(nt, (8, p)), los, per_thread(nt, (10, p))


def place_work(nt: int, p: int, span: int) -> tuple[np.ndarray, ...]:
    """Each of ``nt`` threads' work space for [`place_chunk`][] of a chunk of at most ``span`` new
    vertices: [`_phi_work`][]'s, their points ``(2, span)`` and map ``(2 + 2P, span)``, and the
    chunk's moving pieces ``(10·CHUNK, 3)`` (9 pieces an edge at most)."""
    pts, out = per_thread(nt, (2, span)), per_thread(nt, (2 + 2 * p, span))
    return (*_phi_work(nt, p), pts, out, per_thread(nt, (10 * CHUNK, 3), np.int64))


#: What an edge costs the mesh's kernels, in elements of [`threads`][layoutwarp.kernels.base.threads]' work.
EDGE_WORK = 64
