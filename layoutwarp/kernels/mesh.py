"""Compiled pixel meshes of the built-in curved families, with every vertex's θ-derivative.

[`pixel_mesh`][layoutwarp.mesh.pixel_mesh] builds a learnable layout's mesh in some thousand torch
operations (cut every edge at φ's kinks, bound each piece's sagitta, count its segments, place
the vertices, then autograd back through all of it): on a CPU it costs more than the integral,
on a GPU each operation is a kernel launch. For the curvilinear families (``curv`` and
``fovea``, about any centre, and ``elliptic``) this module does the same in one compiled pass:
φ, its Jacobian and ``∂φ/∂θ`` in closed form as numba functions without a branch on the point
(so a chunk's sample points and new vertices are mapped in one loop that runs in SIMD lanes,
[`_phi_run`][]), the kinks of every edge (with their θ-derivatives where they move with a
learned centre), the count stage and the vertex placement, each step in the order and arithmetic
of [`pixel_mesh`][layoutwarp.mesh.pixel_mesh], so the two agree to rounding (the same segment counts,
vertices within a few ulp). Instead of an
autograd graph it returns ``∂v/∂θ`` of every vertex ``v``: for a vertex at parameter
``t = lo + (hi − lo) k/m`` of a smooth piece of the uniform edge ``a + t (b − a)``,
``dv/dθ = ∂φ/∂θ + J (b − a) (∂lo/∂θ (1 − k/m) + ∂hi/∂θ k/m)``, the second term where the piece's
ends (kinks) move with θ. For a training step on the CPU, [`mesh_integrals`][] places the
vertices and integrates over them chunk by chunk, carrying ``∂v/∂θ`` to the θ-Jacobian of every
edge integral, so θ's gradient is one contraction with the edge gradient.
On a CUDA device [`build_mesh_device`][] builds the same mesh there, one GPU thread per
corner, edge or vertex running the same scalar functions.

[`mesh_spec`][] says whether a layout has a compiled form (exactly these classes: a
subclass may change φ, so it keeps the torch path).
"""

from __future__ import annotations

import functools
import math
import warnings
from dataclasses import dataclass, field

import numpy as np
import torch

from ..caches import ObjectMemo, version_of
from ..layouts import CurvLayout, EllipticLayout, FoveaLayout, Layout
from ..mesh import INNER, MeshTopology, PixelMesh
from .base import CHUNK, available, inline, inline_ir, own, per_thread, run_shares, serial, threads
from .device import CHECKS, CUDA_THREADS, Stamps, cuda_launch, device_checks, host_mapped, stream_of
from .exact import BLOCK, prefix_block_item, prefix_offsets_item, segment_moments, segment_weights

__all__ = [
    "CUDA_KERNELS",
    "CURV",
    "ELLIPTIC",
    "CompiledMesh",
    "DeviceMesh",
    "MeshSpec",
    "build_mesh",
    "build_mesh_device",
    "device_means",
    "device_theta_gradient",
    "edge_gradient",
    "mesh_integrals",
    "mesh_spec",
    "pixel_vertices",
    "theta_gradient",
]

#: Family codes of the compiled maps.
CURV, ELLIPTIC = 0, 1


@dataclass(frozen=True)
class MeshSpec:
    """What the compiled mesh needs to know of a layout besides θ.

    Attributes:
        kind: [`CURV`][] (φ_curv about ``center``) or [`ELLIPTIC`][].
        center: the fixed centre ``(c_x, c_y)``; a learned one is θ's last two entries.
        centred: φ is the centred map itself (fixed centre at the origin): no affine step.
        nparams: θ's length ``P`` (2, or 4 with a learned centre).
    """

    kind: int
    center: tuple[float, float]
    centred: bool
    nparams: int


#: Each fixed centre tensor's values as last read ([`layoutwarp.caches`][]).
CENTRES = ObjectMemo("fixed centres")


def _centre_values(centre: torch.Tensor) -> tuple[float, float]:
    """A fixed centre's two values, read from its device once per tensor and version (a training
    step on a GPU then waits for no copy of it; writing to the tensor in place bumps its
    version)."""
    return CENTRES.get(centre, (version_of(centre),), lambda: tuple(centre.detach().double().cpu().tolist()))


def mesh_spec(layout: Layout) -> MeshSpec | None:
    """The compiled form of ``layout``, or ``None`` where it has none (or numba is missing)."""
    if not available():
        return None
    if type(layout) in (CurvLayout, FoveaLayout):
        c = _centre_values(layout.fixed_center)
        return MeshSpec(CURV, c, layout.centred, int(layout.num_params or 0))
    if type(layout) is EllipticLayout:
        return MeshSpec(ELLIPTIC, (0.0, 0.0), True, 2)
    return None


@dataclass
class CompiledMesh:
    """A pixel mesh as [`build_mesh`][] returns it: the arrays of a
    [`PixelMesh`][] (float64 / int64, CPU) plus ``dverts`` ``(V, 2, P)``, each
    vertex's derivative in θ, and ``counts``, the segments of every smooth piece (what
    ``pixel_mesh(..., subdivisions=counts)`` takes to rebuild the same mesh)."""

    size: tuple[int, int]
    vertices: np.ndarray
    dverts: np.ndarray
    seg_start: np.ndarray
    seg_end: np.ndarray
    seg_edge: np.ndarray
    edge_offsets: np.ndarray
    counts: np.ndarray

    def pixel_mesh(self, device: torch.device | str = "cpu") -> PixelMesh:
        """The [`PixelMesh`][] of these arrays (vertices without gradient)."""

        def t(a: np.ndarray) -> torch.Tensor:
            return torch.from_numpy(a).to(device)

        arrays = (self.vertices, self.seg_start, self.seg_end, self.seg_edge, self.edge_offsets)
        return PixelMesh(self.size, *(t(a) for a in arrays))


# ----------------------------------------------------------------------------------------
# The maps, one point at a time (arithmetic as in layoutwarp.layouts), without a branch on the
# point, so that a loop of them runs in SIMD lanes (4-5x the scalar code on AVX-512)
# ----------------------------------------------------------------------------------------
@inline
def _den(t: float) -> tuple:
    """``(A, B, C)`` with ``A + B (1 − r) + C r = 1 + t − 2tr`` summed as
    [`layoutwarp.layouts._denom`][] sums it (two non-negative terms), for any ``r`` in [0, 1]."""
    return (1 - t, 2 * t, 0.0) if t >= 0 else (1 + t, 0.0, 2 * (-t))


@inline
def _curv0(x: float, y: float, tx: float, ty: float, kx: tuple, ky: tuple) -> tuple:
    """φ_curv about the origin at ``(x, y)``: ``(φ_x, φ_y, ∂φ_x/∂θ_x, ∂φ_y/∂θ_y, J_00, J_01,
    J_10, J_11)`` with ``J`` the spatial Jacobian (the identity on and outside the unit circle);
    ``kx``, ``ky``: [`_den`][] of ``tx``, ``ty``."""
    r = math.sqrt(x * x + y * y)
    inside = r < 1
    dx = kx[0] + kx[1] * (1 - r) + kx[2] * r
    dy = ky[0] + ky[1] * (1 - r) + ky[2] * r
    sx, sy = (1 - tx) / dx, (1 - ty) / dy
    gx, gy = 2 * tx * (1 - tx) / dx**2, 2 * ty * (1 - ty) / dy**2
    ux = x / r if r > 0 else 0.0
    uy = y / r if r > 0 else 0.0
    return (
        x * (1 - tx) / dx if inside else x,
        y * (1 - ty) / dy if inside else y,
        2 * x * (r - 1) / dx**2 if inside else 0.0,
        2 * y * (r - 1) / dy**2 if inside else 0.0,
        sx + x * gx * ux if inside else 1.0,
        x * gx * uy if inside else 0.0,
        y * gy * ux if inside else 0.0,
        sy + y * gy * uy if inside else 1.0,
    )


@inline
def _curv(
    x: float, y: float, tx: float, ty: float, cx: float, cy: float, kx: tuple, ky: tuple, centred: bool
) -> tuple:
    """φ_curv about ``(cx, cy)`` (φ on the four rectangles between the centre and the sensor's
    sides, each scaled to the unit square) at ``(x, y)``: ``(φ_x, φ_y, ∂φ_x/∂θ (4), ∂φ_y/∂θ (4),
    J (4))`` with θ's entries ``(θ_x, θ_y, c_x, c_y)`` (the last two zero for a fixed centre) and
    ``J`` row-major."""
    if centred:
        fx, fy, dx, dy, j00, j01, j10, j11 = _curv0(x, y, tx, ty, kx, ky)
        return fx, fy, dx, 0.0, 0.0, 0.0, 0.0, dy, 0.0, 0.0, j00, j01, j10, j11
    gx = 1.0 if x >= cx else -1.0  # the side of the centre: s = 1 − σ c
    gy = 1.0 if y >= cy else -1.0
    sx, sy = 1 - gx * cx, 1 - gy * cy
    ux, uy = (x - cx) / sx, (y - cy) / sy
    fx, fy, dx, dy, j00, j01, j10, j11 = _curv0(ux, uy, tx, ty, kx, ky)
    out = ux * ux + uy * uy >= 1
    fix_x, fix_y = out | (abs(x) >= 1), out | (abs(y) >= 1)
    # ∂φ_i/∂c_j = δ_ij (1 − σ_i φ0_i) + s_i J0_ij (σ_j u_j − 1) / s_j
    return (
        x if fix_x else cx + sx * fx,
        y if fix_y else cy + sy * fy,
        0.0 if fix_x else sx * dx,
        0.0,
        0.0 if fix_x else (1 - gx * fx) + j00 * (gx * ux - 1),
        0.0 if fix_x else sx * j01 * (gy * uy - 1) / sy,
        0.0,
        0.0 if fix_y else sy * dy,
        0.0 if fix_y else sy * j10 * (gx * ux - 1) / sx,
        0.0 if fix_y else (1 - gy * fy) + j11 * (gy * uy - 1),
        j00,
        j01 * sx / sy,
        j10 * sy / sx,
        j11,
    )


@inline
def _sqrt0(x: float) -> float:
    return math.sqrt(x) if x > 0 else 0.0


@inline
def _inv(x: float) -> float:
    return 1 / x if x > 0 else 0.0


@inline
def _centre(th: np.ndarray, c: np.ndarray) -> tuple:
    """``(c_x, c_y)``: the learned centre (θ's last two entries) or the fixed one."""
    return (th[2], th[3]) if th.shape[0] == 4 else (c[0], c[1])


@inline
def _phi(
    kind: int, centred: bool, x: float, y: float, th: np.ndarray, c: np.ndarray, q: np.ndarray, dq: np.ndarray
) -> None:
    """φ at ``(x, y)`` into ``q`` (2,) and ``∂φ/∂θ`` into ``dq[:, :P]``; for CURV also the spatial
    Jacobian into ``dq[:, P:P + 2]`` (``dq`` is (2, P + 2))."""
    p = th.shape[0]
    if kind == 1:  # elliptic: E⁻¹ ∘ φ_curv ∘ E inside the open square
        for i in range(2):
            for j in range(dq.shape[1]):
                dq[i, j] = 0.0
        if abs(x) < 1 and abs(y) < 1:
            u, v = x * _sqrt0(1 - y * y / 2), y * _sqrt0(1 - x * x / 2)
            a, b, da, db, _, _, _, _ = _curv0(u, v, th[0], th[1], _den(th[0]), _den(th[1]))
            r2 = 2 * math.sqrt(2)
            sa, sb = 2 + a * a - b * b, 2 - a * a + b * b
            p1, m1 = _sqrt0(sa + r2 * a), _sqrt0(sa - r2 * a)
            p2, m2 = _sqrt0(sb + r2 * b), _sqrt0(sb - r2 * b)
            # (p − m)/2 as (p² − m²)/(2(p + m)) = r2·a/(p + m): no cancellation near the axes
            s1, s2 = p1 + m1, p2 + m2
            q[0], q[1] = r2 * a * _inv(s1), r2 * b * _inv(s2)
            # the Jacobian of E⁻¹ at (a, b) times ∂φ_curv/∂θ (diagonal); 1/m − 1/p as (p − m)/(p m)
            ip1, im1, ip2, im2 = _inv(p1), _inv(m1), _inv(p2), _inv(m2)
            dq[0, 0] = ((2 * a + r2) * ip1 - (2 * a - r2) * im1) / 4 * da
            dq[0, 1] = b * (r2 * a * _inv(s1)) * ip1 * im1 * db
            dq[1, 0] = a * (r2 * b * _inv(s2)) * ip2 * im2 * da
            dq[1, 1] = ((2 * b + r2) * ip2 - (2 * b - r2) * im2) / 4 * db
        else:
            q[0], q[1] = x, y
        return
    cx, cy = _centre(th, c)
    f = _curv(x, y, th[0], th[1], cx, cy, _den(th[0]), _den(th[1]), centred)
    q[0], q[1] = f[0], f[1]
    for r in range(p):
        dq[0, r], dq[1, r] = f[2 + r], f[6 + r]
    dq[0, p], dq[0, p + 1], dq[1, p], dq[1, p + 1] = f[10], f[11], f[12], f[13]


@inline
def _store(out: np.ndarray, i: int, f: tuple, p: int) -> None:
    """[`_curv`][]'s point ``f`` into column ``i`` of [`_phi_run`][]'s rows (θ of ``p``)."""
    out[0, i], out[1, i] = f[0], f[1]
    for r in range(p):
        out[2 + r, i], out[2 + p + r, i] = f[2 + r], f[6 + r]


@serial
def _phi_run(
    kind: int, centred: bool, th: np.ndarray, c: np.ndarray, pts: np.ndarray, n: int, out: np.ndarray,
    qi: np.ndarray, work: np.ndarray,
) -> None:  # fmt: skip
    """φ and ``∂φ/∂θ`` at the points ``(pts[0, i], pts[1, i])``, ``i < n``, into ``out[:, i]``:
    ``(φ_x, φ_y, ∂φ_x/∂θ (P), ∂φ_y/∂θ (P))``, as [`_phi`][] gives them. Rows, not points, are
    contiguous, and CURV runs one loop per case without a branch on θ inside it: the loop runs in
    SIMD lanes. ``qi`` ``(2,)``, ``work`` ``(2, P + 2)``: work space (ELLIPTIC's points)."""
    p = th.shape[0]
    if kind == 1:
        for i in range(n):
            _phi(kind, centred, pts[0, i], pts[1, i], th, c, qi, work)
            out[0, i], out[1, i] = qi[0], qi[1]
            for r in range(p):
                out[2 + r, i], out[2 + p + r, i] = work[0, r], work[1, r]
        return
    tx, ty, (cx, cy) = th[0], th[1], _centre(th, c)
    kx, ky = _den(tx), _den(ty)
    if centred:
        for i in range(n):
            _store(out, i, _curv(pts[0, i], pts[1, i], tx, ty, cx, cy, kx, ky, True), 2)
    elif p == 2:
        for i in range(n):
            _store(out, i, _curv(pts[0, i], pts[1, i], tx, ty, cx, cy, kx, ky, False), 2)
    else:
        for i in range(n):
            _store(out, i, _curv(pts[0, i], pts[1, i], tx, ty, cx, cy, kx, ky, False), 4)


@inline
def _unpack(out: np.ndarray, n: int, q: np.ndarray, dq: np.ndarray) -> None:
    """[`_phi_run`][]'s rows into points: ``q[i]`` (2,) and ``dq[i]`` (2, P) for ``i < n``."""
    p = dq.shape[2]
    for i in range(n):
        q[i, 0], q[i, 1] = out[0, i], out[1, i]
        for r in range(p):
            dq[i, 0, r], dq[i, 1, r] = out[2 + r, i], out[2 + p + r, i]


# ----------------------------------------------------------------------------------------
# Kinks of every uniform edge, with their θ-derivatives (as smooth_pieces and
# CurvLayout.edge_breakpoints)
# ----------------------------------------------------------------------------------------
@inline
def _circle(ax: float, ay: float, dx: float, dy: float, sx: float, sy: float, lo: float, hi: float) -> tuple:
    """``(k, t0, t1)``: the ``k`` (0–2) parameters in ``(lo, hi)`` where ``(a + t d) / s`` crosses
    the unit circle (``a`` relative to the centre)."""
    dsx, dsy, asx, asy = dx / sx, dy / sy, ax / sx, ay / sy
    qa = dsx * dsx + dsy * dsy
    qb = 2 * (asx * dsx + asy * dsy)
    qc = (asx * asx + asy * asy) - 1
    disc = qb * qb - 4 * qa * qc
    if not (disc > 0 and qa > 0):
        return 0, 0.0, 0.0
    sq = math.sqrt(disc)
    r0, r1 = (-qb - sq) / (2 * qa), (-qb + sq) / (2 * qa)
    ok0, ok1 = lo < r0 < hi, lo < r1 < hi
    if ok0 and ok1:
        return 2, r0, r1
    if ok0:
        return 1, r0, 0.0
    if ok1:
        return 1, r1, 0.0
    return 0, 0.0, 0.0


@inline_ir  # small, and called with six combinations of constants
def _add_kink(
    t: float, draw: np.ndarray, n: int, cuts: np.ndarray, dcuts: np.ndarray, k: int, grad: bool
) -> int:
    """Insert kink ``t`` (derivative row ``draw[n]``, moved along where ``grad``) into the sorted
    ``cuts[:k]`` if it lies inside ``(1e-6, 1 − 1e-6)``; returns the new count."""
    if not (t > 1e-6 and t < 1 - 1e-6):
        return k
    j = k
    while j > 0 and cuts[j - 1] > t:
        cuts[j] = cuts[j - 1]
        if grad:
            for r in range(dcuts.shape[1]):  # element by element: no slice copy on a GPU
                dcuts[j, r] = dcuts[j - 1, r]
        j -= 1
    cuts[j] = t
    if grad:
        for r in range(dcuts.shape[1]):
            dcuts[j, r] = draw[n, r]
    return k + 1


@inline
def _edge_pieces(
    kind: int, centred: bool, e: int, ends: np.ndarray, th: np.ndarray, c: np.ndarray,
    scratch: np.ndarray, cuts: np.ndarray, dcuts: np.ndarray, lo: np.ndarray, dlo: np.ndarray, grad: bool,
) -> int:  # fmt: skip
    """The smooth pieces of edge ``e``: the ``n + 1`` bounds (0, the kinks of φ along the edge, 1)
    into ``lo`` and, where ``grad``, their θ-derivatives into ``dlo``; returns ``n`` (pieces of
    1e-12 or less dropped). ``scratch`` (8, P), ``cuts`` (8,), ``dcuts`` (8, P) are work space."""
    p = th.shape[0]
    ax, ay, dx, dy = ends[e, 0], ends[e, 1], ends[e, 2] - ends[e, 0], ends[e, 3] - ends[e, 1]
    k = 0
    if grad:
        scratch[:, :] = 0.0
    if (abs(ax) >= 1 and dx == 0) or (abs(ay) >= 1 and dy == 0):
        pass  # a sensor side: φ is the identity along it, no kinks
    elif kind == 0 and centred:
        m, t0, t1 = _circle(ax, ay, dx, dy, 1.0, 1.0, -1.0, 2.0)
        if m > 0:
            k = _add_kink(t0, scratch, 0, cuts, dcuts, k, grad)
        if m > 1:
            k = _add_kink(t1, scratch, 0, cuts, dcuts, k, grad)
    elif kind == 0:
        cx, cy = (th[2], th[3]) if p == 4 else (c[0], c[1])
        b1, b2 = 1.0, 1.0  # the cuts at x = c_x, y = c_y (an axis-aligned edge has one at most)
        for j in range(2):
            dj, aj, cj = (dx, ax, cx) if j == 0 else (dy, ay, cy)
            if dj != 0:
                t = (cj - aj) / dj
                if 0 < t < 1:
                    if grad and p == 4:
                        scratch[1 + j, 2 + j] = 1 / dj
                    k = _add_kink(t, scratch, 1 + j, cuts, dcuts, k, grad)
                    b1, b2 = (t, b1) if t < b1 else (b1, t)
        for piece in range(3):  # the circle's crossings on each part between the cuts
            plo = 0.0 if piece == 0 else (b1 if piece == 1 else b2)
            phi_ = b1 if piece == 0 else (b2 if piece == 1 else 1.0)
            if plo >= phi_:  # an empty part (no cut there): no crossing in it
                continue
            mid = (plo + phi_) / 2
            gx = 1.0 if ax + mid * dx >= cx else -1.0
            gy = 1.0 if ay + mid * dy >= cy else -1.0
            sx, sy = 1 - gx * cx, 1 - gy * cy
            m, t0, t1 = _circle(ax - cx, ay - cy, dx, dy, sx, sy, plo, phi_)
            for i in range(m):
                t = t0 if i == 0 else t1
                if grad and p == 4:  # implicit derivative of |(a + t d − c) / s|² = 1
                    wx, wy = (ax + t * dx - cx) / sx, (ay + t * dy - cy) / sy
                    ft = 2 * (wx * dx / sx + wy * dy / sy)
                    scratch[3, :] = 0.0
                    scratch[3, 2] = -2 * wx * (gx * wx - 1) / sx / ft
                    scratch[3, 3] = -2 * wy * (gy * wy - 1) / sy / ft
                k = _add_kink(t, scratch, 3, cuts, dcuts, k, grad)
    lo[0] = 0.0
    if grad:
        dlo[0, :] = 0.0
    n = 0
    for i in range(k + 1):
        t = cuts[i] if i < k else 1.0
        if t - lo[n] > 1e-12:
            n += 1
            lo[n] = t
            if grad:
                for r in range(p):
                    dlo[n, r] = dcuts[i, r] if i < k else 0.0
    return n


# ----------------------------------------------------------------------------------------
# The mesh: pieces, counts, vertices (threads take chunks of edges in turn, with their own
# work space)
# ----------------------------------------------------------------------------------------
@serial
def _count_share(
    t: int, nt: int, kind: int, centred: bool, ends: np.ndarray, th: np.ndarray, c: np.ndarray,
    out: np.ndarray, work: tuple, grad: bool,
) -> None:  # fmt: skip
    """Thread ``t``'s chunks of edges (in turn): each edge's smooth pieces into ``out``;
    ``work``: [`_edge_work`][]'s arrays; ``grad``: False, passed as a value (a constant would
    compile [`_edge_pieces`][] a second time, beside [`_edge_bounds`][]'s)."""
    ne = ends.shape[0]
    scratch, cuts = own(work[0], t, nt), own(work[1], t, nt)
    dcuts, lo, dlo = own(work[2], t, nt), own(work[3], t, nt), own(work[4], t, nt)
    for chunk in range(t, (ne + CHUNK - 1) // CHUNK, nt):
        for e in range(chunk * CHUNK, min((chunk + 1) * CHUNK, ne)):
            out[e] = _edge_pieces(kind, centred, e, ends, th, c, scratch, cuts, dcuts, lo, dlo, grad)


@inline
def _sample_point(
    ax: float, ay: float, dx: float, dy: float, a: float, b: float, s: int, inner: float
) -> tuple[float, float]:
    """Sample ``s`` of the count stage on the piece ``[a, b]`` of the edge ``a + t d``: for
    ``s < 5`` the point at ``t = a + (b − a)·s/4``; 5 and 6 just inside its start and end
    (``inner`` of the way to the other end), where ``∂φ/∂θ`` may jump at a kink."""
    if s < 5:
        t = a + (b - a) * (s / 4)
        return ax + t * dx, ay + t * dy
    j = s - 5
    t0, t1 = a + (b - a) * ((4 * j) / 4), a + (b - a) * ((4 - 4 * j) / 4)
    x0, y0, x1, y1 = ax + t0 * dx, ay + t0 * dy, ax + t1 * dx, ay + t1 * dy
    return x0 + inner * (x1 - x0), y0 + inner * (y1 - y0)


@inline
def _segment_counts(
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
def _edge_bounds(
    kind: int, centred: bool, e: int, ends: np.ndarray, th: np.ndarray, c: np.ndarray,
    piece_offsets: np.ndarray, scratch: np.ndarray, cuts: np.ndarray, dcuts: np.ndarray,
    lo: np.ndarray, dlo: np.ndarray, bounds: np.ndarray, dbounds: np.ndarray, grad: bool = True,
) -> int:  # fmt: skip
    """Edge ``e``'s smooth pieces with their θ-derivatives ([`_edge_pieces`][]; one piece from
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
        _edge_pieces(kind, centred, e, ends, th, c, scratch, cuts, dcuts, lo, dlo, grad)
    for i in range(n):
        bounds[base + i, 0], bounds[base + i, 1] = lo[i], lo[i + 1]
        for r in range(p):
            dbounds[base + i, 0, r], dbounds[base + i, 1, r] = dlo[i, r], dlo[i + 1, r]
    return n


@inline
def _sagittas(
    out: np.ndarray, n: int, ns: int, grad: bool, p: int, sag: np.ndarray, length: np.ndarray
) -> None:  # fmt: skip
    """Chord length and sagitta bound of each of ``n`` pieces whose ``ns`` samples are columns
    ``q·ns ..`` of [`_phi_run`][]'s rows ``out`` (five along the piece, then, where ``grad``,
    two just inside its ends for ``∂φ/∂θ``, which may jump at a kink): the largest of the
    second differences of φ and, where ``grad``, of every ``∂φ/∂θ`` across the chord, over 8."""
    for q in range(n):
        k = q * ns
        chx, chy = out[0, k + 4] - out[0, k], out[1, k + 4] - out[1, k]
        ln = math.sqrt(chx * chx + chy * chy)
        ux, uy = chx / max(ln, 1e-300), chy / max(ln, 1e-300)
        sg = 0.0
        for s in range(1, 4):
            d2x = (out[0, k + s + 1] - 2 * out[0, k + s] + out[0, k + s - 1]) * 16
            d2y = (out[1, k + s + 1] - 2 * out[1, k + s] + out[1, k + s - 1]) * 16
            sg = max(sg, abs(ux * d2y - uy * d2x))
            if grad:  # the θ-velocity field bends the edge too (inner ends)
                i0 = k + 5 if s == 1 else k + s - 1
                i2 = k + 6 if s == 3 else k + s + 1
                for r in range(2, 2 + p):
                    vx = (out[r, i2] - 2 * out[r, k + s] + out[r, i0]) * 16
                    vy = (out[p + r, i2] - 2 * out[p + r, k + s] + out[p + r, i0]) * 16
                    sg = max(sg, abs(ux * vy - uy * vx))
        sag[q], length[q] = sg / 8, ln


@serial
def _pieces_share(
    t: int, nt: int, kind: int, centred: bool, ends: np.ndarray, th: np.ndarray, c: np.ndarray,
    piece_offsets: np.ndarray, amin: np.ndarray, tol: float, max_subdiv: int, with_grad: bool, inner: float,
    span: int, bounds: np.ndarray, dbounds: np.ndarray, counts: np.ndarray, edge_counts: np.ndarray,
    work: tuple, phi_work: tuple, all_pts: np.ndarray, all_out: np.ndarray, all_sag: np.ndarray,
    all_length: np.ndarray, kink_grad: bool,
) -> None:  # fmt: skip
    """Every smooth piece's parameter range (``bounds`` (pieces, 2), ``dbounds`` (pieces, 2, P))
    and its segment count, bounding the sagitta as [`layoutwarp.mesh._segment_counts`][] does,
    and every edge's segments (``edge_counts[e + 1]``; ``edge_counts[0]`` is left alone). A chunk
    of edges places its sample points first, maps them in one loop ([`_phi_run`][]), then
    counts; ``span``: the most pieces a chunk has. Thread ``t`` of ``nt`` takes every ``nt``-th
    chunk, with its rows of the work space: [`_edge_work`][]'s, [`_phi_work`][]'s, the sample
    points ``(T, 2, 7·span)`` and their map ``(T, 2 + 2P, 7·span)``, the pieces' sagittas and
    lengths ``(T, span)``; ``kink_grad``: True, as a value (see [`_count_share`][])."""
    ne, p = ends.shape[0], th.shape[0]
    n_chunks = (ne + CHUNK - 1) // CHUNK
    ns = 7 if with_grad else 5  # samples a piece: 5 along it, 2 just inside its ends
    scratch, cuts = own(work[0], t, nt), own(work[1], t, nt)
    dcuts, lo, dlo = own(work[2], t, nt), own(work[3], t, nt), own(work[4], t, nt)
    qi, dq = own(phi_work[0], t, nt), own(phi_work[1], t, nt)
    pts, out = own(all_pts, t, nt), own(all_out, t, nt)
    sag, length = own(all_sag, t, nt), own(all_length, t, nt)
    for chunk in range(t, n_chunks, nt):
        e0, e1 = chunk * CHUNK, min((chunk + 1) * CHUNK, ne)
        for e in range(e0, e1):
            base = piece_offsets[e]
            n = _edge_bounds(
                kind, centred, e, ends, th, c, piece_offsets, scratch, cuts, dcuts, lo, dlo,
                bounds, dbounds, kink_grad,
            )  # fmt: skip
            ax, ay = ends[e, 0], ends[e, 1]
            dx, dy = ends[e, 2] - ax, ends[e, 3] - ay
            for i in range(n):
                a, b = lo[i], lo[i + 1]
                k = (base + i - piece_offsets[e0]) * ns
                for s in range(ns):  # five along the piece; with_grad, two just inside its ends
                    pts[0, k + s], pts[1, k + s] = _sample_point(ax, ay, dx, dy, a, b, s, inner)
        npc = piece_offsets[e1] - piece_offsets[e0]
        _phi_run(kind, centred, th, c, pts, npc * ns, out, qi, dq)
        if with_grad and p == 4:  # θ's count a constant: the loop over pieces runs in SIMD lanes
            _sagittas(out, npc, ns, True, 4, sag, length)
        elif with_grad and p == 2:
            _sagittas(out, npc, ns, True, 2, sag, length)
        else:
            _sagittas(out, npc, ns, with_grad, p, sag, length)
        for e in range(e0, e1):
            first, last = piece_offsets[e], piece_offsets[e + 1]
            j0 = first - piece_offsets[e0]
            total = _segment_counts(sag, length, j0, last - first, first, amin[e], tol, max_subdiv, counts)
            edge_counts[e + 1] = total


@functools.lru_cache(maxsize=16)
def _topology(size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Uniform edge ends ``(E, 4)``, their corner indices and the uniform corners ``(V0, 2)`` of
    [`MeshTopology`][] as arrays (cached per size; do not modify)."""
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
def _quad_area(q: np.ndarray, i: int, j: int, w: int) -> float:
    """The area of pixel ``(i, j)``'s corner quad (``q``: the ``(h + 1)(w + 1)`` corners)."""
    a, b = i * (w + 1) + j, i * (w + 1) + j + 1
    d, e = (i + 1) * (w + 1) + j + 1, (i + 1) * (w + 1) + j
    s = (q[b, 1] - q[a, 1]) * (q[a, 0] + q[b, 0]) / 2
    s += (q[d, 1] - q[b, 1]) * (q[b, 0] + q[d, 0]) / 2
    s += (q[e, 1] - q[d, 1]) * (q[d, 0] + q[e, 0]) / 2
    s += (q[a, 1] - q[e, 1]) * (q[e, 0] + q[a, 0]) / 2
    return abs(s)


@inline
def _amin_across(area: np.ndarray, i: int, j: int) -> float:
    """The smaller area of the pixels above and below horizontal edge ``(i, j)`` (from the pixel
    areas ``area`` ``(h, w)``; the sensor's outside counts as infinite)."""
    up = area[i - 1, j] if i > 0 else np.inf
    return min(up, area[i, j] if i < area.shape[0] else np.inf)


@inline
def _amin_beside(area: np.ndarray, i: int, j: int) -> float:
    """The smaller area of the pixels left and right of vertical edge ``(i, j)``."""
    left = area[i, j - 1] if j > 0 else np.inf
    return min(left, area[i, j] if j < area.shape[1] else np.inf)


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
        _phi_run(kind, centred, th, c, pts, n, out, qi, work)
        _unpack(out, n, q[v0:], dq[v0:])


@serial
def _areas_share(t: int, nt: int, q: np.ndarray, area: np.ndarray) -> None:
    """Rows ``t·h/T ..`` of the pixels' corner-quad areas ``area`` ``(h, w)``."""
    h, w = area.shape
    for i in range(t * h // nt, (t + 1) * h // nt):
        for j in range(w):
            area[i, j] = _quad_area(q, i, j, w)


@serial
def _amin_share(t: int, nt: int, area: np.ndarray, amin: np.ndarray) -> None:
    """Rows ``t·h/T ..`` of the edges' smaller adjacent areas ``amin`` ``(E,)``, numbered as
    [`MeshTopology`][] numbers the edges."""
    h, w = area.shape
    nh = (h + 1) * w
    for i in range(t * (h + 1) // nt, (t + 1) * (h + 1) // nt):  # horizontal edges
        for j in range(w):
            amin[i * w + j] = _amin_across(area, i, j)
    for i in range(t * h // nt, (t + 1) * h // nt):  # vertical edges
        for j in range(w + 1):
            amin[nh + i * (w + 1) + j] = _amin_beside(area, i, j)


def _corners(
    kind: int, centred: bool, h: int, w: int, corners: np.ndarray, th: np.ndarray, c: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Deformed corners ``(V0, 2)``, their θ-derivatives ``(V0, 2, P)`` and every edge's smaller
    adjacent pixel area ``(E,)`` from the corner quads (the count stage's area estimate)."""
    nc, p = corners.shape[0], th.shape[0]
    q, dq = np.empty((nc, 2)), np.empty((nc, 2, p))
    nt = threads(nc)
    work = (_phi_work(nt, p), per_thread(nt, (2, CHUNK)), per_thread(nt, (2 + 2 * p, CHUNK)))
    run_shares(_corners_share, nt, kind, centred, corners, th, c, q, dq, *work)
    area, amin = np.empty((h, w)), np.empty((h + 1) * w + h * (w + 1))
    run_shares(_areas_share, nt, q, area)
    run_shares(_amin_share, nt, area, amin)
    return q, dq, amin


@inline
def _edge_segments(
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
def _piece_moves(dbounds: np.ndarray, pc: int, p: int) -> bool:
    """Whether piece ``pc``'s ends move with θ (a learned centre, ``P = 4``, moves the kinks)."""
    moves = False
    if p == 4:
        for r in range(p):
            moves = moves or dbounds[pc, 0, r] != 0 or dbounds[pc, 1, r] != 0
    return moves


@inline
def _add_moving(
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
def _pixel_vertex(x: float, y: float, ws: float, hs: float) -> tuple[float, float]:
    """A vertex in pixel units of a ``ws`` x ``hs`` source, clamped to it."""
    return min(max((x + 1) * (ws / 2), 0.0), ws), min(max((y + 1) * (hs / 2), 0.0), hs)


@serial
def _place_chunk(
    kind: int, centred: bool, ends: np.ndarray, th: np.ndarray, c: np.ndarray, piece_offsets: np.ndarray,
    bounds: np.ndarray, dbounds: np.ndarray, counts: np.ndarray, edge_offsets: np.ndarray, e0: int, e1: int,
    pts: np.ndarray, out: np.ndarray, moving: np.ndarray, qi: np.ndarray, dq: np.ndarray,
    verts: np.ndarray, dverts: np.ndarray,
) -> None:  # fmt: skip
    """The new vertices of edges ``e0 .. e1 − 1`` into ``verts[i]`` ``(2,)`` and ``dverts[i]``
    ``(2, P)``, ``i`` counted from the chunk's first new vertex (segment ``s`` of edge ``e`` ends
    at new vertex ``s − e`` of the mesh unless it is the edge's last): their points first, then
    one loop of [`_phi_run`][]; ``pts``, ``out``, ``moving``, ``qi``, ``dq``: work space."""
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
            if _piece_moves(dbounds, pc, p):
                moving[nm, 0], moving[nm, 1], moving[nm, 2] = pc, e, s
                nm += 1
            for k in range(m):
                if s != first:
                    t = lo + (hi - lo) * (k / m)
                    i = s - e - 1 - base
                    pts[0, i], pts[1, i] = ax + t * dx, ay + t * dy
                s += 1
    n = edge_offsets[e1] - e1 - base
    _phi_run(kind, centred, th, c, pts, n, out, qi, dq)  # the chunk's new vertices in one loop
    _unpack(out, n, verts, dverts)
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
                _phi(kind, centred, ax + t * dx, ay + t * dy, th, c, qi, dq)
                _add_moving(dverts, v, dq, p, dx, dy, dbounds, pc, f)


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
    has), placed by [`_place_chunk`][]; thread ``t`` of ``nt`` takes every ``nt``-th chunk, with
    its rows of ``work`` ([`_place_work`][])."""
    ne = ends.shape[0]
    n_chunks = (ne + CHUNK - 1) // CHUNK
    mesh = (kind, centred, ends, th, c, piece_offsets, bounds, dbounds, counts, edge_offsets)
    qi, dq = own(work[0], t, nt), own(work[1], t, nt)
    pts, out, moving = own(work[2], t, nt), own(work[3], t, nt), own(work[4], t, nt)
    for chunk in range(t, n_chunks, nt):
        e0, e1 = chunk * CHUNK, min((chunk + 1) * CHUNK, ne)
        for e in range(e0, e1):
            _edge_segments(
                e, edge_offsets[e], edge_offsets[e + 1], ea, eb, ncorner, seg_start, seg_end, seg_edge
            )
        v0 = ncorner + edge_offsets[e0] - e0
        _place_chunk(*mesh, e0, e1, pts, out, moving, qi, dq, verts[v0:], dverts[v0:])


@inline
def _still(v: np.ndarray) -> bool:
    """Whether a vertex's θ-velocity ``v`` ``(2, P)`` is zero (φ the identity about it)."""
    for r in range(v.shape[1]):
        if v[0, r] != 0 or v[1, r] != 0:
            return False
    return True


@serial
def _integrate_share(
    t: int, nt: int, kind: int, centred: bool, ends: np.ndarray, ea: np.ndarray, eb: np.ndarray,
    th: np.ndarray, c: np.ndarray, piece_offsets: np.ndarray, bounds: np.ndarray, dbounds: np.ndarray,
    counts: np.ndarray, edge_offsets: np.ndarray, corners: np.ndarray, dcorners: np.ndarray,
    incl: np.ndarray, offsets: np.ndarray, block: int, ws: float, hs: float, span: int, out: np.ndarray,
    jac: np.ndarray, work: tuple, all_verts: np.ndarray, all_dverts: np.ndarray, sums: tuple,
) -> None:  # fmt: skip
    """[`mesh_integrals`][] a chunk of edges at a time: its new vertices into work space
    ([`_place_chunk`][]), in pixel units as [`_to_pixels`][] gives them; its segments'
    integrals (each edge summed in segment order), moments
    ([`segment_moments`][]) and θ-Jacobian while the segment is at hand.
    ``corners`` ``(V0, 2)`` in pixel units, ``span``: the most new vertices a chunk has; into
    ``out`` ``(N + 1, E)`` and ``jac`` ``(N + 1, E, P)``, every edge's written once, from work
    space (no zeroing). Thread ``t`` of ``nt`` takes every ``nt``-th chunk, with its rows of the
    work space: ``work`` ([`_place_work`][]), the chunk's new vertices ``(T, span, 2)`` and their
    θ-derivatives ``(T, span, 2, P)``, and ``sums`` ([`_integral_work`][]: a segment's integrals
    and moments, an edge's θ-Jacobian and integrals)."""
    ne, p, n = ends.shape[0], th.shape[0], incl.shape[2]
    n_chunks = (ne + CHUNK - 1) // CHUNK
    sx, sy = ws / 2, hs / 2  # ∂X/∂x, ∂Y/∂y
    mesh = (kind, centred, ends, th, c, piece_offsets, bounds, dbounds, counts, edge_offsets)
    qi, dq = own(work[0], t, nt), own(work[1], t, nt)
    pts, rows, moving = own(work[2], t, nt), own(work[3], t, nt), own(work[4], t, nt)
    verts, dverts = own(all_verts, t, nt), own(all_dverts, t, nt)
    acc, ma = own(sums[0], t, nt), own(sums[1], t, nt)
    mb, ej, oe = own(sums[2], t, nt), own(sums[3], t, nt), own(sums[4], t, nt)
    for chunk in range(t, n_chunks, nt):
        e0, e1 = chunk * CHUNK, min((chunk + 1) * CHUNK, ne)
        _place_chunk(*mesh, e0, e1, pts, rows, moving, qi, dq, verts, dverts)
        base = edge_offsets[e0] - e0
        for i in range(edge_offsets[e1] - e1 - base):
            verts[i, 0], verts[i, 1] = _pixel_vertex(verts[i, 0], verts[i, 1], ws, hs)
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


@dataclass
class _Counted:
    """The count stage's results (see [`_count_stage`][])."""

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


def _count_stage(
    spec: MeshSpec, size: tuple[int, int], theta: np.ndarray, tol: float, max_subdiv: int, with_grad: bool
) -> _Counted:
    """Corners, every edge's smooth pieces and their segment counts: what the vertices' placement
    needs ([`build_mesh`][], [`mesh_integrals`][])."""
    h, w = size
    ends, _, _, uniform = _topology(size)
    th = np.ascontiguousarray(theta, dtype=np.float64)
    c = np.array(spec.center, dtype=np.float64)
    args = (spec.kind, spec.centred)
    cq, cdq, amin = _corners(*args, h, w, uniform, th, c)
    ne = len(ends)
    nt = threads(ne * _EDGE_WORK)
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
    limits = (float(tol), int(max_subdiv), with_grad, INNER, span)
    out = (bounds, dbounds, counts, edge_offsets)
    ns, p = 7, len(th)  # samples a piece, at most
    points = (per_thread(nt, (2, ns * span)), per_thread(nt, (2 + 2 * p, ns * span)))
    space = (*points, per_thread(nt, (span,)), per_thread(nt, (span,)))
    work = (work, _phi_work(nt, p), *space)
    run_shares(_pieces_share, nt, *args, ends, th, c, piece_offsets, amin, *limits, *out, *work, True)
    edge_offsets[0] = 0
    np.cumsum(edge_offsets, out=edge_offsets)
    vspan = int(np.diff(edge_offsets[chunk_ends] - chunk_ends).max())  # the most new vertices a chunk has
    return _Counted(th, c, cq, cdq, piece_offsets, bounds, dbounds, counts, edge_offsets, vspan)


def build_mesh(
    spec: MeshSpec,
    size: tuple[int, int],
    theta: np.ndarray,
    tol: float,
    *,
    max_subdiv: int = 4096,
    with_grad: bool = True,
) -> CompiledMesh:
    """The mesh [`pixel_mesh`][layoutwarp.mesh.pixel_mesh] builds for the layout of ``spec`` at ``theta``
    (``(P,)`` float64) with tolerance ``tol``, compiled, with every vertex's θ-derivative.

    ``with_grad`` bounds the polylines' error in ``∂φ/∂θ`` too (as ``pixel_mesh`` does when θ
    requires grad), so that θ-gradients are as accurate as values.
    """
    h, w = size
    ends, ea, eb, _ = _topology(size)
    k = _count_stage(spec, size, theta, tol, max_subdiv, with_grad)
    ne, nseg, ncorner = len(ends), int(k.edge_offsets[-1]), (h + 1) * (w + 1)
    verts, dverts = np.empty((ncorner + nseg - ne, 2)), np.empty((ncorner + nseg - ne, 2, len(k.th)))
    verts[:ncorner], dverts[:ncorner] = k.corners, k.dcorners
    seg_start, seg_end, seg_edge = (np.empty(nseg, dtype=np.int64) for _ in range(3))
    nt = threads(ne * _EDGE_WORK)
    run_shares(
        _place_share, nt, spec.kind, spec.centred, ends, ea, eb, k.th, k.c, k.piece_offsets, k.bounds,
        k.dbounds, k.counts, k.edge_offsets, ncorner, k.span, verts, dverts, seg_start, seg_end, seg_edge,
        _place_work(nt, len(k.th), k.span),
    )  # fmt: skip
    return CompiledMesh((h, w), verts, dverts, seg_start, seg_end, seg_edge, k.edge_offsets, k.counts)


def mesh_integrals(
    spec: MeshSpec,
    size: tuple[int, int],
    theta: np.ndarray,
    tol: float,
    tables: tuple[np.ndarray, np.ndarray],
    src_size: tuple[int, int],
    *,
    max_subdiv: int = 4096,
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
    ends, ea, eb, _ = _topology(size)
    k = _count_stage(spec, size, theta, tol, max_subdiv, True)
    corners = _to_pixels(k.corners, float(ws), float(hs))
    ne, n, p = len(ends), tables[0].shape[2], len(k.th)
    out, jac = np.empty((n + 1, ne)), np.empty((n + 1, ne, p))
    nt = threads(ne * _EDGE_WORK)
    space = (per_thread(nt, (k.span, 2)), per_thread(nt, (k.span, 2, p)), _integral_work(nt, n, p))
    run_shares(
        _integrate_share, nt, spec.kind, spec.centred, ends, ea, eb, k.th, k.c, k.piece_offsets, k.bounds,
        k.dbounds, k.counts, k.edge_offsets, corners, k.dcorners, *tables, BLOCK, float(ws), float(hs),
        k.span, out, jac, _place_work(nt, p, k.span), *space,
    )  # fmt: skip
    return out, jac


def _phi_work(nt: int, p: int) -> tuple[np.ndarray, np.ndarray]:
    """Each of ``nt`` threads' work space for [`_phi`][]: a point ``(2,)`` and its derivatives
    ``(2, P + 2)``."""
    return per_thread(nt, (2,)), per_thread(nt, (2, p + 2))


def _edge_work(nt: int, p: int) -> tuple[np.ndarray, ...]:
    """Each of ``nt`` threads' work space for [`_edge_pieces`][]: ``scratch`` ``(8, P)``, ``cuts``
    ``(8,)``, ``dcuts`` ``(8, P)``, ``lo`` ``(10,)``, ``dlo`` ``(10, P)``."""
    cuts, los = per_thread(nt, (8,)), per_thread(nt, (10,))
    return per_thread(nt, (8, p)), cuts, per_thread(nt, (8, p)), los, per_thread(nt, (10, p))


def _place_work(nt: int, p: int, span: int) -> tuple[np.ndarray, ...]:
    """Each of ``nt`` threads' work space for [`_place_chunk`][] of a chunk of at most ``span`` new
    vertices: [`_phi_work`][]'s, their points ``(2, span)`` and map ``(2 + 2P, span)``, and the
    chunk's moving pieces ``(10·CHUNK, 3)`` (9 pieces an edge at most)."""
    pts, out = per_thread(nt, (2, span)), per_thread(nt, (2 + 2 * p, span))
    return (*_phi_work(nt, p), pts, out, per_thread(nt, (10 * CHUNK, 3), np.int64))


def _integral_work(nt: int, n: int, p: int) -> tuple[np.ndarray, ...]:
    """Each of ``nt`` threads' work space for the integrals of ``n`` channels: a segment's
    integrals ``(1, N + 1)`` and moments ``(1, N)`` twice, an edge's θ-Jacobian ``(N + 1, P)`` and
    integrals ``(N + 1,)``."""
    segment = per_thread(nt, (1, n + 1)), per_thread(nt, (1, n)), per_thread(nt, (1, n))
    return (*segment, per_thread(nt, (n + 1, p)), per_thread(nt, (n + 1,)))


#: What an edge costs the mesh's kernels, in elements of [`threads`][layoutwarp.kernels.base.threads]' work.
_EDGE_WORK = 64


@serial
def _to_pixels_share(t: int, nt: int, verts: np.ndarray, ws: float, hs: float, out: np.ndarray) -> None:
    nv = verts.shape[0]
    for v in range(t * nv // nt, (t + 1) * nv // nt):
        out[v, 0], out[v, 1] = _pixel_vertex(verts[v, 0], verts[v, 1], ws, hs)


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


# ----------------------------------------------------------------------------------------
# The mesh on a CUDA device: the same steps, one GPU thread per corner, pixel, edge or vertex
# ----------------------------------------------------------------------------------------
cuda = None  # numba.cuda, bound by the first launch (kernels.cuda_launch)
#: The most θ entries a compiled map has (local arrays on the device have a fixed size).
P_MAX = 4
_DQ, _ROWS = P_MAX + 2, 2 + 2 * P_MAX  # local arrays' sizes must be constants of the module
F8 = np.float64


@inline
def _phi_at(
    kind: int, centred: bool, x: float, y: float, th: np.ndarray, c: np.ndarray, q: np.ndarray, dq: np.ndarray
) -> None:
    """[`_phi`][] at ``(x, y)``, with ``dq`` ``(2, P_MAX + 2)`` work space whose first ``P``
    columns take ``∂φ/∂θ`` and the next two the Jacobian (the device's local arrays have one
    size for every ``P``)."""
    _phi(kind, centred, x, y, th, c, q, dq[:, : th.shape[0] + 2])


@inline
def _edge_pieces_and_counts(
    kind: int, centred: bool, e: int, ends: np.ndarray, th: np.ndarray, c: np.ndarray,
    piece_offsets: np.ndarray, amin: np.ndarray, tol: float, max_subdiv: int, inner: float,
    scratch: np.ndarray, cuts: np.ndarray, dcuts: np.ndarray, lo: np.ndarray, dlo: np.ndarray,
    q: np.ndarray, dq: np.ndarray, rows: np.ndarray, one: np.ndarray, one_len: np.ndarray,
    sag: np.ndarray, length: np.ndarray,
    bounds: np.ndarray, dbounds: np.ndarray, counts: np.ndarray, edge_counts: np.ndarray,
) -> None:  # fmt: skip
    """Edge ``e``'s part of [`_pieces_share`][] (always ``with_grad``): its pieces'
    bounds and segment counts, and its segments into ``edge_counts[e + 1]``; ``rows``
    ``(2 + 2 P_MAX, 7)`` (a piece's seven samples), ``one``, ``one_len`` (1,), ``sag``,
    ``length`` (10,): work space."""
    p = th.shape[0]
    base = piece_offsets[e]
    n = _edge_bounds(
        kind, centred, e, ends, th, c, piece_offsets, scratch, cuts, dcuts, lo, dlo, bounds, dbounds
    )
    ax, ay = ends[e, 0], ends[e, 1]
    dx, dy = ends[e, 2] - ax, ends[e, 3] - ay
    for i in range(n):
        for s in range(7):
            x, y = _sample_point(ax, ay, dx, dy, lo[i], lo[i + 1], s, inner)
            _phi_at(kind, centred, x, y, th, c, q, dq)
            rows[0, s], rows[1, s] = q[0], q[1]
            for r in range(p):
                rows[2 + r, s], rows[2 + p + r, s] = dq[0, r], dq[1, r]
        _sagittas(rows, 1, 7, True, p, one, one_len)  # piece by piece: little work space a thread
        sag[i], length[i] = one[0], one_len[0]
    edge_counts[e + 1] = _segment_counts(sag, length, 0, n, base, amin[e], tol, max_subdiv, counts)


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
        moves = _piece_moves(dbounds, pc, p)
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
                    _add_moving(dverts, v, dq, p, dx, dy, dbounds, pc, f)
            s += 1
    _edge_segments(e, first, s, ea, eb, ncorner, seg_start, seg_end, seg_edge)
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
    ([`_edge_pieces`][]) into ``npieces[i + 1]``, thread 0 setting ``npieces[0] = 0``, so that
    a cumulative sum of ``npieces`` in place gives the pieces' offsets (a mesh has at least as
    many edges as corners), and sums block ``i`` (row × block × channel) of the source
    ``image`` ``(N, H, W)`` into the prefix table ``incl``
    ([`prefix_block_item`][layoutwarp.kernels.exact.prefix_block_item])."""
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
        npieces[i + 1] = _edge_pieces(kind, centred, i, ends, th, c, scratch, cuts, dcuts, lo, dlo, False)


def _cuda_amin(
    q: np.ndarray, h: int, w: int, amin: np.ndarray, block: int, incl: np.ndarray, offsets: np.ndarray
) -> None:
    """Two independent steps in one launch: thread ``e`` takes the smaller of edge ``e``'s two
    pixels' areas (horizontal edges, then vertical; [`_amin_across`][], [`_amin_beside`][]),
    each [`_quad_area`][] of the deformed corners ``q`` (the areas and the minima at once), and
    the block offsets of row × channel ``e`` of the prefix table ``incl``
    ([`prefix_offsets_item`][layoutwarp.kernels.exact.prefix_offsets_item])."""
    e = cuda.grid(1)
    prefix_offsets_item(e, block, incl, offsets)
    nh = (h + 1) * w
    if e < nh:
        i, j = e // w, e % w
        up = _quad_area(q, i - 1, j, w) if i > 0 else np.inf
        amin[e] = min(up, _quad_area(q, i, j, w) if i < h else np.inf)
    elif e < amin.shape[0]:
        i, j = (e - nh) // (w + 1), (e - nh) % (w + 1)
        left = _quad_area(q, i, j - 1, w) if j > 0 else np.inf
        amin[e] = min(left, _quad_area(q, i, j, w) if j < w else np.inf)


#: The slots of a [`MeshRoom`][]'s status, in page-locked host memory its kernels write directly:
#: the pieces and the segments the newest mesh needed, and the stamp of the last mesh that
#: outgrew its room (0: none since the host looked).
PIECES, SEGMENTS, OVERFLOW = range(3)


def _cuda_pieces_and_counts(
    kind: int, centred: bool, ends: np.ndarray, th: np.ndarray, c: np.ndarray,
    piece_offsets: np.ndarray, amin: np.ndarray, tol: float, max_subdiv: int, inner: float,
    bounds: np.ndarray, dbounds: np.ndarray, counts: np.ndarray, edge_counts: np.ndarray,
    status: np.ndarray, stamp: int,
) -> None:  # fmt: skip
    """One thread per edge: [`_edge_pieces_and_counts`][], into room for ``bounds.shape[0]``
    pieces. Where the mesh has more (``piece_offsets[-1]``, read by every thread alike), every
    edge is one straight segment instead (its chord); thread 0 writes the pieces needed to the
    ``status`` and, where they outgrew their room, the mesh's ``stamp``."""
    e = cuda.grid(1)
    ne = ends.shape[0]
    over = piece_offsets[ne] > bounds.shape[0]
    if e == 0:
        edge_counts[0] = 0  # the offsets' leading zero: no zeroed buffer to launch for
        status[PIECES] = piece_offsets[ne]
        if over:
            status[OVERFLOW] = stamp
    if e < ne and over:
        edge_counts[e + 1] = 1
    elif e < ne:
        scratch, cuts = cuda.local.array((8, P_MAX), F8), cuda.local.array(8, F8)
        dcuts = cuda.local.array((8, P_MAX), F8)
        lo, dlo = cuda.local.array(10, F8), cuda.local.array((10, P_MAX), F8)
        q, dq = cuda.local.array(2, F8), cuda.local.array((2, _DQ), F8)
        rows, one, one_len = (
            cuda.local.array((_ROWS, 7), F8),
            cuda.local.array(1, F8),
            cuda.local.array(1, F8),
        )
        sag, length = cuda.local.array(10, F8), cuda.local.array(10, F8)
        _edge_pieces_and_counts(
            kind, centred, e, ends, th, c, piece_offsets, amin, tol, max_subdiv, inner,
            scratch, cuts, dcuts, lo, dlo, q, dq, rows, one, one_len, sag, length, bounds, dbounds, counts,
            edge_counts,
        )  # fmt: skip


def _cuda_place(
    kind: int, centred: bool, ends: np.ndarray, ea: np.ndarray, eb: np.ndarray, th: np.ndarray,
    c: np.ndarray, piece_offsets: np.ndarray, bounds: np.ndarray, dbounds: np.ndarray,
    counts: np.ndarray, edge_offsets: np.ndarray, q: np.ndarray, dq: np.ndarray, ws: float, hs: float,
    verts: np.ndarray, dverts: np.ndarray, seg_start: np.ndarray, seg_end: np.ndarray, seg_edge: np.ndarray,
    pv: np.ndarray, seg_offsets: np.ndarray, status: np.ndarray, stamp: int,
) -> None:  # fmt: skip
    """One thread per edge: [`_edge_vertices`][], then its new vertices in pixel units of a
    ``ws`` x ``hs`` source ([`_pixel_vertex`][]) into ``pv``; thread ``e`` also copies corner
    ``e`` in from ``q``/``dq`` (where the corners' kernel left them; a mesh has at least as many
    edges as corners) with its pixel units. One launch where placing and converting took two.

    The mesh is built in room for ``seg_start.shape[0]`` segments (at least as many as edges):
    where it needs more (``edge_offsets[-1]``), each piece is one segment, its chord; where its
    pieces outgrew their room ([`_cuda_pieces_and_counts`][]) or this one, each edge is.
    Either way the ``status`` gets the mesh's ``stamp``, and ``seg_offsets`` ``(E + 1,)`` holds
    the segments' offsets the mesh has. The room left over holds segments of no length (at vertex 0, which add
    nothing), so a kernel may run over all of it."""
    e = cuda.grid(1)
    nc, ne, room = q.shape[0], ends.shape[0], seg_start.shape[0]
    counted = piece_offsets[ne] <= bounds.shape[0]  # the pieces' kernel counted the segments
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
        pv[e, 0], pv[e, 1] = _pixel_vertex(q[e, 0], q[e, 1], ws, hs)
    if e < ne:
        if pieces_over:  # the edge's chord, from corner to corner
            _edge_segments(e, e, e + 1, ea, eb, nc, seg_start, seg_end, seg_edge)
            seg_offsets[e + 1] = e + 1
        else:
            qi, dqi = cuda.local.array(2, F8), cuda.local.array((2, _DQ), F8)
            first = piece_offsets[e] if over else edge_offsets[e]
            seg_offsets[e + 1] = _edge_vertices(
                kind, centred, e, ends, ea, eb, th, c, piece_offsets, bounds, dbounds, counts, first, over,
                nc, qi, dqi, verts, dverts, seg_start, seg_end, seg_edge,
            )  # fmt: skip
            for v in range(nc + first - e, nc + seg_offsets[e + 1] - e - 1):  # its new vertices
                pv[v, 0], pv[v, 1] = _pixel_vertex(verts[v, 0], verts[v, 1], ws, hs)
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


def _cuda_pixel_means(
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


def _cuda_edge_gradient(
    g: np.ndarray, means: np.ndarray, area: np.ndarray, g_area: np.ndarray, unit: float, g_edge: np.ndarray,
    sums: np.ndarray, done: np.ndarray,
) -> None:  # fmt: skip
    """One thread per pixel edge: the gradient ``(N + 1, E)`` of the edge integrals from the
    means' and the areas' (the adjoint of [`_cuda_pixel_means`][]: the quotient rule and
    [`MeshTopology.combine_adjoint`][layoutwarp.mesh.MeshTopology.combine_adjoint] in one
    pass; ``g`` and ``means`` in the means' dtype, the sums in float64). An edge adds to the
    pixel before it (above, or to its left) and takes from the one after. Thread 0 also zeroes
    ``sums`` and ``done``, which [`_cuda_theta_gradient`][] adds to next."""
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


def _cuda_theta_gradient(
    verts: np.ndarray, seg_start: np.ndarray, seg_end: np.ndarray, seg_edge: np.ndarray, incl: np.ndarray,
    block: int, g_edge: np.ndarray, dverts: np.ndarray, sx: float, sy: float, sums: np.ndarray,
    done: np.ndarray, slope: np.ndarray, g_param: np.ndarray,
) -> None:  # fmt: skip
    """One thread per segment: its Reynolds weights ([`segment_weights`][]) times its normal line
    element ``(ΔY, −ΔX)`` (pixel units, ``verts``) at its two vertices, carried to θ by their
    derivatives ``dverts`` ``(V, 2, P)`` (sensor units, so scaled by ``(sx, sy)``, a pixel unit's
    size in sensor units' reciprocal); the block's sums reduced in shared memory and added to
    ``sums`` ``(P,)`` (float64, zeroed with ``done`` by [`_cuda_edge_gradient`][]), one atomic
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
    "amin": (_cuda_amin, f"void({_A2}, int64, int64, {_A1}, int64, {_F3}, {_A3})"),
    "pieces_and_counts": (
        _cuda_pieces_and_counts,
        f"void(int64, boolean, {_A2}, {_A1}, {_A1}, {_I1}, {_A1}, float64, int64, float64, {_A2}, {_A3}, "
        f"{_I1}, {_I1}, {_I1}, int64)",
    ),
    "place": (
        _cuda_place,
        f"void(int64, boolean, {_A2}, {_I1}, {_I1}, {_A1}, {_A1}, {_I1}, {_A2}, {_A3}, {_I1}, {_I1}, {_A2}, "
        f"{_A3}, float64, float64, {_A2}, {_A3}, {_I1}, {_I1}, {_I1}, {_A2}, {_I1}, {_I1}, int64)",
    ),
    "pixel_means": (
        _cuda_pixel_means,
        f"void({_A2}, {_I1}, float64, {_F3}, {_A2}, {_A2}, {_I1}, int64, int8[::1])",
    ),
    "edge_gradient": (  # the means' gradient as a sum's backward gives it: strided (broadcast)
        _cuda_edge_gradient,
        f"void(float32[:, :, :], {_F3}, {_A2}, {_A2}, float64, {_A2}, {_A1}, {_I1})",
    ),
    "theta_gradient": (
        _cuda_theta_gradient,
        f"void({_A2}, {_I1}, {_I1}, {_I1}, {_F3}, int64, {_A2}, {_A3}, float64, float64, {_A1}, {_I1}, "
        f"{_A1}, float32[::1])",
    ),
}


#: How much more room than it needed a device mesh's kind gets (see [`MeshRoom`][]).
HEADROOM = 1.25


@dataclass
class MeshRoom:
    """The room the device meshes of one learnable layout, sensor size and tolerance are built
    in ([`build_mesh_device`][]): their pieces and segments, sized by the first mesh (the one
    time the host reads how many it needs) with [`HEADROOM`][], and grown when a later mesh came
    within ``1 / HEADROOM`` of them. The kernels write what a mesh needed straight into
    ``status``, page-locked host memory mapped into the device's address space
    ([`host_mapped`][layoutwarp.kernels.device.host_mapped]: no copy launched, nothing waited
    for; a CUDA graph's replays write it too), which the host reads whenever it builds the next
    mesh. So a step allocates without waiting for the device, and a captured step keeps its
    buffers. A mesh that outgrows its room is built with straight chords instead (valid, but
    coarser than the tolerance) and stamps the status: [`device_status`][] reads it at once.
    Its overflows are [`Stamps`][layoutwarp.kernels.device.Stamps]: a captured graph's replays
    all write the stamp of the capture, which [`device_status`][] tells of each time and
    [`look`][layoutwarp.kernels.mesh.MeshRoom.look] the first time."""

    status: np.ndarray  # the slots PIECES, SEGMENTS, OVERFLOW, int64, written by the kernels
    pieces: int = 0
    segments: int = 0
    overflows: Stamps = field(init=False)  # the stamps in slot OVERFLOW

    def __post_init__(self) -> None:
        self.overflows = Stamps(self.status, OVERFLOW)

    def ahead(self, need: int, least: int) -> int:
        """Room for ``need`` items with headroom, at least ``least``."""
        return max(least, math.ceil(need * HEADROOM) + 64)

    def look(self, tell: bool = True) -> dict[str, int | bool]:
        """Take in what the kernels wrote so far, without waiting for them: grow the room a mesh
        came close to and, with ``tell``, warn where one outgrew it. Returns the status' values
        and whether an overflow is news."""
        pieces, segments = int(self.status[PIECES]), int(self.status[SEGMENTS])
        news = self.overflows.news()
        if news and tell:
            need = f"{pieces} pieces" if pieces > self.pieces else f"{segments} segments"
            warnings.warn(
                f"a learnable step's pixel mesh outgrew its room ({need} for {self.pieces} and "
                f"{self.segments} segments): that step integrated straight chords, coarser than its "
                "tolerance; the room has grown (layoutwarp.device_status() tells at once)",
                RuntimeWarning,
                stacklevel=5,
            )
        if pieces > self.pieces:  # the pieces outgrew their room: the segments went uncounted,
            self.segments = 0  # so the next mesh reads its total (once)
        if pieces * HEADROOM > self.pieces:
            self.pieces = self.ahead(pieces, self.pieces)
        if self.segments and segments * HEADROOM > self.segments:
            self.segments = self.ahead(segments, self.segments)
        if self.segments:
            self.segments = max(self.segments, self.pieces)  # room for a chord a piece
        return {"pieces": pieces, "segments": segments, "overflowed": news}


#: Every [`MeshRoom`][], by layout kind and centre, sensor size, tolerance, θ's length and device
#: (the source's size changes no count). Never let go of: a captured CUDA graph writes its
#: room's status for as long as it lives (a few bytes a room).
MESH_ROOMS: dict[tuple, MeshRoom] = {}


@dataclass
class DeviceMesh:
    """A compiled mesh built where its θ lives ([`build_mesh_device`][]), as torch tensors
    there: the [`PixelMesh`][] (its segment arrays as long as its room, the room left over holding
    segments of no length), its vertices in pixel units of the source (clamped to it) and every
    vertex's θ-derivative ``(V, 2, P)`` (the rows past the mesh's vertices are not written),
    every smooth piece's segment count (as [`CompiledMesh`][] has them, in the first
    ``status[PIECES]`` rows; not written where the pieces outgrew their room, and not the mesh's
    where its segments did), the room it was built in and its stamp there, the source
    image's prefix table and block offsets
    ([`prefix_tables`][layoutwarp.kernels.exact.prefix_tables], built in the same launches), and
    θ's derivative in the parameter it was built from (``(P,)``, float64; see
    [`build_mesh_device`][])."""

    mesh: PixelMesh
    pixel_vertices: torch.Tensor
    dverts: torch.Tensor
    counts: torch.Tensor
    room: MeshRoom
    stamp: int
    incl: torch.Tensor
    offsets: torch.Tensor
    slope: torch.Tensor


@functools.lru_cache(maxsize=16)
def _device_centre(center: tuple[float, float], device: str) -> torch.Tensor:
    """A centre as a float64 tensor on ``device`` (cached: no copy to the device every step; do
    not modify)."""
    return torch.tensor(center, dtype=torch.float64, device=device)


@functools.lru_cache(maxsize=16)
def _device_topology(size: tuple[int, int], device: str) -> tuple[torch.Tensor, ...]:
    """[`_topology`][] on ``device`` (cached per size and device; do not modify)."""
    return tuple(torch.from_numpy(np.ascontiguousarray(a)).to(device) for a in _topology(size))


def build_mesh_device(
    spec: MeshSpec,
    size: tuple[int, int],
    theta: torch.Tensor,
    tol: float,
    src_size: tuple[int, int],
    *,
    bounds: torch.Tensor | None = None,
    image: torch.Tensor | None = None,
    max_subdiv: int = 4096,
) -> DeviceMesh:
    """[`build_mesh`][] (``with_grad``) and [`pixel_vertices`][] on the CUDA device that
    holds ``theta`` ``(P,)``: θ itself, or with ``bounds`` (``(P,)``, float64, on that device;
    ``None`` or empty: none) the parameter ρ of ``θ = bounds · tanh(ρ)`` (a learnable layout's,
    in its dtype), which the first kernel makes θ of in float64, so neither takes a launch of its
    own. In four kernels (corners and pieces, edges' smaller areas, counts, vertices with their
    pixel units: one thread per corner and edge, each thread the CPU's steps for its item) and
    two cumulative sums, so no mesh crosses the bus: at 2048x1024 → 257x129 a fovea mesh is about
    50 MB. The first two kernels also build the prefix table of the source ``image``
    ``(N, H, W)`` (contiguous, on the same device; ``None``: none). The buffers are its
    [`MeshRoom`][]'s: the host reads the mesh's totals only for the first mesh of its kind (and
    its segments' after a mesh whose pieces outgrew their room, which counted none), and never
    waits for the device otherwise. A ``theta`` on the CPU runs the same kernels in numba's CUDA simulator
    (``NUMBA_ENABLE_CUDASIM=1``), which is how they are tested without a GPU."""
    dev = theta.device
    stream = stream_of(theta)
    (h, w), (hs, ws) = size, src_size
    ends, ea, eb, uniform = _device_topology(size, str(dev))
    param = theta.detach().contiguous()
    c = _device_centre(spec.center, str(dev))
    p, ne, nc = param.numel(), ends.shape[0], uniform.shape[0]
    f64, i64 = {"dtype": torch.float64, "device": dev}, {"dtype": torch.int64, "device": dev}
    th, slope = torch.empty(p, **f64), torch.empty(p, **f64)
    bounds = th[:0] if bounds is None else bounds
    key = (spec, size, float(tol), p, str(dev), max_subdiv)
    if key not in MESH_ROOMS:
        MESH_ROOMS[key] = MeshRoom(host_mapped(3, dev))
    room = MESH_ROOMS[key]
    room.look()
    stamp = room.overflows.take()

    def launch(name: str, count: int, *args: object) -> None:
        cuda_launch(CUDA_KERNELS[name][0], count, stream, *args)

    q, dq, piece_offsets = torch.empty(nc, 2, **f64), torch.empty(nc, 2, p, **f64), torch.empty(ne + 1, **i64)
    if image is None:
        image = torch.empty(0, hs, ws, **f64)
    n = image.shape[0]
    incl = image.new_empty(hs, ws, n)
    offsets = image.new_empty(hs, -(-ws // BLOCK), n, dtype=torch.float64)
    launch(
        "corners", max(ne, hs * offsets.shape[1] * n), spec.kind, spec.centred, uniform, ends, param,
        bounds, c, th, slope, q, dq, piece_offsets, image, BLOCK, incl,
    )  # fmt: skip
    amin = torch.empty(ne, **f64)
    launch("amin", max(ne, hs * n), q, h, w, amin, BLOCK, incl, offsets)
    piece_offsets.cumsum_(0)
    if not room.pieces:  # the first mesh of its kind: its totals read, once
        room.pieces = room.ahead(int(piece_offsets[-1]), ne)
    lims, dlims = torch.empty(room.pieces, 2, **f64), torch.empty(room.pieces, 2, p, **f64)  # pieces' ends
    counts, edge_counts = torch.empty(room.pieces, **i64), torch.empty(ne + 1, **i64)
    launch(
        "pieces_and_counts", ne, spec.kind, spec.centred, ends, th, c, piece_offsets, amin, float(tol),
        int(max_subdiv), INNER, lims, dlims, counts, edge_counts, room.status, stamp,
    )  # fmt: skip
    edge_offsets = torch.cumsum(edge_counts, 0)
    if not room.segments:  # the first mesh, or one after the pieces outgrew theirs: read, once
        room.segments = room.ahead(int(edge_offsets[-1]), room.pieces)
    nv = nc + room.segments - ne
    verts, dverts = torch.empty(nv, 2, **f64), torch.empty(nv, 2, p, **f64)
    seg_start, seg_end, seg_edge = (torch.empty(room.segments, **i64) for _ in range(3))
    pv, seg_offsets = torch.empty_like(verts), torch.empty(ne + 1, **i64)
    launch(
        "place", ne, spec.kind, spec.centred, ends, ea, eb, th, c, piece_offsets, lims, dlims, counts,
        edge_offsets, q, dq, float(ws), float(hs), verts, dverts, seg_start, seg_end, seg_edge, pv,
        seg_offsets, room.status, stamp,
    )  # fmt: skip
    mesh = PixelMesh(size, verts, seg_start, seg_end, seg_edge, seg_offsets)
    return DeviceMesh(mesh, pv, dverts, counts, room, stamp, incl, offsets, slope)


def device_means(
    dm: DeviceMesh, per_seg: torch.Tensor, unit: float, check: bool, dtype: torch.dtype, zero: torch.Tensor
) -> tuple[torch.Tensor, ...]:
    """The pixels' means ``(N, h, w)`` (in ``dtype``, rounded once), areas ``(h, w)`` and areas
    in sensor units (float64) of the device mesh ``dm`` from its segments' integrals ``per_seg``
    ``(S, N + 1)`` (the exact forward's,
    [`exact_forward`][layoutwarp.kernels.exact.exact_forward]'s per-segment values), in one
    launch (``unit``: a source pixel's area in sensor units; ``check``: a NaN or ±inf mean
    raises when the host next looks, [`DeviceChecks`][layoutwarp.kernels.device.DeviceChecks];
    an earlier call's raises now), which also zeroes the one-element ``zero``."""
    (h, w), n = dm.mesh.size, per_seg.shape[1] - 1
    means, area, area_units = (
        per_seg.new_empty(n, h, w, dtype=dtype),
        per_seg.new_empty(h, w),
        per_seg.new_empty(h, w),
    )
    checks = device_checks(per_seg.device)
    if check:
        checks.look()
    args = (per_seg, dm.mesh.edge_offsets, float(unit), means, area, area_units, checks.status)
    cuda_launch(_cuda_pixel_means, h * w, stream_of(per_seg), *args, checks.take() if check else 0, zero)
    return means, area, area_units


def device_status() -> dict[str, object]:
    """What the GPU reported since the last call, read now: every device is synchronised first
    (so call it where the loop waits anyway, e.g. beside ``loss.item()``; a captured CUDA graph's
    replays report too). Returns ``{"overflowed": bool, "nonfinite": bool, "meshes": [...]}``,
    a dict per kind of learnable mesh with the pieces and segments the newest needed and its
    room. ``overflowed``: some mesh outgrew its room and integrated straight chords, coarser than
    its tolerance: run that step again outside the graph (the room has grown; a graph captured
    before keeps its buffers, so capture it again). ``nonfinite``: a checked call's input held
    NaN or Inf. Nothing is raised or warned."""
    if torch.cuda.is_available() and torch.cuda.is_initialized():
        for index in range(torch.cuda.device_count()):
            torch.cuda.synchronize(index)
    meshes = []
    for room in list(MESH_ROOMS.values()):
        before = (room.pieces, room.segments)
        values = room.look(tell=False)  # the room grown by what it reports
        meshes.append({**values, "overflowed": room.overflows.clear(), "room": before})
    nonfinite = [checks.clear() for checks in CHECKS.values()]
    return {"overflowed": any(m["overflowed"] for m in meshes), "nonfinite": any(nonfinite), "meshes": meshes}


def device_theta_gradient(
    dm: DeviceMesh,
    means: torch.Tensor,
    area: torch.Tensor,
    grad: torch.Tensor,
    grad_area: torch.Tensor | None,
    unit: float,
    src_size: tuple[int, int],
    dtype: torch.dtype,
) -> torch.Tensor:
    """The gradient ``(P,)`` of the parameter ``dm`` was built from (θ, or ρ; see
    [`build_mesh_device`][]), in ``dtype``, from the gradients of [`device_means`][]' means
    ``grad`` (the means' dtype) and areas in sensor units ``grad_area`` (``None``: none), over
    the image whose prefix table ``dm`` holds: two launches (the edge integrals' gradient, then
    every segment's Reynolds weights carried to θ, summed in float64 and carried to the
    parameter)."""
    stream, mesh = stream_of(means), dm.mesh
    g_area = area.new_empty(0, 0) if grad_area is None else grad_area.detach().double().contiguous()
    g_edge = area.new_empty(means.shape[0] + 1, mesh.edge_offsets.numel() - 1)
    sums, done = area.new_empty(dm.dverts.shape[2]), mesh.edge_offsets.new_empty(1)
    args = (grad.detach(), means, area, g_area, float(unit), g_edge, sums, done)  # grad as it is: no copy
    cuda_launch(_cuda_edge_gradient, g_edge.shape[1], stream, *args)
    hs, ws = src_size
    g_param = area.new_empty(sums.shape[0], dtype=dtype)
    args = (dm.pixel_vertices, mesh.seg_start, mesh.seg_end, mesh.seg_edge, dm.incl, BLOCK, g_edge, dm.dverts)
    cuda_launch(
        _cuda_theta_gradient, mesh.num_segments, stream, *args, ws / 2, hs / 2, sums, done, dm.slope, g_param
    )
    return g_param
