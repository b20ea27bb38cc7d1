"""Compiled CPU kernels of the exact integrator (numba; no compiler needed on the user's machine).

Each kernel fuses what the torch reference in :mod:`layoutwarp.integrators` does in some
forty vectorised passes: cutting every pixel-boundary segment into single-cell pieces, the
prefix-table look-ups of Green's theorem and the accumulation, one segment per loop
iteration (``prange``, so segments run in parallel and no two iterations write the same
output). The arithmetic mirrors the reference step for step, so both agree to rounding.

Compiled code is cached on disk (``cache=True``): a second process loads it instead of
compiling again. :func:`available` says whether numba is installed; without it the torch
reference runs.
"""

from __future__ import annotations

import math

import numpy as np

try:  # numba is a dependency, but the torch reference keeps working without it
    from numba import njit, prange
except ImportError:  # pragma: no cover - depends on the environment
    njit = prange = None

__all__ = ["BLOCK", "available", "exact_backward", "exact_forward", "prefix_tables"]

#: Columns per block of the prefix tables (see :func:`prefix_tables`).
BLOCK = 16


def available() -> bool:
    """Whether the compiled kernels can run (numba is importable)."""
    return njit is not None


def _jit(fn):
    return njit(parallel=True, cache=True, nogil=True)(fn) if njit is not None else fn


@_jit
def prefix_tables(image: np.ndarray, block: int) -> tuple[np.ndarray, np.ndarray]:
    """Row prefix sums of ``image (N, H, W)``, safe in float32.

    Returns ``(incl, offsets)``: ``incl[n, r, c]`` is the inclusive prefix sum within the
    ``block``-column block of ``c`` (the image's dtype), ``offsets[n, r, k]`` the float64
    sum of the whole blocks before block ``k``. ``P_r(c) = offsets[r, c // block] +
    (incl[r, c] − L[r, c])`` never carries more than one block's rounding.
    """
    n, h, w = image.shape
    nb = (w + block - 1) // block
    incl = np.empty_like(image)
    offsets = np.empty((n, h, nb), dtype=np.float64)
    for nr in prange(n * h):
        k, r = nr // h, nr % h
        total = 0.0
        for b in range(nb):
            offsets[k, r, b] = total
            acc = image[k, r, b * block] * 0  # zero in the image's dtype
            for c in range(b * block, min(w, (b + 1) * block)):
                acc += image[k, r, c]
                incl[k, r, c] = acc
            total += acc
    return incl, offsets


@_jit
def exact_forward(
    ax: np.ndarray,
    ay: np.ndarray,
    bx: np.ndarray,
    by: np.ndarray,
    image: np.ndarray,
    incl: np.ndarray,
    offsets: np.ndarray,
    block: int,
) -> np.ndarray:
    """``∫ P dY`` along every segment ``(ax, ay) → (bx, by)`` (source pixel units, inside the
    image), for every channel: ``(N, S)`` float64.

    A segment is cut at source rows, then each row piece at columns; a piece in cell
    ``(r, c)`` with mid-``X`` fraction ``f`` adds ``ΔY · (P_r(c) + f · L[r, c])`` (exact for a
    box image, see :class:`~layoutwarp.integrators.GreenPieces`).
    """
    n, h, w = image.shape
    s_count = ax.shape[0]
    out = np.zeros((n, s_count), dtype=np.float64)
    for s in prange(s_count):
        x0, y0, dxv, dyv = ax[s], ay[s], bx[s] - ax[s], by[s] - ay[s]
        if dyv == 0.0:
            continue  # ΔY = 0 adds nothing
        inv_dy = 1.0 / dyv
        ylo, yhi = min(ay[s], by[s]), max(ay[s], by[s])
        r0 = min(max(math.floor(ylo), 0), h - 1)
        r1 = max(min(max(math.ceil(yhi) - 1, 0), h - 1), r0)
        for row in range(r0, r1 + 1):
            ta = min(max((max(ylo, row) - y0) * inv_dy, 0.0), 1.0)
            tb = min(max((min(yhi, row + 1.0) - y0) * inv_dy, 0.0), 1.0)
            t_lo, t_hi = min(ta, tb), max(ta, tb)
            xa, xb = x0 + t_lo * dxv, x0 + t_hi * dxv
            xlo, xhi = min(xa, xb), max(xa, xb)
            c0 = min(max(math.floor(xlo), 0), w - 1)
            c1 = max(min(max(math.ceil(xhi) - 1, 0), w - 1), c0)
            if dxv == 0.0:
                c1 = c0
            one_column = c1 == c0
            inv_dx = 1.0 / dxv if not one_column else 1.0
            for col in range(c0, c1 + 1):
                if one_column:  # keep the row piece's range (X → t is ill-conditioned)
                    t0, t1 = t_lo, t_hi
                else:
                    u0 = min(max((max(xlo, col) - x0) * inv_dx, 0.0), 1.0)
                    u1 = min(max((min(xhi, col + 1.0) - x0) * inv_dx, 0.0), 1.0)
                    t0, t1 = max(min(u0, u1), t_lo), min(max(u0, u1), t_hi)
                dy = (t1 - t0) * dyv
                frac = min(max(x0 + (t0 + t1) / 2 * dxv - col, 0.0), 1.0)
                blk = col // block
                for k in range(n):
                    lv = image[k, row, col]
                    start = np.float64(incl[k, row, col] - lv)  # in the table's dtype, as the reference
                    out[k, s] += dy * (offsets[k, row, blk] + start + frac * np.float64(lv))
    return out


@_jit
def exact_backward(
    ax: np.ndarray, ay: np.ndarray, bx: np.ndarray, by: np.ndarray, image: np.ndarray, grad: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Reynolds weights of every segment's end points for the vertex gradient.

    For segment ``s`` with ``r(t) = a + t (b − a)``: ``wa = Σ_n grad[n, s] ∫ (1 − t) L dt`` and
    ``wb = Σ_n grad[n, s] ∫ t L dt`` over its pieces; ``L`` on a cell boundary line is the mean
    of the two cells (the symmetric derivative). The caller multiplies by the segment's
    normal ``(ΔY, −ΔX)`` and adds to the vertices.
    """
    n, h, w = image.shape
    s_count = ax.shape[0]
    wa = np.zeros(s_count, dtype=np.float64)
    wb = np.zeros(s_count, dtype=np.float64)
    for s in prange(s_count):
        x0, y0, dxv, dyv = ax[s], ay[s], bx[s] - ax[s], by[s] - ay[s]
        flat = dyv == 0.0
        vertical = dxv == 0.0
        inv_dy = 1.0 / dyv if not flat else 1.0
        ylo, yhi = min(ay[s], by[s]), max(ay[s], by[s])
        r0 = min(max(math.floor(ylo), 0), h - 1)
        r1 = max(min(max(math.ceil(yhi) - 1, 0), h - 1), r0)
        if flat:
            r1 = r0
        for row in range(r0, r1 + 1):
            if flat:
                t_lo, t_hi = 0.0, 1.0
            else:
                ta = min(max((max(ylo, row) - y0) * inv_dy, 0.0), 1.0)
                tb = min(max((min(yhi, row + 1.0) - y0) * inv_dy, 0.0), 1.0)
                t_lo, t_hi = min(ta, tb), max(ta, tb)
            row2 = row - 1 if (flat and y0 == row and row > 0) else row  # on a row boundary
            xa, xb = x0 + t_lo * dxv, x0 + t_hi * dxv
            xlo, xhi = min(xa, xb), max(xa, xb)
            c0 = min(max(math.floor(xlo), 0), w - 1)
            c1 = max(min(max(math.ceil(xhi) - 1, 0), w - 1), c0)
            if vertical:
                c1 = c0
            one_column = c1 == c0
            inv_dx = 1.0 / dxv if not one_column else 1.0
            for col in range(c0, c1 + 1):
                if one_column:
                    t0, t1 = t_lo, t_hi
                else:
                    u0 = min(max((max(xlo, col) - x0) * inv_dx, 0.0), 1.0)
                    u1 = min(max((min(xhi, col + 1.0) - x0) * inv_dx, 0.0), 1.0)
                    t0, t1 = max(min(u0, u1), t_lo), min(max(u0, u1), t_hi)
                col2 = col - 1 if (vertical and x0 == col and col > 0) else col  # on a column boundary
                gl = 0.0
                for k in range(n):
                    gl += grad[k, s] * (
                        0.5 * (np.float64(image[k, row, col]) + np.float64(image[k, row2, col2]))
                    )
                m1 = (t1 * t1 - t0 * t0) / 2
                wa[s] += gl * ((t1 - t0) - m1)
                wb[s] += gl * m1
    return wa, wb
