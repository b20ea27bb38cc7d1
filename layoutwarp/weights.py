"""A fixed layout's area weights, built: the share of every sensor pixel's area in every source cell.

The exact integrator (Green's theorem over the pixel polygons) of a fixed layout is linear in the
image, so it is a sparse matrix of area weights. [`fixed_runs`][] builds them as the
[`Runs`][layoutwarp.kernels.runs.Runs] the fixed layout's product reads, by a compiled walk over
each pixel's boundary where the fixed layout's kernels run (on a compiled mesh where that one
runs: [`COMPILED_MESH_PIXELS`][]), else from [`area_weights`][]: numpy's sparse matrix of the
same weights, block by block of sensor rows (the reference the tests hold the walk to). A build
that runs [`PROGRESS_AFTER_S`][] or longer shows a progress bar on a terminal.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
import torch
from tqdm import tqdm

from . import jit, kernels
from .checks import check_size
from .green import green_pieces
from .kernels.mesh import build_mesh, mesh_spec
from .kernels.runs import Runs
from .kernels.weights import ZERO
from .layouts import Layout
from .mesh import PixelMesh, pixel_mesh
from .tolerance import data_tolerance

if TYPE_CHECKING:
    import scipy.sparse

__all__ = ["COMPILED_MESH_PIXELS", "PIECES_PER_BLOCK", "PROGRESS_AFTER_S", "area_weights", "fixed_runs"]

#: Boundary pieces (segments cut at source cell lines) that [`area_weights`][] handles at once:
#: it works through blocks of sensor rows of about this many, so its temporaries stay bounded.
PIECES_PER_BLOCK = 1 << 14
#: A weights build that runs this long shows its progress and the time left on a terminal.
PROGRESS_AFTER_S = 2.0
#: A fixed layout's sensor of this many pixels or more builds its mesh compiled even where the mesh
#: unit is not in the disk cache yet: compiling it takes seconds, which the compiled mesh wins back
#: from here on (torch's takes a second or more). Below, the unit is used where it loads from the
#: cache (tens of milliseconds once the fixed unit is loaded), else torch's mesh.
COMPILED_MESH_PIXELS = 1 << 18


def fixed_runs(
    layout: Layout, size: tuple[int, int], src_size: tuple[int, int], tol: float, progress: bool | None = None
) -> tuple[Runs, torch.Tensor]:
    """The area weights of a fixed ``layout`` on an ``(h, w)`` sensor over ``(H, W)`` images as
    [`Runs`][layoutwarp.kernels.runs.Runs] (the polylines of curved edges within ``tol``, as
    [`area_weights`][]), and the pixels' areas ``(h, w)`` (float64, sensor units: the square
    ``[-1, 1]²``). Built by the compiled walk where the fixed layout's kernels run (for a sensor of
    [`COMPILED_MESH_PIXELS`][] or more, compiled first where they are not: numpy's build would
    take longer), else from [`area_weights`][]: the same runs, cut weights equal to float32
    rounding. ``progress``: the progress bar ([`PROGRESS_AFTER_S`][]) on or off (``None``: on a
    terminal)."""
    with torch.no_grad():  # the mesh the weights are built on, not kept: the weights and the
        # areas are all later calls need (a kept mesh is 0.5-0.8 copies of an RGB image)
        mesh = _fixed_mesh(layout, size, tol)
        areas = mesh.areas()
    (h, w), (hs, ws) = size, src_size
    cells = areas.flatten().cpu().numpy() * (hs * ws / 4)  # in source cells
    if not jit.ready("fixed", torch.float32, wait=h * w >= COMPILED_MESH_PIXELS):  # while they compile
        weights = area_weights(layout, size, src_size, tol=tol, mesh=mesh, progress=progress)
        return Runs.of(weights, cells, ws), areas
    with torch.no_grad():
        verts = mesh.pixel_vertices(src_size)
        area = mesh.areas(verts).flatten().cpu().numpy()
    parts = (t.cpu().numpy() for t in (verts, mesh.seg_start, mesh.seg_end, mesh.edge_offsets))
    nt = kernels.threads(hs * ws + 64 * h * w)  # a pixel's walk: its boundary's pieces and its box
    with _progress_bar(h, w, 2 * h, progress) as bar:  # two passes over the rows
        runs = kernels.build_runs(*parts, size, src_size, area, cells, nt, bar.update)
    return runs, areas


def _progress_bar(h: int, w: int, rows: int, progress: bool | None) -> tqdm:
    """The progress bar of an ``(h, w)`` sensor's weights build over ``rows`` rows, drawn on stderr
    once the build has run [`PROGRESS_AFTER_S`][], with the time left (``progress``: on, off, or
    ``None``: on a terminal)."""
    return tqdm(total=rows, desc=f"area weights {h}x{w}", unit="row", leave=False, delay=PROGRESS_AFTER_S,
                disable=None if progress is None else not progress)  # fmt: skip


def area_weights(
    layout: Layout,
    size: tuple[int, int],
    src_size: tuple[int, int],
    *,
    tol: float | None = None,
    dtype: torch.dtype | np.dtype | type = np.float32,
    weights_dtype: np.dtype | type = np.float64,
    mesh: PixelMesh | None = None,
    progress: bool | None = None,
) -> scipy.sparse.csr_matrix:
    """Exact area weights of every sensor pixel over the source cells, as a sparse matrix.

    ``W[k, r · W_src + c]`` is the fraction of pixel ``k``'s area (row-major sensor index)
    inside source cell ``(r, c)``; rows sum to 1, and ``W @ image.reshape(-1, C)`` equals
    ``simulate(image, layout, size, method="exact", tol=tol)`` up to rounding.

    Built from the same Green's-theorem pieces as the exact integrator: a boundary piece in
    cell ``(r, c)`` contributes ``ΔY · (Σ_{c' < c} L[r, c'] + f · L[r, c])``, a step in ``c'``;
    the steps of one pixel and row are summed by a sort and a cumulative sum, so only the
    cells inside the pixel get (non-zero) weights; ``nnz ≈`` source pixels plus the cells on
    pixel boundaries. Computed in float64, block by block of sensor rows
    ([`PIECES_PER_BLOCK`][]), each block's rows written in order: besides the result, what
    the build holds at once is one block's pieces. A build that runs `PROGRESS_AFTER_S` (2 s) or
    longer shows a progress bar with the time left, on a terminal (stderr).

    Args:
        layout: the pixel layout.
        size: sensor size ``(h, w)``.
        src_size: source size ``(H, W)``.
        tol: bound on each pixel's error relative to the images' value range, spent on the
            polyline approximation of curved edges; ``None``: what images of ``dtype`` resolve
            ([`data_tolerance`][]).
        dtype: the dtype of the images the weights are for (sets the default ``tol``).
        weights_dtype: the dtype of the returned weights (float64 or float32).
        mesh: the layout's float64 [`pixel_mesh`][] at ``tol``, where the
            caller has built it (default: the cached one, built on first use).
        progress: the progress bar on or off (``None``: on a terminal).

    Returns:
        a ``(h · w, H · W)`` ``scipy.sparse.csr_matrix``.
    """
    (h, w), (hs, ws) = check_size(size), check_size(src_size, "src_size")
    tol = data_tolerance(dtype)[0] if tol is None else tol
    with torch.no_grad():
        if mesh is None:
            mesh = pixel_mesh(layout, (h, w), tol=tol, dtype=torch.float64)
        verts = mesh.pixel_vertices((hs, ws))
        area = mesh.areas(verts).flatten().cpu().numpy()  # source pixel units, same polylines
        verts, starts, ends = verts.cpu(), mesh.seg_start.cpu(), mesh.seg_end.cpu()
        pieces = sum(  # a bound on the pieces, in chunks: no segment-long temporaries
            float(((verts[e] - verts[s]).abs().ceil().sum(-1) + 2).sum())
            for s, e in zip(starts.split(1 << 16), ends.split(1 << 16), strict=True)
        )
    top, off = mesh.topology, mesh.edge_offsets.cpu().numpy()
    seg_edge, pix = mesh.seg_edge.cpu(), top.edge_pixels()
    step = max(1, h // max(1, math.ceil(pieces / PIECES_PER_BLOCK)))
    # at most a cell per source pixel (inside one pixel) plus two per piece (the pixels on its
    # sides); np.empty takes address space only, so the bound's unused pages are never touched
    bound = hs * ws + 2 * int(pieces)
    index = np.int32 if bound < 2**31 else np.int64
    indices, data = np.empty(bound, index), np.empty(bound, weights_dtype)
    counts, n = [np.zeros(1, np.int64)], 0
    bar = _progress_bar(h, w, h, progress)
    for i0 in range(0, h, step):
        i1 = min(h, i0 + step)
        # the block's pixels are bounded by horizontal edges of corner rows i0..i1 and vertical
        # edges of rows i0..i1-1: two runs of edges, so two runs of segments
        runs = (top.horizontal(i0, 0), top.horizontal(i1 + 1, 0)), (top.vertical(i0, 0), top.vertical(i1, 0))
        segs = torch.cat([torch.arange(int(off[e0]), int(off[e1])) for e0, e1 in runs])
        with torch.no_grad():
            pcs = green_pieces(verts[starts[segs]], verts[ends[segs]], (hs, ws))
        edge = seg_edge[segs[pcs.seg]].numpy()
        pixel, cell, value = _block_weights(
            pix[edge], *(t.numpy() for t in (pcs.row, pcs.col, pcs.dy, pcs.frac)), (i0 * w, i1 * w), hs, ws
        )
        indices[n : n + cell.size] = cell
        data[n : n + cell.size] = value / area[pixel]
        n += cell.size
        counts.append(np.bincount(pixel - i0 * w, minlength=(i1 - i0) * w))
        bar.update(i1 - i0)
    bar.close()
    indices.resize(n, refcheck=False)  # shrunk in place: the pages past n go back
    data.resize(n, refcheck=False)
    indptr = np.cumsum(np.concatenate(counts)).astype(index)
    import scipy.sparse  # loaded on first use: `import layoutwarp` does not load scipy

    return scipy.sparse.csr_matrix((data, indices, indptr), shape=(h * w, hs * ws))


def _block_weights(
    pix: np.ndarray,
    row: np.ndarray,
    col: np.ndarray,
    dy: np.ndarray,
    frac: np.ndarray,
    pixels: tuple[int, int],
    hs: int,
    ws: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The weights' entries of the pixels ``[pixels[0], pixels[1])`` from the Green pieces of the
    edges bounding them (``pix``: each piece's edge's adding and subtracting pixel, ``(P, 2)``):
    pixel, source cell and unnormalised weight of every non-zero entry, sorted by pixel and cell
    (the order of a CSR matrix's rows)."""
    keys, cols, deltas = [], [], []
    for k, sign in ((0, 1.0), (1, -1.0)):
        p = pix[:, k]
        m = (p >= pixels[0]) & (p < pixels[1])  # the pixels of this block; -1 off the sensor
        v = sign * dy[m]
        key = p[m] * hs + row[m]
        keys += [key, key]
        cols += [col[m], col[m] + 1]
        deltas += [v * (frac[m] - 1), -v * frac[m]]
    key, c, delta = np.concatenate(keys), np.concatenate(cols), np.concatenate(deltas)
    order = np.lexsort((c, key))
    key, c, delta = key[order], c[order], delta[order]
    cum = np.cumsum(delta)
    start = np.flatnonzero(np.r_[True, key[1:] != key[:-1]])
    cum -= np.repeat(np.r_[0.0, cum[start[1:] - 1]], np.diff(np.r_[start, key.size]))  # per group
    last = np.r_[key[1:] != key[:-1], True]
    run = np.where(last, 0, np.r_[c[1:], 0] - c)  # cells from this step to the next
    scale = np.abs(delta).max(initial=1.0)
    live = (run > 0) & (np.abs(cum) > ZERO * scale)
    key, c, cum, run = key[live], c[live], cum[live], run[live]
    rep = np.repeat(np.arange(key.size), run)
    offs = np.arange(rep.size) - np.repeat(np.cumsum(run) - run, run)
    pixel, r = np.divmod(key[rep], hs)
    return pixel, r * ws + c[rep] + offs, cum[rep]


def _fixed_mesh(layout: Layout, size: tuple[int, int], tol: float) -> PixelMesh:
    """The float64 mesh a fixed layout's weights are built on: compiled ([`build_mesh`][]) for a
    family with a compiled map where the mesh unit is loaded or loads from the disk cache
    ([`jit.load`][]), or, for a sensor of [`COMPILED_MESH_PIXELS`][] or more, will have compiled
    ([`jit.ready`][]); else torch's [`pixel_mesh`][] (the same mesh to rounding), not kept."""
    spec = mesh_spec(layout)
    if spec is not None and (
        jit.load("mesh") or (size[0] * size[1] >= COMPILED_MESH_PIXELS and jit.ready("mesh"))
    ):
        theta = layout.theta_as(torch.float64).detach().cpu().numpy()
        return build_mesh(spec, size, theta, tol, with_grad=False).pixel_mesh()
    return pixel_mesh(layout, size, tol=tol, dtype=torch.float64, cache=False)
