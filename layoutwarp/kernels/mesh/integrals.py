"""A training step's integrals on the CPU without holding the mesh ([`mesh_integrals`][]: the
edge integrals and their θ-Jacobian, chunk by chunk), and the backward: the quotient rule
([`edge_gradient`][]) and one contraction ([`theta_gradient`][])."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from ...mesh import MAX_SUBDIV
from ..base import CHUNK, inline, own, per_thread, run_chunks, run_shares, serial, take, threads, tries
from ..exact import segment_moments
from ..prefix import BLOCK
from .build import EDGE_WORK, count_stage, mesh_topology, pixel_vertex, place_chunk, place_work
from .spec import CompiledMesh, MeshSpec

if TYPE_CHECKING:
    pass


@inline
def _still(v: np.ndarray) -> bool:
    """Whether a vertex's θ-velocity ``v`` ``(2, P)`` is zero (φ the identity about it)."""
    for r in range(v.shape[1]):
        if v[0, r] != 0 or v[1, r] != 0:
            return False
    return True


@serial
def _integrate_share(
    t: int, nt: int, claims: np.ndarray, kind: int, centred: bool, ends: np.ndarray, ea: np.ndarray,
    eb: np.ndarray, th: np.ndarray, c: np.ndarray, piece_offsets: np.ndarray, bounds: np.ndarray,
    dbounds: np.ndarray, counts: np.ndarray, edge_offsets: np.ndarray, corners: np.ndarray,
    dcorners: np.ndarray, incl: np.ndarray, offsets: np.ndarray, block: int, ws: float, hs: float,
    span: int, out: np.ndarray, jac: np.ndarray, work: tuple, all_verts: np.ndarray,
    all_dverts: np.ndarray, sums: tuple,
) -> None:  # fmt: skip
    """[`mesh_integrals`][] a chunk of edges at a time: its new vertices into work space
    ([`place_chunk`][]), in pixel units as [`_to_pixels`][] gives them; its segments'
    integrals (each edge summed in segment order), moments
    ([`segment_moments`][]) and θ-Jacobian while the segment is at hand.
    ``corners`` ``(V0, 2)`` in pixel units, ``span``: the most new vertices a chunk has; into
    ``out`` ``(N + 1, E)`` and ``jac`` ``(N + 1, E, P)``, every edge's written once, from work
    space (no zeroing). Thread ``t`` of ``nt`` takes every ``nt``-th chunk, then the others' left
    ([`run_chunks`][layoutwarp.kernels.base.run_chunks]), with its rows of the work space:
    ``work`` ([`place_work`][]), the chunk's new vertices ``(T, span, 2)`` and their
    θ-derivatives ``(T, span, 2, P)``, and ``sums`` ([`_integral_work`][]: a segment's integrals
    and moments, an edge's θ-Jacobian and integrals)."""
    ne, p, n = ends.shape[0], th.shape[0], incl.shape[2]
    sx, sy = ws / 2, hs / 2  # ∂X/∂x, ∂Y/∂y
    mesh = (kind, centred, ends, th, c, piece_offsets, bounds, dbounds, counts, edge_offsets)
    qi, dq = own(work[0], t, nt), own(work[1], t, nt)
    pts, rows, moving = own(work[2], t, nt), own(work[3], t, nt), own(work[4], t, nt)
    verts, dverts = own(all_verts, t, nt), own(all_dverts, t, nt)
    acc, ma = own(sums[0], t, nt), own(sums[1], t, nt)
    mb, ej, oe = own(sums[2], t, nt), own(sums[3], t, nt), own(sums[4], t, nt)
    for m in range(tries(claims, nt)):
        chunk = take(claims, t, nt, m)
        if chunk < 0:
            continue
        e0, e1 = chunk * CHUNK, min((chunk + 1) * CHUNK, ne)
        place_chunk(*mesh, e0, e1, pts, rows, moving, qi, dq, verts, dverts)
        base = edge_offsets[e0] - e0
        for i in range(edge_offsets[e1] - e1 - base):
            verts[i, 0], verts[i, 1] = pixel_vertex(verts[i, 0], verts[i, 1], ws, hs)
        for e in range(e0, e1):
            first, last = edge_offsets[e], edge_offsets[e + 1] - 1
            ej[:, :] = 0.0
            oe[:] = 0.0
            x1, y1 = corners[ea[e], 0], corners[ea[e], 1]
            vb = dcorners[ea[e]]  # the θ-velocity (2, P) of the segment's end, then of its start
            for s in range(first, last + 1):
                x0, y0, va = x1, y1, vb
                i = s - e - base  # the segment's end is new vertex i, unless it is the edge's last
                if s == last:
                    x1, y1, vb = corners[eb[e], 0], corners[eb[e], 1], dcorners[eb[e]]
                else:
                    x1, y1, vb = verts[i, 0], verts[i, 1], dverts[i]
                if y1 == y0 and _still(va) and _still(vb):  # no ∫ P dY, and no θ moves it: adds 0
                    continue
                segment_moments(x0, y0, x1, y1, incl, offsets, block, acc, ma, mb)
                for k in range(n + 1):
                    oe[k] += acc[0, k]
                nx, ny = (y1 - y0) * sx, (x0 - x1) * sy  # the normal, times dX/dx and dY/dy
                for r in range(p):  # ν·v at both ends, times the moments
                    da = nx * va[0, r] + ny * va[1, r]
                    db = nx * vb[0, r] + ny * vb[1, r]
                    for k in range(n):
                        ej[k, r] += ma[0, k] * da + mb[0, k] * db
                    ej[n, r] += (da + db) / 2
            for k in range(n + 1):
                out[k, e] = oe[k]
                for r in range(p):
                    jac[k, e, r] = ej[k, r]


def mesh_integrals(
    spec: MeshSpec,
    size: tuple[int, int],
    theta: np.ndarray,
    tol: float,
    tables: tuple[np.ndarray, np.ndarray],
    src_size: tuple[int, int],
    *,
    max_subdiv: int = MAX_SUBDIV,
) -> tuple[np.ndarray, np.ndarray]:
    """The exact integrator's edge integrals ``(N + 1, E)`` of [`build_mesh`][]'s mesh (with
    ``with_grad``) over an ``(H, W)`` source of prefix tables ``tables``
    ([`prefix_tables`][layoutwarp.kernels.prefix_tables]), as
    [`exact_forward`][layoutwarp.kernels.exact_forward]
    gives them for the mesh's [`pixel_vertices`][], and their θ-Jacobian ``(N + 1, E, P)``,
    without the mesh's arrays: each chunk of edges places its vertices in work space of its own
    and integrates its segments while they are in cache (a training step's mesh is 50–100 MB of
    vertices, θ-derivatives and indices at 2048x1024 → 257x129, written once and read twice).

    The Jacobian is the Reynolds transport theorem in forward mode: segment ``s`` from ``a`` to
    ``b`` of edge ``e`` adds ``ma[n]·v_a + mb[n]·v_b`` to row ``n`` and ``(v_a + v_b)/2`` to the
    area row ``N``, with its normal ``ν = (ΔY, −ΔX)``, ``v = ν · (W/2 ∂x/∂θ, H/2 ∂y/∂θ)`` at each
    end and its moments ``ma[n] = ∫ (1 − t) L_n dt``, ``mb[n] = ∫ t L_n dt``
    ([`segment_moments`][]); θ's gradient is then one contraction with
    the edge gradient ([`edge_gradient`][], [`theta_gradient`][]).
    """
    hs, ws = src_size
    ends, ea, eb, _ = mesh_topology(size)
    k = count_stage(spec, size, theta, tol, max_subdiv, True)
    corners = _to_pixels(k.corners, float(ws), float(hs))
    ne, n, p = len(ends), tables[0].shape[2], len(k.th)
    out, jac = np.empty((n + 1, ne)), np.empty((n + 1, ne, p))
    nt = threads(ne * EDGE_WORK)
    space = (per_thread(nt, (k.span, 2)), per_thread(nt, (k.span, 2, p)), _integral_work(nt, n, p))
    run_chunks(
        _integrate_share, nt, (ne + CHUNK - 1) // CHUNK, spec.kind, spec.centred, ends, ea, eb, k.th, k.c,
        k.piece_offsets, k.bounds, k.dbounds, k.counts, k.edge_offsets, corners, k.dcorners, *tables, BLOCK,
        float(ws), float(hs), k.span, out, jac, place_work(nt, p, k.span), *space,
    )  # fmt: skip
    return out, jac


def _integral_work(nt: int, n: int, p: int) -> tuple[np.ndarray, ...]:
    """Each of ``nt`` threads' work space for the integrals of ``n`` channels: a segment's
    integrals ``(1, N + 1)`` and moments ``(1, N)`` twice, an edge's θ-Jacobian ``(N + 1, P)`` and
    integrals ``(N + 1,)``."""
    segment = per_thread(nt, (1, n + 1)), per_thread(nt, (1, n)), per_thread(nt, (1, n))
    return (*segment, per_thread(nt, (n + 1, p)), per_thread(nt, (n + 1,)))


@serial
def _to_pixels_share(t: int, nt: int, verts: np.ndarray, ws: float, hs: float, out: np.ndarray) -> None:
    nv = verts.shape[0]
    for v in range(t * nv // nt, (t + 1) * nv // nt):
        out[v, 0], out[v, 1] = pixel_vertex(verts[v, 0], verts[v, 1], ws, hs)


def _to_pixels(verts: np.ndarray, ws: float, hs: float) -> np.ndarray:
    out = np.empty_like(verts)
    run_shares(_to_pixels_share, threads(len(verts)), verts, ws, hs, out)
    return out


def pixel_vertices(mesh: CompiledMesh, src_size: tuple[int, int]) -> np.ndarray:
    """The mesh's vertices in pixel units of an ``(H, W)`` source, clamped to it, as
    [`pixel_vertices`][layoutwarp.mesh.PixelMesh.pixel_vertices] gives them."""
    hs, ws = src_size
    return _to_pixels(mesh.vertices, float(ws), float(hs))


@serial
def _pixel_gradient_share(
    t: int, nt: int, grad: np.ndarray, means: np.ndarray, areas: np.ndarray, area_grad: np.ndarray,
    gp: np.ndarray,
) -> None:  # fmt: skip
    """Rows ``t·h/T ..`` of the pixels' boundary integrals' gradient ``gp`` ``(N + 1, h, w)``: the
    quotient rule."""
    n, h, w = grad.shape
    own = area_grad.shape[0] > 0
    for i in range(t * h // nt, (t + 1) * h // nt):
        for j in range(w):
            acc = 0.0
            for k in range(n):
                gp[k, i, j] = grad[k, i, j] / areas[i, j]
                acc += grad[k, i, j] * means[k, i, j]
            gp[n, i, j] = -acc / areas[i, j] + area_grad[i, j] if own else -acc / areas[i, j]


@serial
def _edge_gradient_share(t: int, nt: int, gp: np.ndarray, out: np.ndarray) -> None:
    """Rows ``t·h/T ..`` of every edge's gradient ``out`` ``(N + 1, E)``: + the pixel it bounds
    above / on the right, − below / left."""
    n1, h, w = gp.shape
    nh = (h + 1) * w
    for k in range(n1):
        for i in range(t * (h + 1) // nt, (t + 1) * (h + 1) // nt):
            for j in range(w):
                top = gp[k, i, j] if i < h else 0.0
                out[k, i * w + j] = top - gp[k, i - 1, j] if i > 0 else top
        for i in range(t * h // nt, (t + 1) * h // nt):
            for j in range(w + 1):
                right = gp[k, i, j - 1] if j > 0 else 0.0
                out[k, nh + i * (w + 1) + j] = right - gp[k, i, j] if j < w else right


def edge_gradient(
    grad: np.ndarray, means: np.ndarray, areas: np.ndarray, area_grad: np.ndarray | None = None
) -> np.ndarray:
    """The gradient ``(N + 1, E)`` of a mesh's edge integrals (``N`` channels and the area, as
    [`MeshTopology`][] numbers the edges) from the gradient ``grad``
    ``(N, H, W)`` of the pixel means ``means = Σ_edges / areas`` and, where the areas ``(H, W)``
    are an output too (sensor physics), ``area_grad``, the gradient of the areas themselves: the
    quotient rule, then [`combine_adjoint`][layoutwarp.mesh.MeshTopology.combine_adjoint], in one
    compiled pass."""
    own = np.zeros((0, 0)) if area_grad is None else area_grad
    args = [np.ascontiguousarray(a, dtype=np.float64) for a in (grad, means, areas, own)]
    n, h, w = args[0].shape
    gp, out = np.empty((n + 1, h, w)), np.empty((n + 1, (h + 1) * w + h * (w + 1)))
    nt = threads(grad.size + means.size)
    run_shares(_pixel_gradient_share, nt, *args, gp)
    run_shares(_edge_gradient_share, nt, gp, out)
    return out


@serial
def _contract_share(t: int, nt: int, g: np.ndarray, jac: np.ndarray, part: np.ndarray) -> None:
    """Thread ``t``'s chunks of 4096 rows (in turn), each chunk's sums into its row of ``part``."""
    rows, p = jac.shape
    for c in range(t, part.shape[0], nt):
        for r in range(c * 4096, min(rows, (c + 1) * 4096)):
            for q in range(p):
                part[c, q] += g[r] * jac[r, q]


def theta_gradient(g_edge: np.ndarray, jac: np.ndarray) -> np.ndarray:
    """θ's gradient ``(P,)`` from the edge integrals' gradient ``g_edge`` ``(N + 1, E)``
    ([`edge_gradient`][]) and their θ-Jacobian ``jac`` ``(N + 1, E, P)``
    ([`mesh_integrals`][]): ``Σ g_edge[n, e]·jac[n, e, :]``, compiled and with no BLAS call,
    whose worker threads would keep spinning on the cores into the next step's kernels (a
    2048x1024 → 257x129 fovea step ran 2.5x slower with numpy's ``@`` here)."""
    p = jac.shape[-1]
    g, j = np.ascontiguousarray(g_edge).reshape(-1), np.ascontiguousarray(jac).reshape(-1, p)
    part = np.zeros(((len(j) + 4095) // 4096, p))  # fixed chunks summed in order: any thread count
    run_shares(_contract_share, threads(jac.size), g, j, part)
    out = np.zeros(p)
    for row in part:  # in order, as a loop (numpy's sum would pair them)
        out += row
    return out
