"""Integrators: the mean radiance over every deformed pixel (paper eq. 7).

All functions take a source ``image`` of shape ``(N, H, W)`` (channels flattened into
``N``; callers reshape ``(B, C, H, W)``) in a floating dtype and return ``(N, h, w)``.
Source pixel ``(r, c)`` covers ``[c, c + 1) × [r, r + 1)`` in source pixel units, which map
to the sensor square by ``X = (x + 1) · W / 2``, ``Y = (y + 1) · H / 2``.

* [`integrate_exact`][] — box radiance over polygonal pixels by Green's theorem,
  ``∬_A L = ∮_∂A P dY`` with ``P`` the row prefix integral. Cost grows with the pixel
  perimeter; each shared edge is integrated once. Tables are float64.
* [`integrate_separable`][] — rectangular layouts: per-axis overlap weights (the
  weights ``cv2.resize(INTER_AREA)`` uses for the uniform layout).
* [`integrate_montecarlo`][] — the paper's stratified Monte Carlo, with the Reynolds
  transport (boundary flux) or the autograd gradient estimator.
* [`integrate_point`][] — one sample per pixel at the deformed centre.
"""

from __future__ import annotations

import contextlib
import itertools
import warnings
from collections import OrderedDict
from collections.abc import Callable, Iterator
from typing import Any, NamedTuple

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from . import kernels, ops
from .checks import (
    all_finite,
    check_choice,
    check_float_dtype,
    check_int,
    check_shape,
    check_size,
    floating_dtype,
    raise_nonfinite,
)
from .coords import grid_lines, pixel_centers, sensor_to_pixels
from .kernels.device import runs_on_device, stream_of
from .kernels.mesh import (
    MeshSpec,
    build_mesh_device,
    device_means,
    device_theta_gradient,
    edge_gradient,
    mesh_integrals,
    mesh_spec,
    theta_gradient,
)
from .layouts import Layout, theta_of
from .maps import sample_points
from .mesh import MeshTopology, PixelMesh, pixel_mesh
from .ops import layout_token

__all__ = [
    "BACKENDS",
    "RADIANCES",
    "GreenPieces",
    "Radiance",
    "axis_weights",
    "data_tolerance",
    "green_pieces",
    "integrate_exact",
    "integrate_montecarlo",
    "integrate_point",
    "integrate_separable",
    "segment_cells",
]

#: Radiance models of a pixel image: each source pixel a constant square, or bilinear.
RADIANCES = ("box", "bilinear")
#: Implementations of the exact integrator (see [`integrate_exact`][]).
BACKENDS = ("auto", "numba", "torch")


def _check_image(image: Tensor, name: str = "image") -> Tensor:
    check_shape(image, ["N", "H", "W"], name)
    if not image.is_floating_point():
        raise TypeError(f"{name} must be a floating-point tensor, got {image.dtype}")
    if image.shape[-1] == 0 or image.shape[-2] == 0:
        raise ValueError(f"{name} height and width must be >= 1, got {tuple(image.shape[-2:])}")
    return image


def data_tolerance(dtype: torch.dtype | np.dtype | type) -> tuple[float, str]:
    """The curved-edge tolerance the data needs, relative to the image's value range, and why.

    Integer images: a quarter of one quantisation step of the dtype's range (``0.25/255``
    for uint8, ``0.25/65535`` for uint16), so an exact integral rounds to the right level.
    float16/bfloat16: a quarter of their precision at 1.0 (``2⁻¹²``, ``2⁻⁹``). Other floats:
    ``2⁻¹²`` (a quarter of a 10-bit step, for the 8–10-bit data most float images hold; pass
    ``tol`` for finer).

    Examples:
        >>> data_tolerance(torch.uint8)[0] == 0.25 / 255
        True
    """
    if isinstance(dtype, torch.dtype):
        if dtype in (torch.float16, torch.bfloat16):
            eps = torch.finfo(dtype).eps
            return eps / 4, f"{dtype}: a quarter of its precision at 1.0"
        if not dtype.is_floating_point:
            dtype = torch.empty((), dtype=dtype).numpy().dtype
    if not isinstance(dtype, torch.dtype):
        dtype = np.dtype(dtype)
        if np.issubdtype(dtype, np.integer):
            step = 1 / np.iinfo(dtype).max
            return 0.25 * step, f"{dtype} input: a quarter of one step (1/{np.iinfo(dtype).max} of the range)"
        if dtype == np.float16:
            return float(np.finfo(dtype).eps) / 4, f"{dtype}: a quarter of its precision at 1.0"
    return 2.0**-12, "float input: a quarter of a 10-bit step (2^-12) of the value range"


def _ranges(lo: Tensor, count: Tensor) -> tuple[Tensor, Tensor]:
    """Expand runs: for ``count[i]`` consecutive integers from ``lo[i]``, the pair
    ``(parent index i, integer)`` of every element, in order.

    Examples:
        >>> _ranges(torch.tensor([5, 0]), torch.tensor([2, 3]))
        (tensor([0, 0, 1, 1, 1]), tensor([5, 6, 0, 1, 2]))
    """
    parent = torch.repeat_interleave(torch.arange(count.numel(), device=count.device), count)
    first = torch.cumsum(count, 0) - count
    return parent, lo[parent] + (torch.arange(parent.numel(), device=count.device) - first[parent])


#: A black-box radiance: points ``(..., 2)`` in sensor coordinates to values ``(..., N)``.
Radiance = Callable[[Tensor], Tensor]


# ----------------------------------------------------------------------------------------
# Exact: Green's theorem over polygon pixels
# ----------------------------------------------------------------------------------------
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
        self.incl = incl.reshape(n, -1)
        self.offsets = offs.reshape(n, -1)

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
    piece, row = _ranges(r0, r1 - r0 + 1)
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
    sub, col = _ranges(c0, c1 - c0 + 1)
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
        arrays = _kernel_arrays(verts, mesh)
        ctx.image = image.detach().contiguous().numpy()
        out, ctx.tables = _cpu_forward(*arrays, mesh.seg_edge.cpu().numpy(), ctx.image)
        return torch.from_numpy(out)

    @staticmethod
    def backward(ctx, grad: Tensor):
        (verts,) = ctx.saved_tensors
        mesh = ctx.mesh
        if runs_on_device(verts):
            return _cuda_backward(verts, ctx.tables, mesh, grad), None, None
        g_edge = np.ascontiguousarray(grad.detach().double().cpu().numpy())
        v, seg_start, seg_end, _ = _kernel_arrays(verts, mesh)
        seg_edge = mesh.seg_edge.cpu().numpy()
        wa, wb = _cpu_weights(v, seg_start, seg_end, seg_edge, ctx.image, ctx.tables, g_edge)
        wa_t, wb_t = torch.from_numpy(wa), torch.from_numpy(wb)
        return _vertex_gradient(verts.detach(), mesh.seg_start, mesh.seg_end, wa_t, wb_t), None, None


def _cpu_forward(
    verts: np.ndarray,
    seg_start: np.ndarray,
    seg_end: np.ndarray,
    edge_offsets: np.ndarray,
    seg_edge: np.ndarray,
    image: np.ndarray,
) -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray] | None]:
    """The compiled forward on the CPU: ``(N + 1, E)`` edge integrals (and areas), and the prefix
    tables where the image is small enough to keep them for the backward (else ``None``: it is
    integrated in bands of rows, holding no whole table)."""
    nt = kernels.threads(image.size + _SEGMENT_WORK * len(seg_start))
    if image.nbytes <= kernels.WHOLE_TABLE_BYTES:
        tables = kernels.prefix_tables(image, kernels.BLOCK, nt)
        out = kernels.exact_forward(verts, seg_start, seg_end, edge_offsets, *tables, kernels.BLOCK, nt)
        return out, tables
    band = kernels.band_rows(image, nt)
    seg_edge = np.ascontiguousarray(seg_edge)
    out = kernels.exact_forward_banded(
        verts, seg_start, seg_end, edge_offsets, seg_edge, image, kernels.BLOCK, band, nt
    )
    return out, None


#: What a segment costs the kernels, in elements of [`layoutwarp.kernels.threads`][]' work.
_SEGMENT_WORK = 64


def _cpu_weights(
    verts: np.ndarray,
    seg_start: np.ndarray,
    seg_end: np.ndarray,
    seg_edge: np.ndarray,
    image: np.ndarray,
    tables: tuple[np.ndarray, np.ndarray] | None,
    grad: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """The compiled backward on the CPU: the Reynolds weights ``(wa, wb)`` of every segment
    ([`exact_backward`][layoutwarp.kernels.exact_backward]) for the edge gradient ``grad`` ``(N + 1, E)``."""
    nt = kernels.threads(image.size + _SEGMENT_WORK * len(seg_start))
    incl = (tables or kernels.prefix_tables(image, kernels.BLOCK, nt))[0]
    seg_edge = np.ascontiguousarray(seg_edge)
    return kernels.exact_backward(verts, seg_start, seg_end, seg_edge, incl, kernels.BLOCK, grad, nt)


# ----------------------------------------------------------------------------------------
# The exact integrator as a torch operator: θ and an image in, the pixels' means and areas out
# ----------------------------------------------------------------------------------------
def _unit(image: Tensor) -> float:
    """A source pixel's area in sensor units (the square ``[-1, 1]²`` is 4)."""
    return 4 / (image.shape[-2] * image.shape[-1])


def _jacobian_shape(theta: Tensor, image: Tensor, height: int, width: int) -> tuple[int, int, int]:
    """The θ-Jacobian of the edge integrals a learnable step keeps: ``(N + 1, E, P)``."""
    return image.shape[0] + 1, MeshTopology((height, width)).num_edges, theta.shape[0]


@torch.library.custom_op("layoutwarp::exact", mutates_args=())
def _exact(
    theta: Tensor,
    image: Tensor,
    layout: str,
    height: int,
    width: int,
    tol: float,
    backend: str,
    jacobian: bool,
    check: bool,
    bounds: Tensor,
    dtype: torch.dtype,
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """The exact means ``(N, h, w)`` (computed in float64, rounded once into ``dtype``) and
    areas ``(h, w)`` (float64, sensor units) of the pixels of ``layout`` (a
    [`layout_token`][layoutwarp.ops.layout_token]) at θ over the box image ``image``
    ``(N, H, W)``. ``theta`` is θ itself where ``bounds`` is empty, else the parameter ρ of
    ``θ = bounds · tanh(ρ)`` (float64;
    [`Layout.theta_source`][layoutwarp.layouts.base.Layout.theta_source]): the operator makes
    θ, so a learnable step's ρ → θ and back cost no launches of their own. With ``jacobian`` (θ
    is learned) also the θ-Jacobian of the edge integrals ``(N + 1, E, P)`` where the compiled
    mesh gives it (the backward is then one contraction), and a 0-d flag on the image's device,
    1 where it holds it (0: the backward computes again; only a CPU step holds one, so reading
    it never waits for a device).
    ``backend``: ``"auto"``, ``"numba"`` or ``"torch"`` (see [`integrate_exact`][]); ``check``:
    raise ``ValueError`` where NaN/Inf reach the means (every source pixel reaches some sensor
    pixel with positive weight, so a bad input value always reaches its output); a device mesh
    checks on the device, and the error comes when its status reaches the host, in a later step
    ([`device_status`][layoutwarp.kernels.mesh.device_status] reads it at once): the step waits
    for nothing."""
    size, (hs, ws) = (height, width), image.shape[-2:]
    which = "torch" if backend == "torch" else ops.backend(image, "learn", wait=backend == "numba")
    if backend == "numba" and which == "torch":
        raise ValueError(
            "backend='numba' needs numba installed, a CPU image or a CUDA image where numba's CUDA "
            "target runs, and no image gradient; use backend='torch'"
        )
    template = ops.layout_of(layout)
    spec = mesh_spec(template) if which != "torch" else None
    image = image.contiguous()
    if spec is not None and which == "cuda":  # the mesh built where it is used: none crosses the bus
        held = image.new_empty((), dtype=torch.int8)  # where the image is: a graph holds no CPU tensor
        means, area, areas, dm = _device_exact(spec, theta, bounds, image, size, tol, check, dtype, held)
        if jacobian:  # the device mesh kept for the backward (the entry holds the means: their
            DEVICE_MESHES[means.data_ptr()] = (means, dm, area)  # memory is not reused meanwhile)
            while len(DEVICE_MESHES) > 4:
                DEVICE_MESHES.popitem(last=False)
        return means, areas, image.new_empty(0, dtype=torch.float64), held  # checked on the device
    no_jac = (  # zeros: the torch path's room for a Jacobian it does not fill
        image.new_zeros(_jacobian_shape(theta, image, *size), dtype=torch.float64)
        if _keeps_jacobian(image, jacobian)
        else image.new_empty(0, dtype=torch.float64)
    )
    held = image.new_zeros((), dtype=torch.int8)
    if spec is not None and jacobian:  # mesh, integrals and their θ-Jacobian, chunk by chunk
        th = theta_of(theta, bounds).detach().cpu().numpy()
        tables = kernels.prefix_tables(image.numpy(), kernels.BLOCK)
        out, j = mesh_integrals(spec, size, th, tol, tables, (hs, ws))
        pix = MeshTopology(size).combine(out)
        held.fill_(1)
        means, areas, jac = (torch.from_numpy(a) for a in (pix[:-1] / pix[-1], pix[-1] * _unit(image), j))
    else:
        with ops.autograd_inside() if jacobian else contextlib.nullcontext():  # the mesh a gradient needs
            th = theta_of(theta, bounds).detach().requires_grad_(jacobian)
            means, areas = _mesh_exact(th, image, template, size, tol, which != "torch", cache=not jacobian)
        means, areas, jac = means.detach(), areas.detach().clone(), no_jac
    means = means.to(dtype)
    if check and not all_finite(means):
        raise_nonfinite(image)
    return means, areas, jac, held


@_exact.register_fake
def _(theta, image, layout, height, width, tol, backend, jacobian, check, bounds, dtype):
    n = image.shape[0]
    jac = _jacobian_shape(theta, image, height, width) if _keeps_jacobian(image, jacobian) else (0,)
    return (
        image.new_empty(n, height, width, dtype=dtype),
        image.new_empty(height, width, dtype=torch.float64),
        image.new_empty(jac, dtype=torch.float64),
        image.new_empty((), dtype=torch.int8),
    )


def _keeps_jacobian(image: Tensor, jacobian: bool) -> bool:
    """Whether ``layoutwarp::exact`` returns a θ-Jacobian's room: a learnable step on the CPU (a
    device keeps its mesh instead)."""
    return jacobian and not runs_on_device(image)


#: The device meshes of the last four learnable forwards on a CUDA device (with their images'
#: prefix tables), their means and areas, by the address of their means: the backward takes its forward's
#: rather than building the mesh again (where a compiled graph copied the means, it builds it).
DEVICE_MESHES: OrderedDict[int, tuple] = OrderedDict()


def _device_exact(
    spec: MeshSpec,
    theta: Tensor,
    bounds: Tensor,
    image: Tensor,
    size: tuple[int, int],
    tol: float,
    check: bool,
    dtype: torch.dtype,
    zero: Tensor,
) -> tuple:
    """The device mesh of ``spec`` at θ (``theta`` and ``bounds`` as [`_exact`][] takes them; with
    ``image``'s prefix table) and its integrals over ``image``: ``(means in dtype, areas in source
    pixels, areas in sensor units, mesh)``; the 0-d ``zero`` set to 0 on the way."""
    src = tuple(image.shape[-2:])
    param, bounds = theta.detach().to(image.device), bounds.to(image.device)
    if param.dtype not in (torch.float32, torch.float64):  # numba takes no half precision
        param = param.float()
    dm = build_mesh_device(spec, size, param, tol, src, bounds=bounds, image=image)
    per_seg = _cuda_per_segment(dm.pixel_vertices, dm.mesh, dm.incl, dm.offsets)
    means, area, areas = device_means(dm, per_seg, _unit(image), check, dtype, zero.view(1))
    return means, area, areas, dm


def _mesh_exact(
    theta: Tensor,
    image: Tensor,
    layout: Layout,
    size: tuple[int, int],
    tol: float,
    compiled: bool,
    cache: bool = True,
) -> tuple[Tensor, Tensor]:
    """Means and areas (sensor units) of ``layout``'s polygon mesh at ``theta``: the compiled
    kernels on the mesh, or the torch reference (differentiable in θ and, on the torch path, in
    the image, where autograd is on)."""
    mesh = pixel_mesh(layout, size, tol=tol, dtype=torch.float64, theta=theta, cache=cache)
    return _exact_on_mesh(image, mesh, compiled), mesh.areas()


@torch.library.custom_op("layoutwarp::exact_backward", mutates_args=())
def _exact_backward(
    grad_means: Tensor | None,
    grad_areas: Tensor | None,
    theta: Tensor,
    image: Tensor,
    means: Tensor,
    areas: Tensor,
    jac: Tensor,
    held: Tensor,
    layout: str,
    height: int,
    width: int,
    tol: float,
    backend: str,
    theta_grad: bool,
    image_grad: bool,
    bounds: Tensor,
) -> tuple[Tensor, Tensor]:
    """The gradients of ``layoutwarp::exact``'s ``theta`` (θ or ρ, as ``bounds`` says) and image
    from those of its means and areas (``None``: unused) (the image's: an empty tensor unless
    ``image_grad``; θ's, zeros unless ``theta_grad``): the exact Reynolds transport gradient, by
    one contraction with the kept Jacobian, by the device kernels, or by the mesh again with
    autograd."""
    size = (height, width)
    if (
        jac.numel() and bool(held) and not image_grad
    ):  # the compiled CPU step: the quotient rule and one contraction
        g = np.zeros(means.shape) if grad_means is None else grad_means.detach().double().cpu().numpy()
        own = None if grad_areas is None else grad_areas.detach().double().cpu().numpy() * _unit(image)
        g_edge = edge_gradient(g, means.double().cpu().numpy(), areas.cpu().numpy() / _unit(image), own)
        g_theta = theta_gradient(g_edge, jac.cpu().numpy())
        return _to_param(torch.from_numpy(g_theta), theta, bounds), image.new_empty(0)
    which = "torch" if backend == "torch" or image_grad else ops.backend(image, "learn")
    template = ops.layout_of(layout)
    spec = mesh_spec(template) if which == "cuda" else None
    if spec is not None:  # the forward's device mesh, else built again (its sizes live on the device)
        kept = DEVICE_MESHES.pop(means.data_ptr(), None)
        if kept is None:
            zero = image.new_empty(1, dtype=torch.int8)
            _, area, _, dm = _device_exact(
                spec, theta, bounds, image.contiguous(), size, tol, False, means.dtype, zero
            )
        else:
            _, dm, area = kept
        g_means = torch.zeros_like(means) if grad_means is None else grad_means
        args = (means, area, g_means, grad_areas, _unit(image), tuple(image.shape[-2:]), theta.dtype)
        return device_theta_gradient(dm, *args), image.new_empty(0)
    with ops.autograd_inside():
        param = theta.detach().requires_grad_(theta_grad)  # the forward's mesh: built as it was
        th = theta_of(param, bounds)
        img = image.detach().requires_grad_(image_grad)
        m, a = _mesh_exact(th, img, template, size, tol, which != "torch", cache=False)
        inputs = [t for t in (param, img) if t.requires_grad]
        outs = [(o, g) for o, g in ((m, grad_means), (a, grad_areas)) if o.requires_grad and g is not None]
        grads = iter(
            torch.autograd.grad([o for o, _ in outs], inputs, [g for _, g in outs], allow_unused=True)
            if outs
            else ()
        )
    g_theta, g_image = (next(grads, None) if t.requires_grad else None for t in (param, img))
    return (
        torch.zeros_like(theta) if g_theta is None else g_theta.to(theta),
        image.new_empty(0)
        if not image_grad
        else torch.zeros_like(image)
        if g_image is None
        else g_image.to(image).contiguous(),
    )


@_exact_backward.register_fake
def _(grad_means, grad_areas, theta, image, *rest):
    return torch.empty_like(theta), image.new_empty(image.shape) if rest[-2] else image.new_empty(0)


def _to_param(g_theta: Tensor, param: Tensor, bounds: Tensor) -> Tensor:
    """The gradient of θ's parameter ``param`` (θ, or ρ: see
    [`theta_of`][layoutwarp.layouts.base.theta_of]) from θ's, ``g_theta`` (float64), in
    ``param``'s dtype."""
    if not bounds.numel():
        return g_theta.to(param)
    with ops.autograd_inside():
        p = param.detach().double().requires_grad_(True)
        (g,) = torch.autograd.grad(theta_of(p, bounds), p, g_theta.to(p.device))
    return g.to(param)


def _exact_setup(ctx: Any, inputs: tuple, output: tuple) -> None:
    theta, image, layout, height, width, tol, backend, _, _, bounds, _ = inputs
    means, areas, jac, held = output
    ctx.save_for_backward(theta, image, means, areas, jac, held, bounds)
    ctx.args = (layout, height, width, tol, backend)
    ctx.set_materialize_grads(False)  # an output nobody used costs its backward nothing


def _exact_grad(ctx: Any, grad_means: Tensor, grad_areas: Tensor, *_: Tensor) -> tuple:
    theta, image, means, areas, jac, held, bounds = ctx.saved_tensors
    theta_grad, image_grad = ctx.needs_input_grad[:2]
    if grad_means is None and grad_areas is None:
        return (None,) * 11
    g_theta, g_image = _exact_backward(
        grad_means,
        grad_areas,
        theta,
        image,
        means,
        areas,
        jac,
        held,
        *ctx.args,
        theta_grad,
        image_grad,
        bounds,
    )
    return (
        (g_theta if theta_grad else None),
        (g_image if image_grad else None),
        *[None] * 9,
    )


_exact.register_autograd(_exact_grad, setup_context=_exact_setup)
ops.first_order_only(_exact_backward, "exact")
ops.register(_exact, fold=1, outputs=("image", "shared", "jacobian", "shared"))
ops.register(_exact_backward)


def _kernel_arrays(verts: Tensor, mesh: PixelMesh) -> list[np.ndarray]:
    """Vertices (float64) and the mesh's segment and edge indices as contiguous arrays."""
    tensors = (verts.detach().double(), mesh.seg_start, mesh.seg_end, mesh.edge_offsets)
    return [np.ascontiguousarray(t.cpu().numpy()) for t in tensors]


def _cuda_segments(verts: Tensor, image: Tensor, mesh: PixelMesh) -> tuple[Tensor, Tensor]:
    """The exact forward's values per segment ``(S, N + 1)`` on a CUDA device (or in the
    simulator) and the prefix table ``incl`` (kept for the backward): three launches."""
    n, h, w = image.shape
    stream = stream_of(image)
    incl = image.new_empty(h, w, n)
    offsets = image.new_empty(h, -(-w // kernels.BLOCK), n, dtype=torch.float64)
    kernels.cuda_launch("prefix_blocks", h * offsets.shape[1] * n, stream, image, kernels.BLOCK, incl)
    kernels.cuda_launch("prefix_offsets", h * n, stream, kernels.BLOCK, incl, offsets)
    return _cuda_per_segment(verts, mesh, incl, offsets), incl


def _cuda_per_segment(verts: Tensor, mesh: PixelMesh, incl: Tensor, offsets: Tensor) -> Tensor:
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


def integrate_exact(
    image: Tensor,
    layout: Layout,
    size: tuple[int, int],
    *,
    tol: float | None = None,
    mesh: PixelMesh | None = None,
    theta: Tensor | None = None,
    backend: str = "auto",
    return_areas: bool = False,
    dtype: torch.dtype = torch.float64,
    allow_nonfinite: bool = True,
) -> Tensor | tuple[Tensor, Tensor]:
    """Exact mean of a piecewise-constant (box) image over every polygonal pixel.

    Uses Green's theorem ``∬_A L dA = ∮_∂A P dY`` with ``P(X, Y) = ∫_0^X L(s, Y) ds``: each
    boundary segment is cut at source rows and columns, and within one cell ``P`` is linear
    in ``X``, so a piece contributes ``ΔY · P(mid-X)`` exactly. Each shared edge is computed
    once; straight-edged pixels are exact, curved edges are polylines within ``tol``
    (see [`layoutwarp.mesh.pixel_mesh`][pixel_mesh]). Differentiable in the image (autograd through
    the prefix tables) and, through the mesh vertices, in θ, with the exact Reynolds
    boundary gradient (symmetric where an edge lies on a source cell boundary).

    Args:
        image: ``(N, H, W)`` floating source image (float32 tables for float32 input,
            float64 for float64).
        layout: the pixel layout.
        size: sensor size ``(h, w)``.
        tol: bound on each pixel's error relative to the image's value range, spent on the
            polyline approximation of curved edges; ``None``: what the image's dtype resolves
            ([`data_tolerance`][]), as [`simulate`][layoutwarp.sensor.simulate] does.
        mesh: a precomputed mesh (overrides ``layout``/``tol``/``theta`` for the geometry).
        theta: use this θ instead of the layout's own (e.g. for ``gradcheck``).
        backend: ``"numba"`` (the compiled kernels of `layoutwarp.kernels`: CPU, and
            CUDA where numba's CUDA target runs; no image gradient), ``"torch"`` (the
            vectorised reference: any device, image gradient) or ``"auto"`` (numba when it
            applies, else torch).
        return_areas: also return the pixels' areas ``(h, w)`` (float64, sensor units: the square
            ``[-1, 1]²`` is 4), differentiable in θ like the means (what sensor physics needs: a
            learnable layout's compiled path has them as the boundary integral of 1 it divides by).
        dtype: the means' dtype (computed in float64 and rounded once;
            [`simulate`][layoutwarp.sensor.simulate] asks for the image's).
        allow_nonfinite: ``False`` raises ``ValueError`` where NaN/Inf in the image reach the means.

    Returns:
        ``(N, h, w)`` in ``dtype``; with ``return_areas``, ``(means, areas)``.
    """
    _check_image(image)
    check_choice(backend, BACKENDS, "backend")
    dtype = check_float_dtype(dtype)
    work = image.to(floating_dtype(image.dtype)).contiguous()
    if mesh is not None:  # a mesh given: its geometry, as it is (eager)
        kernel_ok = backend != "torch" and not image.requires_grad
        kernel_ok = kernel_ok and ops.backend(work, "learn", wait=backend == "numba") != "torch"
        means = _exact_on_mesh(work, mesh, kernel_ok).to(dtype)
        return (means, mesh.areas()) if return_areas else means
    tol = data_tolerance(image.dtype)[0] if tol is None else tol
    # θ as the operator takes it: a fixed layout's as it was set (float64), a learnable one's ρ
    param, bounds = (
        layout.theta_source() if theta is None else (theta, theta.new_empty(0, dtype=torch.float64))
    )
    if image.requires_grad and backend == "numba":
        raise ValueError(
            "backend='numba' needs numba installed, a CPU image or a CUDA image where numba's CUDA "
            "target runs, and no image gradient; use backend='torch'"
        )
    which = "torch" if image.requires_grad else backend
    jacobian = param.requires_grad and torch.is_grad_enabled()
    h, w = check_size(size)
    token = layout_token(layout)
    check = not allow_nonfinite
    means, areas, _, _ = torch.ops.layoutwarp.exact(
        param, work, token, h, w, float(tol), which, jacobian, check, bounds, dtype
    )
    return (means, areas) if return_areas else means


def _exact_on_mesh(work: Tensor, mesh: PixelMesh, compiled: bool) -> Tensor:
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


# ----------------------------------------------------------------------------------------
# Separable: rectangular layouts
# ----------------------------------------------------------------------------------------
def axis_weights(edges: Tensor, n_src: int) -> tuple[Tensor, Tensor, Tensor]:
    """Sparse overlap weights between sensor intervals and source cells along one axis.

    Args:
        edges: ``(n + 1,)`` increasing interval boundaries in source pixel units.
        n_src: number of source cells (cell ``c`` is ``[c, c + 1)``).

    Returns:
        ``(dst, src, weight)``: interval ``dst[t]`` overlaps cell ``src[t]`` over a fraction
        ``weight[t]`` of the interval's length (weights of one interval sum to 1).
        Differentiable in ``edges``.
    """
    lo, hi = edges[:-1], edges[1:]
    c0 = lo.detach().floor().clamp(0, n_src - 1).long()
    c1 = (hi.detach().ceil().long() - 1).clamp(0, n_src - 1)
    dst, src = _ranges(c0, torch.maximum(c1, c0) - c0 + 1)
    cf = src.to(edges.dtype)
    overlap = (torch.minimum(hi[dst], cf + 1) - torch.maximum(lo[dst], cf)).clamp_min(0)
    return dst, src, overlap / (hi - lo)[dst]


def _separable_edges(
    layout: Layout, size: tuple[int, int], src: tuple[int, int], theta: Tensor
) -> tuple[Tensor, Tensor]:
    """Pixel edges along x and y in source pixel units (float64, differentiable in θ)."""
    h, w = size
    hs, ws = src
    theta = theta.double()
    gx, gy = grid_lines(w, theta.dtype, theta.device), grid_lines(h, theta.dtype, theta.device)
    qx = layout.phi(torch.stack([gx, torch.zeros_like(gx)], -1), theta)  # the column edges on y = 0
    qy = layout.phi(torch.stack([torch.zeros_like(gy), gy], -1), theta)  # the row edges on x = 0
    ex = sensor_to_pixels(qx, (hs, ws))[:, 0]
    ey = sensor_to_pixels(qy, (hs, ws))[:, 1]
    return ex.clamp(0, ws), ey.clamp(0, hs)


def _axis_csr(edges: Tensor, n_src: int, dtype: torch.dtype) -> tuple[Tensor, Tensor]:
    """The ``(n, n_src)`` overlap-weight matrix of an axis and its transpose, as CSR."""
    dst, src, wt = axis_weights(edges.detach(), n_src)
    n = edges.numel() - 1
    idx, wt = torch.stack([dst, src]), wt.to(dtype)
    with warnings.catch_warnings():  # torch calls CSR "beta" and warns once per process
        warnings.simplefilter("ignore", UserWarning)
        mat = torch.sparse_coo_tensor(idx, wt, (n, n_src), check_invariants=False).coalesce().to_sparse_csr()
        mat_t = torch.sparse_coo_tensor(idx.flip(0), wt, (n_src, n), check_invariants=False)
        mat_t = mat_t.coalesce().to_sparse_csr()
    return mat, mat_t


def _rows(mat: Tensor, x: Tensor) -> Tensor:
    """``mat @ x[k]`` for every ``k``: sparse ``(m, H)`` times ``(N, H, W)`` gives ``(N, m, W)``."""
    n, h, w = x.shape
    if n <= 8:
        return torch.stack([torch.sparse.mm(mat, x[k]) for k in range(n)])
    flat = x.permute(1, 0, 2).reshape(h, n * w)  # one call for many small images
    return torch.sparse.mm(mat, flat).view(-1, n, w).permute(1, 0, 2)


def _cols(x: Tensor, mat_t: Tensor) -> Tensor:
    """``x @ mat_t``: ``(N, H, W)`` times sparse ``(W, m)`` gives ``(N, H, m)``."""
    n, h, w = x.shape
    return torch.mm(x.reshape(n * h, w), mat_t).view(n, h, -1)


def _edge_values(profile: Tensor, edges: Tensor) -> Tensor:
    """A piecewise-constant ``profile (..., n_src)`` read at ``edges (m,)``: ``(..., m)``.

    At an exact cell boundary the mean of the two cells is returned (the symmetric
    subgradient, which is what central differences see).
    """
    n_src = profile.shape[-1]
    x = edges.detach()
    left = (x.ceil().long() - 1).clamp(0, n_src - 1)
    right = x.floor().long().clamp(0, n_src - 1)
    return 0.5 * (profile[..., left] + profile[..., right])


@torch.library.custom_op("layoutwarp::separable", mutates_args=())
def _separable(image: Tensor, ex: Tensor, ey: Tensor, check: bool) -> Tensor:
    """``W_y · image · W_xᵀ`` ``(N, h, w)`` with the overlap weights of the interval edges ``ex``
    ``(w + 1,)`` and ``ey`` ``(h + 1,)`` (source pixel units); ``check``: raise ``ValueError``
    where NaN/Inf reach the output."""
    _, hs, ws = image.shape
    wy = _axis_csr(ey, hs, image.dtype)[0]
    wx_t = _axis_csr(ex, ws, image.dtype)[1]
    out = _cols(_rows(wy, image), wx_t)
    if check and not all_finite(out):
        raise_nonfinite(image)
    return out


@_separable.register_fake
def _(image, ex, ey, check):
    return image.new_empty(image.shape[0], ey.shape[0] - 1, ex.shape[0] - 1)


@torch.library.custom_op("layoutwarp::separable_backward", mutates_args=())
def _separable_backward(
    grad: Tensor, image: Tensor, ex: Tensor, ey: Tensor, out: Tensor, needs: list[bool]
) -> tuple[Tensor, Tensor, Tensor]:
    """The gradients of ``layoutwarp::separable`` in the image, ``ex`` and ``ey`` (empty tensors
    where ``needs`` says none is needed).

    The gradient w.r.t. an interval edge is the boundary (Reynolds) term of the box integral:
    for interval ``i`` with length ``Δ_i`` and mean ``I_i``, moving its right edge ``e_{i+1}``
    changes ``I_i`` by ``(L(e_{i+1}) − I_i) / Δ_i``, where ``L`` is the image already averaged
    over the other axis."""
    _, hs, ws = image.shape
    grad = grad.contiguous()
    wy, wy_t = _axis_csr(ey, hs, image.dtype)
    wx, wx_t = _axis_csr(ex, ws, image.dtype)
    g_img, g_ex, g_ey = image.new_empty(0), ex.new_empty(0), ey.new_empty(0)
    if needs[0]:
        g_img = _rows(wy_t, _cols(grad, wx))
    if needs[1]:
        y1 = _rows(wy, image)  # (N, h, W)
        g_ex = _edge_grad(grad, out, _edge_values(y1, ex), ex, -1).to(ex)
    if needs[2]:
        # the image averaged over each column interval, needed only on the boundary rows
        y = ey.detach()
        rows = torch.cat([(y.ceil().long() - 1).clamp(0, hs - 1), y.floor().long().clamp(0, hs - 1)])
        x1 = _cols(image.index_select(1, rows).contiguous(), wx_t)  # (N, 2(h + 1), w)
        vals = 0.5 * (x1[:, : y.numel()] + x1[:, y.numel() :])  # symmetric at cell boundaries
        g_ey = _edge_grad(grad, out, vals, ey, -2).to(ey)
    return g_img.contiguous(), g_ex.contiguous(), g_ey.contiguous()


@_separable_backward.register_fake
def _(grad, image, ex, ey, out, needs):
    return tuple(
        t.new_empty(t.shape) if n else t.new_empty(0) for t, n in zip((image, ex, ey), needs, strict=True)
    )


def _separable_setup(ctx: Any, inputs: tuple, output: Tensor) -> None:
    image, ex, ey, _ = inputs
    ctx.save_for_backward(image, ex, ey, output)


def _separable_grad(ctx: Any, grad: Tensor) -> tuple:
    image, ex, ey, out = ctx.saved_tensors
    needs = list(ctx.needs_input_grad[:3])
    grads = _separable_backward(grad, image, ex, ey, out, needs)
    return (*(g if n else None for g, n in zip(grads, needs, strict=True)), None)


_separable.register_autograd(_separable_grad, setup_context=_separable_setup)
ops.first_order_only(_separable_backward, "separable")
ops.register(_separable, fold=0)
ops.register(_separable_backward)


def _edge_grad(grad: Tensor, out: Tensor, vals: Tensor, edges: Tensor, dim: int) -> Tensor:
    """``∂loss/∂edge`` from boundary values ``vals`` (``n + 1`` along ``dim`` of ``out``)."""
    n = out.shape[dim]
    shape = [1] * out.ndim
    shape[dim] = n
    weight = grad / (edges[1:] - edges[:-1]).to(out.dtype).view(shape)
    others = [d for d in range(out.ndim) if d != dim % out.ndim]
    right = (weight * (vals.narrow(dim, 1, n) - out)).sum(others).double()
    left = (weight * (vals.narrow(dim, 0, n) - out)).sum(others).double()
    return F.pad(right, (1, 0)) - F.pad(left, (0, 1))


def integrate_separable(
    image: Tensor,
    layout: Layout,
    size: tuple[int, int],
    *,
    theta: Tensor | None = None,
    return_areas: bool = False,
    allow_nonfinite: bool = True,
) -> Tensor | tuple[Tensor, Tensor]:
    """Exact box-radiance mean over the rectangular pixels of a separable layout.

    Two sparse passes, rows (``H → h``) then columns (``W → w``), with per-axis overlap
    weights. For the uniform layout this is area resampling, identical to
    ``cv2.resize(..., interpolation=cv2.INTER_AREA)`` when downscaling. Differentiable in the
    image and in θ (analytic boundary gradient).

    Args:
        image: ``(N, H, W)`` floating source image.
        layout: a layout with ``separable = True``.
        size: sensor size ``(h, w)``.
        theta: use this θ instead of the layout's own (e.g. for ``gradcheck``).
        return_areas: also return the pixels' areas ``(h, w)`` (float64, sensor units: the square
            ``[-1, 1]²`` is 4), differentiable in θ: products of the rows' and columns' widths.
        allow_nonfinite: ``False`` raises ``ValueError`` where NaN/Inf in the image reach the means.

    Returns:
        ``(N, h, w)`` in float64 for float64 input, else float32; with ``return_areas``,
        ``(means, areas)``.
    """
    _, hs, ws = _check_image(image).shape
    if not layout.separable:
        raise ValueError(f"integrate_separable needs a separable layout, got {type(layout).__name__}")
    ex, ey = _separable_edges(layout, check_size(size), (hs, ws), layout.resolve_theta(theta))
    work = image.to(floating_dtype(image.dtype)).contiguous()
    means = torch.ops.layoutwarp.separable(work, ex, ey, not allow_nonfinite)
    if not return_areas:
        return means
    return means, torch.outer(ey.diff() * (2 / hs), ex.diff() * (2 / ws))


# ----------------------------------------------------------------------------------------
# Sampling integrators
# ----------------------------------------------------------------------------------------
def _sample(image: Tensor | Radiance, points: Tensor, radiance: str) -> Tensor:
    """Radiance at sensor points ``(P, Q, 2)``: ``(N, P, Q)``.

    ``image`` is an ``(N, H, W)`` tensor sampled with ``radiance`` = ``"bilinear"`` or
    ``"box"`` (the source pixel containing the point), or a callable ``L(points) -> (..., N)``.
    """
    if callable(image) and not isinstance(image, Tensor):
        vals = image(points)
        if vals.ndim == points.ndim - 1:
            vals = vals[..., None]
        return vals.movedim(-1, 0)
    mode = {"bilinear": "bilinear", "box": "nearest"}[radiance]
    grid = points.to(image.dtype)[None]
    return F.grid_sample(image[None], grid, mode=mode, padding_mode="border", align_corners=False)[0]


def _check_radiance(image: Tensor | Radiance, radiance: str) -> None:
    check_choice(radiance, RADIANCES, "radiance")
    if not callable(image) or isinstance(image, Tensor):
        _check_image(image)


def integrate_point(
    image: Tensor | Radiance,
    layout: Layout,
    size: tuple[int, int],
    *,
    radiance: str = "bilinear",
    theta: Tensor | None = None,
) -> Tensor:
    """One sample per pixel at the deformed pixel centre ``φ(c_k)``: the aliasing baseline.

    Args:
        image: ``(N, H, W)`` tensor, or a callable radiance ``L(points (..., 2)) -> (..., N)``.
        layout: the pixel layout.
        size: sensor size ``(h, w)``.
        radiance: ``"bilinear"`` or ``"box"`` for tensor images.
        theta: use this θ instead of the layout's own.

    Returns:
        ``(N, h, w)``; differentiable in the image and (for bilinear or callable radiance)
        in θ.
    """
    _check_radiance(image, radiance)
    theta = layout.resolve_theta(theta)
    c = pixel_centers(check_size(size), dtype=theta.dtype, device=theta.device)
    return _sample(image, layout.phi(c, theta), radiance)


@torch.library.custom_op("layoutwarp::flux", mutates_args=())
def _flux(
    value: Tensor,
    theta: Tensor,
    vol: Tensor,
    image: Tensor,
    seed: Tensor,
    layout: str,
    radiance_fn: str,
    height: int,
    width: int,
    samples: int,
    radiance: str,
) -> Tensor:
    """Identity on ``value``; its θ-gradient is the Reynolds boundary flux (paper eq. 16).

    ``∂I_k/∂θ = (1/|A_k|) ∮_∂A_k (L − I_k) ⟨∂r/∂θ, n⟩ ds`` (constant sensitivity ``W``, so
    the interior term vanishes), estimated with stratified jittered samples along every
    edge (drawn from ``seed``); each shared edge is sampled once and used with opposite signs by
    its two pixels. Needs no gradient of ``L`` (the image, or the callable of ``radiance_fn``).
    The work is done in the backward pass only."""
    return value.clone()


@_flux.register_fake
def _(value, *rest):
    return torch.empty_like(value)


@torch.library.custom_op("layoutwarp::flux_backward", mutates_args=())
def _flux_backward(
    grad: Tensor,
    value: Tensor,
    theta: Tensor,
    vol: Tensor,
    image: Tensor,
    seed: Tensor,
    layout: str,
    radiance_fn: str,
    height: int,
    width: int,
    samples: int,
    radiance: str,
) -> Tensor:
    """θ's gradient of ``layoutwarp::flux``: [`_flux_gradient`][] with the weights ``grad / vol``."""
    source = ops.object_of(radiance_fn) if radiance_fn else image
    generator = ops.generator_of(seed, theta.device)
    with ops.autograd_inside():
        g = _flux_gradient(
            source, ops.layout_of(layout), theta.detach(), (height, width), samples, radiance, generator,
            grad / vol, value,
        )  # fmt: skip
    return g.to(theta.dtype)


@_flux_backward.register_fake
def _(grad, value, theta, *rest):
    return torch.empty_like(theta)


def _flux_setup(ctx: Any, inputs: tuple, output: Tensor) -> None:
    value, theta, vol, image, seed, *args = inputs
    ctx.save_for_backward(value, theta, vol, image, seed)
    ctx.args = args


def _flux_grad(ctx: Any, grad: Tensor) -> tuple:
    g_theta = _flux_backward(grad, *ctx.saved_tensors, *ctx.args) if ctx.needs_input_grad[1] else None
    return grad, g_theta, *[None] * 9


_flux.register_autograd(_flux_grad, setup_context=_flux_setup)
ops.first_order_only(_flux_backward, "flux")
ops.register(_flux)
ops.register(_flux_backward)


def _flux_gradient(
    image, layout: Layout, theta: Tensor, size, m: int, radiance, generator, weight: Tensor, value: Tensor
) -> Tensor:
    """``Σ_{n,k} weight[n, k] ∮_∂A_k (L_n − I_nk) ⟨∂r/∂θ, n⟩ ds``: θ's gradient of the pixel
    means through their boundary fluxes, for ``weight`` and ``value`` ``(N, h, w)``.

    Along an edge ``r(t) = φ(γ(t))`` the outward normal line element of the positively
    oriented pixel boundary is ``n ds = (ṙ_y, −ṙ_x) dt`` with ``ṙ = J_φ γ̇``, sampled at ``m``
    stratified points. The weights are summed onto the edges first (each edge adds to one
    pixel and subtracts from the other), so each sample carries one coefficient ``c``, and the
    gradient is one vector-Jacobian product of φ in θ with the cotangent ``c · (ṙ_y, −ṙ_x)``:
    no ``∂φ/∂θ`` of ``(E, m, 2, P)`` is formed, so the cost does not grow with θ's length.
    """
    dtype, dev = theta.dtype, theta.device
    topo = MeshTopology(size)
    a, b = topo.edge_ends(dtype, dev)  # (E, 2): horizontal edges run +x, vertical edges +y
    at = generator.device if generator is not None else dev  # drawn where the generator is
    t = (
        torch.arange(m, dtype=dtype, device=dev)
        + torch.rand(m, generator=generator, dtype=dtype, device=at).to(dev)
    ) / m
    pts = a[:, None] + t[:, None] * (b - a)[:, None]  # (E, m, 2) stratified along every edge
    with torch.enable_grad():
        th = theta.detach().requires_grad_(True)
        r = layout.phi(pts, th)
    if not r.requires_grad:  # φ does not depend on θ
        return torch.zeros_like(theta)
    rdot = (layout.phi_jacobian(pts, theta) @ (b - a)[:, None, :, None])[..., 0]  # J γ̇
    lv = _sample(image, r.detach(), radiance).to(dtype)  # (N, E, m)
    w = weight.to(dtype)
    per_edge = topo.combine_adjoint(w)  # (N, E): Σ_k ±weight[n, k] over the edge's two pixels
    offset = topo.combine_adjoint(w * value.to(dtype)).sum(0)  # (E,): the same of weight · I
    c = ((lv * per_edge[..., None]).sum(0) - offset[:, None]) / m  # (E, m)
    cot = torch.stack([c * rdot[..., 1], -c * rdot[..., 0]], -1)  # (E, m, 2)
    (grad,) = torch.autograd.grad(r, th, cot, allow_unused=True)
    return torch.zeros_like(theta) if grad is None else grad


def integrate_montecarlo(
    image: Tensor | Radiance,
    layout: Layout,
    size: tuple[int, int],
    *,
    samples: int = 4,
    radiance: str = "bilinear",
    grad: str = "reynolds",
    generator: torch.Generator | None = None,
    seed: int | None = None,
    theta: Tensor | None = None,
) -> Tensor:
    """Stratified Monte Carlo estimate of every pixel's mean radiance (the paper's method).

    ``s × s`` jittered samples per uniform cell ``U_k`` are mapped by φ and weighted by
    ``|det J_φ|``: ``I_k = Σ L(φ(u)) |det J| / Σ |det J|``. The image is sampled in place (no
    copy per sample).

    Args:
        image: ``(N, H, W)`` tensor, or a callable radiance ``L(points (..., 2)) -> (..., N)``.
        layout: the pixel layout.
        size: sensor size ``(h, w)``.
        samples: ``s`` (``s²`` samples per pixel).
        radiance: ``"bilinear"`` (the paper) or ``"box"`` for tensor images.
        grad: θ-gradient estimator: ``"reynolds"`` (interior + boundary flux, no gradient
            of ``L`` needed) or ``"autograd"`` (reparameterised samples; needs a
            differentiable ``L``, so not ``"box"``).
        generator: random generator for the jitter (reproducibility).
        seed: instead of ``generator``, the seed of the jitter's draws (on θ's device); the
            boundary flux draws from ``seed + 1``. What ``torch.compile`` and ``torch.export``
            take (a generator object cannot enter a compiled graph).
        theta: use this θ instead of the layout's own (e.g. for ``gradcheck``).

    Returns:
        ``(N, h, w)``.
    """
    _check_radiance(image, radiance)
    check_choice(grad, ("reynolds", "autograd"), "grad")
    h, w = size = check_size(size)
    s = check_int(samples, "samples", 1)
    theta = layout.resolve_theta(theta)
    dtype = theta.dtype if not isinstance(image, Tensor) else torch.promote_types(theta.dtype, image.dtype)
    u = sample_points(size, s, jitter=True, generator=generator, seed=seed, dtype=dtype, device=theta.device)
    if grad == "autograd":
        if radiance == "box" and isinstance(image, Tensor):
            raise ValueError(
                "grad='autograd' needs a differentiable radiance; box radiance has zero "
                "spatial gradient almost everywhere: use grad='reynolds'"
            )
        th = theta.to(dtype)
    else:
        th = theta.detach().to(dtype)
    p = layout.phi(u, th)
    wdet = layout.phi_jacobian_det(u, th).abs()
    vals = _sample(image, p, radiance)  # (N, h*s, w*s)
    n = vals.shape[0]
    num = (vals * wdet.to(vals.dtype)).reshape(n, h, s, w, s).sum((2, 4))
    den = wdet.reshape(h, s, w, s).sum((1, 3)).to(vals.dtype)
    out = num / den
    if grad == "reynolds" and theta.requires_grad and theta.numel() > 0:
        vol = den * (4 / (h * w * s * s))  # Monte Carlo pixel areas, consistent with ``out``
        is_fn = callable(image) and not isinstance(image, Tensor)
        source, fn = (theta.new_empty(0), ops.object_token(image)) if is_fn else (image, "")
        edge_seed = ops.random_seed(generator, None if seed is None else seed + 1)
        args = (layout_token(layout), fn, h, w, s, radiance)
        out = torch.ops.layoutwarp.flux(out, theta, vol.detach(), source, edge_seed, *args)
    return out
