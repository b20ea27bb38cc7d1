"""The compiled maps one point at a time (arithmetic as in [`layoutwarp.layouts`][]), without a
branch on the point, so that a loop of them runs in SIMD lanes; and the kinks of every uniform
edge, with their θ-derivatives (as [`smooth_pieces`][layoutwarp.mesh.smooth_pieces] and
``CurvLayout.edge_breakpoints`` find them)."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from ..base import inline, inline_ir, serial

if TYPE_CHECKING:
    pass


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
def phi_point(
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
            if th[0] == 0 and th[1] == 0:  # the uniform layout: p exactly, as the torch map gives it
                q[0], q[1] = x, y
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
    """[`_curv`][]'s point ``f`` into column ``i`` of [`phi_run`][]'s rows (θ of ``p``)."""
    out[0, i], out[1, i] = f[0], f[1]
    for r in range(p):
        out[2 + r, i], out[2 + p + r, i] = f[2 + r], f[6 + r]


@serial
def phi_run(
    kind: int, centred: bool, th: np.ndarray, c: np.ndarray, pts: np.ndarray, n: int, out: np.ndarray,
    qi: np.ndarray, work: np.ndarray,
) -> None:  # fmt: skip
    """φ and ``∂φ/∂θ`` at the points ``(pts[0, i], pts[1, i])``, ``i < n``, into ``out[:, i]``:
    ``(φ_x, φ_y, ∂φ_x/∂θ (P), ∂φ_y/∂θ (P))``, as [`phi_point`][] gives them. Rows, not points, are
    contiguous, and CURV runs one loop per case without a branch on θ inside it: the loop runs in
    SIMD lanes. ``qi`` ``(2,)``, ``work`` ``(2, P + 2)``: work space (ELLIPTIC's points)."""
    p = th.shape[0]
    if kind == 1:
        for i in range(n):
            phi_point(kind, centred, pts[0, i], pts[1, i], th, c, qi, work)
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
def unpack_point(out: np.ndarray, n: int, q: np.ndarray, dq: np.ndarray) -> None:
    """[`phi_run`][]'s rows into points: ``q[i]`` (2,) and ``dq[i]`` (2, P) for ``i < n``."""
    p = dq.shape[2]
    for i in range(n):
        q[i, 0], q[i, 1] = out[0, i], out[1, i]
        for r in range(p):
            dq[i, 0, r], dq[i, 1, r] = out[2 + r, i], out[2 + p + r, i]


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
def edge_pieces(
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
