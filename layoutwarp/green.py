"""The exact integrator on a polygon mesh (paper eq. 7 by Green's theorem), below the operators:
the torch reference (differentiable in θ and the image), and the glue to the compiled CPU and
CUDA kernels of [`layoutwarp.kernels`][].

``∬_A L dA = ∮_∂A P dY`` with ``P`` the row prefix integral of the box image: each boundary
segment is cut at source rows and columns ([`green_pieces`][]), and within one cell ``P`` is
linear in ``X``, so a piece contributes ``ΔY · P(mid-X)`` exactly; each shared edge is
integrated once ([`exact_on_mesh`][]). Tables are float64.
"""

from __future__ import annotations

import itertools
from collections.abc import Iterator
from typing import NamedTuple

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from . import kernels
from .kernels.device import runs_on_device, stream_of
from .mesh import PixelMesh

__all__ = [
    "GreenPieces",
    "cuda_per_segment",
    "exact_on_mesh",
    "expand_runs",
    "green_pieces",
    "segment_cells",
]


def expand_runs(lo: Tensor, count: Tensor) -> tuple[Tensor, Tensor]:
    """Expand runs: for ``count[i]`` consecutive integers from ``lo[i]``, the pair
    ``(parent index i, integer)`` of every element, in order.

    Examples:
        >>> expand_runs(torch.tensor([5, 0]), torch.tensor([2, 3]))
        (tensor([0, 0, 1, 1, 1]), tensor([5, 6, 0, 1, 2]))
    """
    parent = torch.repeat_interleave(torch.arange(count.numel(), device=count.device), count)
    first = torch.cumsum(count, 0) - count
    return parent, lo[parent] + (torch.arange(parent.numel(), device=count.device) - first[parent])


class _PrefixTables:
    """Row prefix sums of a piecewise-constant image ``(N, H, W)``, safe in float32.

    ``P_r(X) = ∫_0^X L(s, r) ds`` is split into a float64 block offset (the sum of whole
    ``B``-column blocks before ``X``) and a block-local inclusive prefix ``I`` in the image's
    dtype, so a value never carries more than ``B`` cells' worth of rounding however wide the
    row is. Inside cell ``c``, ``P`` interpolates ``I(c − 1)`` and ``I(c)`` linearly: exact for
    the box image ``I(c) − I(c − 1)`` (``L`` up to the rounding of one block), and two
    look-ups of the same cell use bit-identical numbers, so the left and right boundaries of
    a pixel narrower than a source cell cancel exactly. The compiled kernels use the same
    formula ([`layoutwarp.kernels.exact_forward`][]).
    """

    def __init__(self, image: Tensor, block: int = kernels.BLOCK):
        n, h, w = image.shape
        nb = -(-w // block)
        padded = image if nb * block == w else F.pad(image, (0, nb * block - w))
        incl = padded.reshape(n, h, nb, block).cumsum(-1)  # block-local inclusive prefix
        offs = incl[..., -1].double().cumsum(-1) - incl[..., -1].double()  # exclusive, float64
        self.block, self.nb, self.width, self.rows = block, nb, nb * block, h
        self.incl = incl.reshape(n, h * nb * block)  # sizes named: an empty batch has them too
        self.offsets = offs.reshape(n, h * nb)

    def _ends(self, row: Tensor, col: Tensor) -> tuple[Tensor, Tensor]:
        """``I(c − 1)`` (0 at a block start) and ``I(c)`` in float64, ``(N, pieces)`` each."""
        idx = row * self.width + col
        cur = self.incl[:, idx].double()
        prev = torch.where(col % self.block == 0, 0.0, self.incl[:, idx - 1].double())
        return prev, cur

    def prefix(self, row: Tensor, col: Tensor, frac: Tensor) -> Tensor:
        """``P_row(col + frac)`` for ``frac`` in ``[0, 1]``: ``(N, pieces)`` in float64."""
        prev, cur = self._ends(row, col)
        offset = self.offsets[:, row * self.nb + col // self.block]
        return offset + prev + frac.to(torch.float64) * (cur - prev)

    def cell(self, row: Tensor, col: Tensor) -> Tensor:
        """The box image ``I(c) − I(c − 1)`` at the cells, ``(N, pieces)`` in float64."""
        prev, cur = self._ends(row, col)
        return cur - prev


def segment_cells(
    a: Tensor, b: Tensor, rows: int, cols: int
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Cut segments ``a → b`` (source pixel units, ``(S, 2)``) into single-cell pieces.

    Segments are cut at integer ``Y`` (rows), then each row piece at integer ``X``
    (columns); both cuts come out in order, so nothing is sorted.

    Returns:
        ``(seg, t0, t1, row, col, idx2)``: parent segment, the piece's parameter range on it,
        its cell, and a second flat cell index ``r · cols + c`` that differs from the cell's
        own only where the piece lies exactly on a cell boundary line (then the mean of the
        two cells is the radiance along it: the symmetric, central-difference derivative).
    """
    ya, yb = a[:, 1], b[:, 1]
    flat = ya == yb
    ylo, yhi = torch.minimum(ya, yb), torch.maximum(ya, yb)
    r0 = ylo.floor().clamp(0, rows - 1).long()
    r1 = torch.maximum((yhi.ceil().long() - 1).clamp(0, rows - 1), r0)
    r1 = torch.where(flat, r0, r1)
    piece, row = expand_runs(r0, r1 - r0 + 1)
    pa, pb, fl = a[piece], b[piece], flat[piece]
    rowf = row.to(a.dtype)
    dyv = pb[:, 1] - pa[:, 1]
    inv_dy = 1 / torch.where(fl, torch.ones_like(dyv), dyv)
    ta = ((torch.maximum(ylo[piece], rowf) - pa[:, 1]) * inv_dy).clamp(0, 1)
    tb = ((torch.minimum(yhi[piece], rowf + 1) - pa[:, 1]) * inv_dy).clamp(0, 1)
    t_lo = torch.where(fl, torch.zeros_like(ta), torch.minimum(ta, tb))
    t_hi = torch.where(fl, torch.ones_like(ta), torch.maximum(ta, tb))
    # a horizontal segment on a row boundary reads the rows on both sides
    on_row = fl & (pa[:, 1] == rowf) & (row > 0)
    row2 = torch.where(on_row, row - 1, row)
    # columns within each row piece
    dxv = pb[:, 0] - pa[:, 0]
    xa = pa[:, 0] + t_lo * dxv
    xb = pa[:, 0] + t_hi * dxv
    xlo, xhi = torch.minimum(xa, xb), torch.maximum(xa, xb)
    c0 = xlo.floor().clamp(0, cols - 1).long()
    c1 = torch.maximum((xhi.ceil().long() - 1).clamp(0, cols - 1), c0)
    vertical = dxv == 0
    c1 = torch.where(vertical, c0, c1)
    sub, col = expand_runs(c0, c1 - c0 + 1)
    colf = col.to(a.dtype)
    sa = pa[sub]
    # from one column line's crossing to the next, the row piece's ends in place of the outer
    # lines: the columns tile t_lo .. t_hi exactly, however ill-conditioned X → t is for a tiny
    # ΔX (one column keeps the row piece's range)
    one = (c1 == c0)[sub]  # vertical pieces included (c1 set to c0 above)
    lo, hi, d = t_lo[sub], t_hi[sub], dxv[sub]
    inv_dx = 1 / torch.where(one, torch.ones_like(d), d)
    forward = d > 0  # X grows with t
    ua = torch.where(col == c0[sub], torch.where(forward, lo, hi), (colf - sa[:, 0]) * inv_dx)
    ub = torch.where(col == c1[sub], torch.where(forward, hi, lo), (colf + 1 - sa[:, 0]) * inv_dx)
    ua, ub = ua.clamp(lo, hi), ub.clamp(lo, hi)
    t0 = torch.where(one, lo, torch.minimum(ua, ub))
    t1 = torch.where(one, hi, torch.maximum(ua, ub))
    # a vertical piece on a column boundary reads the columns on both sides
    on_col = vertical[sub] & (sa[:, 0] == colf) & (col > 0)
    col2 = torch.where(on_col, col - 1, col)
    return piece[sub], t0, t1, row[sub], col, row2[sub] * cols + col2


class GreenPieces(NamedTuple):
    """Single-cell pieces of pixel boundary segments, the terms of Green's theorem.

    ``∬_A L dA = ∮_∂A P dY`` with ``P(X, Y) = ∫_0^X L(s, Y) ds``; inside source cell
    ``(row, col)`` of a box image ``P`` is linear in ``X``, so a piece contributes exactly
    ``dy · (Σ_{c < col} L[row, c] + frac · L[row, col])``. Pieces with ``ΔY = 0`` contribute
    nothing and are left out.

    Attributes:
        seg: the boundary segment each piece belongs to.
        row, col: the source cell of each piece.
        dy: ``ΔY`` of the piece.
        frac: the piece's mid-``X`` within its cell, in ``[0, 1]``.
    """

    seg: Tensor
    row: Tensor
    col: Tensor
    dy: Tensor
    frac: Tensor


def green_pieces(a: Tensor, b: Tensor, src_size: tuple[int, int]) -> GreenPieces:
    """Cut boundary segments ``a → b`` (``(S, 2)``, source pixel units, inside the image)
    into the [`GreenPieces`][] of an ``(H, W)`` box image."""
    hs, ws = src_size
    keep = torch.nonzero(a[:, 1] != b[:, 1]).squeeze(1)  # ΔY = 0 adds nothing
    a, b = a[keep], b[keep]
    seg, t0, t1, row, col, _ = segment_cells(a, b, hs, ws)
    d = (b - a)[seg]
    frac = (a[seg, 0] + (t0 + t1) / 2 * d[:, 0] - col.to(d.dtype)).clamp(0, 1)
    return GreenPieces(keep[seg], row, col, (t1 - t0) * d[:, 1], frac)


def _segment_chunks(a: Tensor, b: Tensor, max_pieces: int = 1 << 18) -> Iterator[slice]:
    """Consecutive slices of the segments ``a → b`` that each cut into about ``max_pieces``
    single-cell pieces or fewer, so that per-piece temporaries stay bounded."""
    est = ((b - a).abs().ceil().sum(-1) + 2).cumsum(0)
    n = a.shape[0]
    if n == 0:
        return
    total = float(est[-1])
    cuts = torch.searchsorted(
        est, torch.arange(1, -(-total // max_pieces), device=est.device, dtype=est.dtype) * max_pieces
    )
    bounds = [0, *sorted(set(cuts.tolist())), n]
    for lo, hi in itertools.pairwise(bounds):
        if hi > lo:
            yield slice(lo, hi)


class _BoundaryFlux(torch.autograd.Function):
    """Identity on per-segment integrals; gives the vertices their exact Reynolds gradient.

    For a straight segment ``r(t) = a + t (b − a)`` with outward normal line element
    ``n ds = (ΔY, −ΔX) dt``, ``∂/∂a = (ΔY, −ΔX) ∫ (1 − t) L dt`` and
    ``∂/∂b = (ΔY, −ΔX) ∫ t L dt``. Summed around each closed pixel boundary this is the
    derivative of ``∬_A L`` w.r.t. the vertices (the per-segment terms differ from a single
    open segment's derivative only by endpoint terms that cancel around the loop).
    """

    @staticmethod
    def forward(ctx, per_seg, verts, tables, src_size, seg_start, seg_end):
        ctx.save_for_backward(verts, seg_start, seg_end)
        ctx.tables, ctx.src_size = tables, src_size
        return per_seg.clone()

    @staticmethod
    def backward(ctx, grad):
        verts, seg_start, seg_end = ctx.saved_tensors
        tables, (hs, ws) = ctx.tables, ctx.src_size
        a, b = verts[seg_start], verts[seg_end]
        wa = verts.new_zeros(seg_start.numel())
        wb = torch.zeros_like(wa)
        for sl in _segment_chunks(a, b):
            seg, t0, t1, row, col, i2 = segment_cells(a[sl], b[sl], hs, ws)
            seg = seg + sl.start
            lv = 0.5 * (tables.cell(row, col) + tables.cell(i2 // ws, i2 % ws)).to(grad.dtype)  # (N, pieces)
            gl = (grad[:, seg] * lv).sum(0)  # Σ over channels of ∂loss/∂E_s · L
            m1 = (t1 * t1 - t0 * t0) / 2  # ∫ t dt
            wa.index_add_(0, seg, gl * ((t1 - t0) - m1))
            wb.index_add_(0, seg, gl * m1)
        return grad, _vertex_gradient(verts, seg_start, seg_end, wa, wb), None, None, None, None


def _vertex_gradient(verts: Tensor, seg_start: Tensor, seg_end: Tensor, wa: Tensor, wb: Tensor) -> Tensor:
    """Vertex gradients from each segment's Reynolds weights: ``wa`` (start) and ``wb`` (end)
    times the segment's normal line element ``(ΔY, −ΔX)``, summed over the segments."""
    a, b = verts[seg_start], verts[seg_end]
    normal = torch.stack([b[:, 1] - a[:, 1], a[:, 0] - b[:, 0]], -1)
    g = torch.zeros_like(verts)
    g.index_add_(0, seg_start, wa[:, None] * normal)
    return g.index_add_(0, seg_end, wb[:, None] * normal)


class _ExactKernel(torch.autograd.Function):
    """Per-edge Green integrals and areas by the compiled kernel, ``(N + 1, E)``; its backward
    is the exact Reynolds vertex gradient (as [`_BoundaryFlux`][]), also compiled. No image
    gradient."""

    @staticmethod
    def forward(ctx, verts: Tensor, image: Tensor, mesh: PixelMesh) -> Tensor:
        ctx.save_for_backward(verts)
        ctx.mesh = mesh
        if runs_on_device(image):
            out, ctx.tables = _cuda_forward(verts, image.detach().contiguous(), mesh)
            return out
        ctx.image = image.detach().contiguous().numpy()
        out, ctx.tables = _cpu_forward(_kernel_arrays(verts, mesh), ctx.image)
        return torch.from_numpy(out)

    @staticmethod
    def backward(ctx, grad: Tensor):
        (verts,) = ctx.saved_tensors
        mesh = ctx.mesh
        if runs_on_device(verts):
            return _cuda_backward(verts, ctx.tables, mesh, grad), None, None
        g_edge = np.ascontiguousarray(grad.detach().double().cpu().numpy())
        wa, wb = _cpu_weights(_kernel_arrays(verts, mesh), ctx.image, ctx.tables, g_edge)
        wa_t, wb_t = torch.from_numpy(wa), torch.from_numpy(wb)
        return _vertex_gradient(verts.detach(), mesh.seg_start, mesh.seg_end, wa_t, wb_t), None, None


def _cpu_forward(
    arrays: tuple[np.ndarray, ...], image: np.ndarray
) -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray] | None]:
    """The compiled forward on the CPU of the mesh's [`_kernel_arrays`][]: ``(N + 1, E)`` edge
    integrals (and areas), and the prefix tables where the image is small enough to keep them for
    the backward (else ``None``: it is integrated in bands of rows, holding no whole table)."""
    verts, seg_start, seg_end, edge_offsets, seg_edge = arrays
    nt = kernels.threads(image.size + _SEGMENT_WORK * len(seg_start))
    if image.nbytes <= kernels.WHOLE_TABLE_BYTES:
        tables = kernels.prefix_tables(image, kernels.BLOCK, nt)
        out = kernels.exact_forward(verts, seg_start, seg_end, edge_offsets, *tables, kernels.BLOCK, nt)
        return out, tables
    band = kernels.band_rows(image, nt)
    out = kernels.exact_forward_banded(
        verts, seg_start, seg_end, edge_offsets, seg_edge, image, kernels.BLOCK, band, nt
    )
    return out, None


#: What a segment costs the kernels, in elements of [`layoutwarp.kernels.threads`][]' work.
_SEGMENT_WORK = 64


def _cpu_weights(
    arrays: tuple[np.ndarray, ...],
    image: np.ndarray,
    tables: tuple[np.ndarray, np.ndarray] | None,
    grad: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """The compiled backward on the CPU of the mesh's [`_kernel_arrays`][]: the Reynolds weights
    ``(wa, wb)`` of every segment ([`exact_backward`][layoutwarp.kernels.exact_backward]) for the
    edge gradient ``grad`` ``(N + 1, E)``."""
    verts, seg_start, seg_end, _, seg_edge = arrays
    nt = kernels.threads(image.size + _SEGMENT_WORK * len(seg_start))
    incl = (tables or kernels.prefix_tables(image, kernels.BLOCK, nt))[0]
    return kernels.exact_backward(verts, seg_start, seg_end, seg_edge, incl, kernels.BLOCK, grad, nt)


def _kernel_arrays(verts: Tensor, mesh: PixelMesh) -> tuple[np.ndarray, ...]:
    """What the CPU kernels take of a mesh, as contiguous arrays: its vertices (float64), its
    segments' starts and ends, its edges' offsets into the segments and each segment's edge."""
    tensors = (verts.detach().double(), mesh.seg_start, mesh.seg_end, mesh.edge_offsets, mesh.seg_edge)
    return tuple(np.ascontiguousarray(t.cpu().numpy()) for t in tensors)


def _cuda_segments(verts: Tensor, image: Tensor, mesh: PixelMesh) -> tuple[Tensor, Tensor]:
    """The exact forward's values per segment ``(S, N + 1)`` on a CUDA device (or in the
    simulator) and the prefix table ``incl`` (kept for the backward): three launches."""
    n, h, w = image.shape
    stream = stream_of(image)
    incl = image.new_empty(h, w, n)
    offsets = image.new_empty(h, -(-w // kernels.BLOCK), n, dtype=torch.float64)
    kernels.cuda_launch("prefix_blocks", h * offsets.shape[1] * n, stream, image, kernels.BLOCK, incl)
    kernels.cuda_launch("prefix_offsets", h * n, stream, kernels.BLOCK, incl, offsets)
    return cuda_per_segment(verts, mesh, incl, offsets), incl


def cuda_per_segment(verts: Tensor, mesh: PixelMesh, incl: Tensor, offsets: Tensor) -> Tensor:
    """The exact forward's values per segment ``(S, N + 1)`` from the prefix table ``incl`` and
    its block ``offsets``: one launch."""
    v = verts.detach().double().contiguous()
    seg_start, seg_end = (t.to(incl.device) for t in (mesh.seg_start, mesh.seg_end))
    per_seg = v.new_empty(mesh.num_segments, incl.shape[2] + 1)  # each row written whole by its thread
    kernels.cuda_launch(
        "forward",
        mesh.num_segments,
        stream_of(incl),
        v,
        seg_start,
        seg_end,
        incl,
        offsets,
        kernels.BLOCK,
        per_seg,
    )
    return per_seg


def _cuda_forward(verts: Tensor, image: Tensor, mesh: PixelMesh) -> tuple[Tensor, Tensor]:
    """[`_ExactKernel`][]'s forward on a CUDA device: ``(N + 1, E)`` and the prefix table
    ``incl`` (kept for the backward); the tables and a value per segment are the memory it takes."""
    per_seg, incl = _cuda_segments(verts, image, mesh)
    edge_offsets = mesh.edge_offsets.to(image.device)
    out = per_seg.new_empty(per_seg.shape[1], edge_offsets.numel() - 1)  # each column written whole
    stream = stream_of(image)
    kernels.cuda_launch("edge_sums", out.shape[1], stream, per_seg, edge_offsets, out)
    return out, incl


def _cuda_backward(verts: Tensor, incl: Tensor, mesh: PixelMesh, grad: Tensor) -> Tensor:
    """[`_ExactKernel`][]'s vertex gradient on a CUDA device."""
    stream = stream_of(verts)
    v = verts.detach().double().contiguous()
    seg_start, seg_end, seg_edge = (t.to(verts.device) for t in (mesh.seg_start, mesh.seg_end, mesh.seg_edge))
    wa, wb = v.new_zeros(mesh.num_segments), v.new_zeros(mesh.num_segments)
    g = grad.detach().double().contiguous()
    kernels.cuda_launch(
        "backward", mesh.num_segments, stream, v, seg_start, seg_end, seg_edge, incl, kernels.BLOCK, g, wa, wb
    )
    return _vertex_gradient(verts.detach(), seg_start, seg_end, wa, wb)


def exact_on_mesh(work: Tensor, mesh: PixelMesh, compiled: bool) -> Tensor:
    """[`integrate_exact`][] on a mesh: the compiled kernels, or the torch reference."""
    n, hs, ws = work.shape
    verts = mesh.pixel_vertices((hs, ws))
    if compiled:
        pix = mesh.combine_edges(_ExactKernel.apply(verts, work, mesh))
        return pix[:-1] / pix[-1]
    vd = verts.detach()
    a, b = vd[mesh.seg_start], vd[mesh.seg_end]
    tables = _PrefixTables(work)
    per_seg = vd.new_zeros(n, mesh.num_segments)
    for sl in _segment_chunks(a, b):  # autograd records each in-place add (image gradient)
        pcs = green_pieces(a[sl], b[sl], (hs, ws))
        per_seg.index_add_(1, pcs.seg + sl.start, pcs.dy[None] * tables.prefix(pcs.row, pcs.col, pcs.frac))
    if verts.requires_grad:
        per_seg = _BoundaryFlux.apply(per_seg, verts, tables, (hs, ws), mesh.seg_start, mesh.seg_end)
    return mesh.combine_edges(mesh.sum_over_edges(per_seg)) / mesh.areas(verts)
