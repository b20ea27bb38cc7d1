"""Pixel meshes: the polygons of a layout's pixels, with shared edges stored once.

A sensor of size ``(H, W)`` has ``(H + 1) × (W + 1)`` pixel corners; the uniform corner
``(i, j)`` (row ``i``, column ``j``) sits at ``x = (2j − W)/W``, ``y = (2i − H)/H`` and the
layout moves it to ``φ(corner)``. Pixel edges are the images of the uniform grid lines:
straight for rectangular layouts (one segment), curved for curvilinear ones (a polyline,
subdivided only as much as its curvature and the requested tolerance need).

Every pixel is bounded by four edges, and every interior edge is shared by two pixels with
opposite orientation; [`MeshTopology`][layoutwarp.topology.MeshTopology] numbers the edges once
for everyone, so a boundary integral is computed once per edge and pixel ``(i, j)`` collects
``E_top − E_bottom + E_right − E_left`` (positive orientation in ``(x, y)``).
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from typing import TypeVar

import numpy as np
import torch
from torch import Tensor

from .caches import LRU
from .checks import check_number, check_size
from .coords import sensor_to_pixels
from .layoutfile import layout_key
from .layouts import Layout
from .topology import MeshTopology

__all__ = [
    "BENDS",
    "MAX_SUBDIV",
    "MESHES",
    "SAMPLES",
    "PixelMesh",
    "pixel_mesh",
    "polygon_area",
    "segment_area",
    "smooth_pieces",
    "warn_if_capped",
]

_A = TypeVar("_A", Tensor, np.ndarray)


# ----------------------------------------------------------------------------------------
# Geometry helpers
# ----------------------------------------------------------------------------------------
def segment_area(a: _A, b: _A) -> _A:
    """The contribution ``∫ x dy`` of segments ``a → b`` (``(..., 2)``) to a polygon's area.

    Summed around a closed, positively oriented polygon (in ``(x, y)``; clockwise on screen,
    where ``y`` points down) it gives the area exactly. Works on tensors and arrays.
    """
    return (b[..., 1] - a[..., 1]) * (a[..., 0] + b[..., 0]) / 2


def polygon_area(poly: _A) -> _A:
    """Signed area of polygons ``(..., n, 2)`` (first vertex not repeated), by the shoelace sum.

    Examples:
        >>> float(polygon_area(np.array([[0.0, 0.0], [2.0, 0.0], [2.0, 1.0], [0.0, 1.0]])))
        2.0
    """
    n = poly.shape[-2]
    return segment_area(poly, poly[..., [*range(1, n), 0], :]).sum(-1)


def smooth_pieces(
    layout: Layout, a: Tensor, b: Tensor, extra: Tensor | None = None, theta: Tensor | None = None
) -> tuple[Tensor, Tensor, Tensor]:
    """Cut the uniform segments ``a → b`` (``(E, 2)``) where φ is not smooth along them.

    The cuts are [`Layout.edge_breakpoints`][layoutwarp.layouts.base.Layout.edge_breakpoints] for
    ``theta`` (e.g. the unit circle of
    φ_curv; differentiable where they move with θ) and any ``extra`` parameters ``(E, K)``
    (NaN for none); cuts within ``1e-6`` of an end are dropped.

    Returns:
        ``(edge, t0, t1)``: for every smooth piece, its segment and parameter range, in
        segment order.
    """
    ne = a.shape[0]
    brk = layout.edge_breakpoints(a, b, theta).to(a.dtype).reshape(ne, -1)
    if extra is not None:
        brk = torch.cat([brk, extra.to(a.dtype).reshape(ne, -1)], 1)
    keep = torch.isfinite(brk) & (brk > 1e-6) & (brk < 1 - 1e-6)
    brk = torch.where(keep, brk, torch.ones_like(brk))
    bounds = torch.cat([torch.zeros_like(a[:, :1]), brk, torch.ones_like(a[:, :1])], 1).sort(1).values
    edge, k = torch.nonzero(bounds[:, 1:].detach() - bounds[:, :-1].detach() > 1e-12, as_tuple=True)
    return edge, bounds[edge, k], bounds[edge, k + 1]


# ----------------------------------------------------------------------------------------
# Pixel mesh
# ----------------------------------------------------------------------------------------
@dataclass
class PixelMesh:
    """Polygonal pixel mesh of a sensor.

    Attributes:
        size: sensor size ``(H, W)``.
        vertices: ``(V, 2)`` polyline vertices in sensor coordinates; the first
            ``(H + 1)(W + 1)`` are the corners in row-major order. Differentiable in θ.
        seg_start, seg_end: ``(S,)`` vertex indices of each boundary segment, oriented along
            its edge (see [`MeshTopology`][layoutwarp.topology.MeshTopology]).
        seg_edge: ``(S,)`` edge index of each segment.
        edge_offsets: ``(E + 1,)`` start of each edge's (contiguous) segments.
    """

    size: tuple[int, int]
    vertices: Tensor
    seg_start: Tensor
    seg_end: Tensor
    seg_edge: Tensor
    edge_offsets: Tensor

    @property
    def topology(self) -> MeshTopology:
        return MeshTopology(self.size)

    @property
    def num_edges(self) -> int:
        return self.topology.num_edges

    @property
    def corners(self) -> Tensor:
        """Deformed corners, ``(H + 1, W + 1, 2)``."""
        h, w = self.size
        return self.vertices[: (h + 1) * (w + 1)].view(h + 1, w + 1, 2)

    @property
    def num_segments(self) -> int:
        return int(self.seg_start.numel())

    def sum_over_edges(self, seg_values: Tensor) -> Tensor:
        """Sum per-segment values ``(..., S)`` into per-edge values ``(..., E)``."""
        out = seg_values.new_zeros(*seg_values.shape[:-1], self.num_edges)
        return out.index_add(-1, self.seg_edge, seg_values)

    def combine_edges(self, edge_values: Tensor) -> Tensor:
        """Pixel boundary integrals ``(..., H, W)`` from oriented edge integrals ``(..., E)``."""
        return self.topology.combine(edge_values)

    def pixel_vertices(self, src_size: tuple[int, int]) -> Tensor:
        """The vertices in pixel units of an ``(H, W)`` source image, clamped to it (differentiable)."""
        hs, ws = src_size
        v = sensor_to_pixels(self.vertices.double(), (hs, ws))
        return torch.stack([v[:, 0].clamp(0, ws), v[:, 1].clamp(0, hs)], -1)

    def areas(self, vertices: Tensor | None = None) -> Tensor:
        """Polygon area of every pixel, ``(H, W)`` (in sensor units they sum to 4).

        ``vertices`` replaces the mesh's own (same topology, other units), e.g.
        [`pixel_vertices`][]. The mesh's own areas are computed once where its vertices need
        no gradient (a fixed layout's cached mesh serves every call).
        """
        fixed = vertices is None and not self.vertices.requires_grad
        if fixed and "_areas" in self.__dict__:
            return self.__dict__["_areas"]
        v = self.vertices if vertices is None else vertices
        out = self.combine_edges(self.sum_over_edges(segment_area(v[self.seg_start], v[self.seg_end])))
        if fixed:
            self.__dict__["_areas"] = out
        return out

    def edge_vertices(self, e: int) -> Tensor:
        """Ordered polyline vertices ``(n + 1, 2)`` of edge ``e``."""
        lo, hi = int(self.edge_offsets[e]), int(self.edge_offsets[e + 1])
        idx = torch.cat([self.seg_start[lo:hi], self.seg_end[hi - 1 : hi]])
        return self.vertices[idx]

    def edge_polylines(self, vertices: Tensor | None = None) -> list[np.ndarray]:
        """Every edge's ordered polyline as a float64 ``(n + 1, 2)`` array, in edge order.

        ``vertices`` replaces the mesh's own (same topology, other units, e.g. micrometres).
        """
        v = (self.vertices if vertices is None else vertices).detach().double().cpu().numpy()
        start, end = self.seg_start.cpu().numpy(), self.seg_end.cpu().numpy()
        off = self.edge_offsets.cpu().numpy()
        return [v[np.append(start[off[e] : off[e + 1]], end[off[e + 1] - 1])] for e in range(len(off) - 1)]

    def polygons(self) -> list[np.ndarray]:
        """Every pixel's closed polygon as a float64 ``(n, 2)`` array, row-major order.

        Vertices run top edge (+x), right edge (+y), bottom edge (−x), left edge (−y): positive
        orientation in ``(x, y)`` (clockwise on screen, where y points down); the first vertex
        is not repeated at the end.
        """
        verts = self.vertices.detach().double().cpu().numpy()
        start = self.seg_start.cpu().numpy()
        end = self.seg_end.cpu().numpy()
        off = self.edge_offsets.cpu().numpy()

        def chain(e: int) -> np.ndarray:  # vertex indices of edge e without its last vertex
            return start[off[e] : off[e + 1]]

        def backwards(e: int) -> np.ndarray:  # edge e reversed, without its first vertex
            return np.append(chain(e)[1:], end[off[e + 1] - 1])[::-1]

        polys = []
        for top, right, bottom, left in self.topology.pixel_edges().reshape(-1, 4):
            idx = np.concatenate([chain(top), chain(right), backwards(bottom), backwards(left)])
            polys.append(verts[idx])
        return polys

    def subdivisions(self) -> Tensor:
        """Number of segments of every edge, ``(E,)``."""
        return self.edge_offsets.diff()


def _edge_parameters(
    layout: Layout, size: tuple[int, int], theta: Tensor, tol: float, max_subdiv: int, with_grad: bool
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Polyline parameters of every edge so that pixel values stay within ``tol``.

    Each uniform edge is first cut where φ is not smooth along it ([`smooth_pieces`][]), so that a
    polyline vertex sits on every kink. A smooth piece with chord ``ℓ`` and sagitta ``e`` cut into
    ``n`` equal parameter steps deviates by about ``e / n²`` from the curve and changes the area
    next to it by at most ``(2/3) ℓ e / n²``. Giving each of a pixel's four edges a quarter of the
    budget ``tol · A`` (``A`` the smaller adjacent pixel area: of each pixel, the smaller of its
    corner quad's area and its sampled polygon's, which a pixel that bends far inside its corners
    needs), shared along the edge in proportion to length, bounds every pixel's value error by
    ``tol`` times the radiance range. The sagitta is bounded by ``max |φ''⊥| / 8``, across the
    edge's own direction at each sample (a piece that turns bends across its chord only in part),
    from second differences at the 13 [`SAMPLES`][] of each piece, graded towards its ends: φ bends
    hardest where a piece meets the unit circle or the sensor's border (θ near ±1 puts nearly all of
    an edge's bend into its last thousandth), and an S-shaped piece has no sagitta at its middle.
    Straight edges get exactly one segment. With ``with_grad``, the parameter velocity ``∂φ/∂θ``
    along each edge, sampled at the 11 inner samples (it may jump at a kink, a piece's end), is held
    to the same bound, so that θ-gradients are as accurate as values where the image changes
    little from one source pixel to the next (docs/integrators.md: an image that jumps at every
    cell line the edge crosses moves its gradient beyond ``tol``, the more so the more cells the
    edge crosses).

    Returns:
        ``(edge, lo, hi, n)``: the smooth pieces (their edge and parameter range, ordered by
        edge and parameter; differentiable in θ with ``with_grad``) and the segments of each,
        ``(pieces,)``.
    """
    th = theta.detach().double()
    topo = MeshTopology(size)
    ua, ub = topo.edge_ends(device=th.device)
    edge, lo_g, hi_g = smooth_pieces(layout, ua, ub, theta=theta if with_grad else th)
    with torch.no_grad():  # the counts need no gradient (only the vertices do)
        n = _segment_counts(layout, topo, th, edge, lo_g, hi_g, tol, max_subdiv, with_grad)
    return edge, lo_g, hi_g, n


def _segment_counts(
    layout: Layout,
    topo: MeshTopology,
    th: Tensor,
    edge: Tensor,
    lo: Tensor,
    hi: Tensor,
    tol: float,
    max_subdiv: int,
    with_grad: bool,
) -> Tensor:
    """The count stage of `_edge_parameters` (its caller runs it under ``no_grad``):
    segments per smooth piece, ``(pieces,)``."""
    h, w = topo.size
    dev = th.device
    ua, ub = topo.edge_ends(device=dev)
    cd = layout.phi(topo.corners(device=dev), th).view(h + 1, w + 1, 2)
    quads = torch.stack([cd[:-1, :-1], cd[:-1, 1:], cd[1:, 1:], cd[1:, :-1]], -2)
    area = polygon_area(quads).abs()  # (H, W)
    a0, d = ua[edge], (ub - ua)[edge]
    s_t = torch.tensor(SAMPLES, dtype=ua.dtype, device=dev)
    step = max(1, PHI_CHUNK // len(SAMPLES))  # pieces per chunk: φ's temporaries stay chunk-sized
    chunks = [
        _chord_and_sagitta(layout, th, a0[sl], d[sl], lo[sl], hi[sl], s_t, with_grad)
        for sl in (slice(i, i + step) for i in range(0, max(len(edge), 1), step))
    ]
    length, sag, swept = (torch.cat(parts) for parts in zip(*chunks, strict=True))
    ne = topo.num_edges
    # a pixel's area: the smaller of its corner quad's and its samples' polygon's (a pixel may
    # bend far inside its corners: an elliptic strip at θ near -1 keeps 0.09x of its quad)
    sampled = topo.combine(torch.zeros(ne, dtype=ua.dtype, device=dev).index_add_(0, edge, swept))
    area = torch.minimum(area, sampled.abs())
    inf = torch.full((1, w), math.inf, dtype=area.dtype, device=dev)
    area_h = torch.minimum(torch.cat([inf, area]), torch.cat([area, inf]))  # (H+1, W)
    inf = torch.full((h, 1), math.inf, dtype=area.dtype, device=dev)
    area_v = torch.minimum(torch.cat([inf, area], 1), torch.cat([area, inf], 1))  # (H, W+1)
    amin = torch.cat([area_h.flatten(), area_v.flatten()])
    edge_len = torch.zeros(ne, dtype=ua.dtype, device=dev).index_add_(0, edge, length)
    budget = 3 * tol * amin[edge] / (8 * edge_len[edge].clamp_min(1e-300))
    n = torch.sqrt(2 * sag / budget).ceil().clamp(1, max_subdiv)
    n = torch.where(sag <= 1e-15 * length, torch.ones_like(n), n).long()
    warn_if_capped(int(n.max()) if n.numel() else 0, max_subdiv)
    return n


def warn_if_capped(most: int, max_subdiv: int) -> None:
    """Warn (a ``RuntimeWarning``, once per process at the default filter) where the most
    segments a smooth piece got, ``most``, reached the cap ``max_subdiv``: its polyline may then
    err by more than the tolerance (the count stages of torch and of the compiled CPU mesh call
    it at once; a CUDA mesh's room, from the cap its kernel wrote to its status, at the next
    step)."""
    if most >= max_subdiv:
        warnings.warn(
            f"pixel mesh: a smooth piece of an edge reached max_subdiv={max_subdiv} segments, so its "
            "polyline may err by more than tol (a fine tol with θ near ±1): raise max_subdiv "
            "(lw.pixel_mesh) or pass a coarser tol",
            RuntimeWarning,
            stacklevel=2,
        )


def _chord_and_sagitta(
    layout: Layout, th: Tensor, a0: Tensor, d: Tensor, lo: Tensor, hi: Tensor, s_t: Tensor, with_grad: bool
) -> tuple[Tensor, Tensor, Tensor]:
    """Chord length, sagitta bound and swept area of smooth pieces ``a0 + [lo, hi] · d`` of
    uniform edges under φ: the bound from second differences at the parameters ``lo + (hi − lo) ·
    s_t`` ([`SAMPLES`][]) and, with ``with_grad``, of ``∂φ/∂θ`` at the inner ones, each across the
    edge's own direction there (a piece that turns bends across its chord only in part), see
    `_edge_parameters`; the area ``∫ x dy`` ([`segment_area`][]) along the polyline of those
    samples, from which the count stage has each pixel's area."""
    pts = a0[:, None] + (lo[:, None] + (hi - lo)[:, None] * s_t)[..., None] * d[:, None]  # (pieces, K, 2)
    pts = pts.transpose(0, 1)  # (K, pieces, 2)
    f = layout.phi(pts, th)
    chord = f[-1] - f[0]
    length = torch.sqrt(chord[:, 0] ** 2 + chord[:, 1] ** 2)
    tangent = f[2:] - f[:-2]  # (K-2, pieces, 2): the direction at each inner sample
    span = torch.sqrt(tangent[..., 0] ** 2 + tangent[..., 1] ** 2).clamp_min(1e-300)
    tx, ty = tangent[..., 0] / span, tangent[..., 1] / span
    d2 = _second_differences(f, slice(None))
    sag = (tx * d2[..., 1] - ty * d2[..., 0]).abs().amax(0) / 8
    if with_grad and th.numel():
        # the θ-gradient moves each edge by ∂φ/∂θ, which bends it even where φ does not
        # (e.g. at θ = 0): bound the curvature of that field the same way. ∂φ/∂θ may jump at
        # a piece's ends (a kink that moves with θ): the inner samples only.
        v = layout.phi_dtheta(pts[1:-1], th)  # (K-2, pieces, 2, P)
        d2 = _second_differences(v, slice(1, -1))  # (K-4, pieces, 2, P)
        normal = (tx[1:-1, :, None] * d2[..., 1, :] - ty[1:-1, :, None] * d2[..., 0, :]).abs()
        sag = torch.maximum(sag, normal.amax(0).amax(-1) / 8)
    swept = segment_area(f[0], f[1])  # ∫ x dy along the samples' polyline, summed in order
    for k in range(1, len(s_t) - 1):
        swept = swept + segment_area(f[k], f[k + 1])
    return length, sag, swept


def _second_differences(f: Tensor, inner: slice) -> Tensor:
    """``f''`` at the inner samples ``inner`` of [`SAMPLES`][] from the values ``f`` ``(K, ...)`` at
    those and one on either side, by [`BENDS`][] (the compiled count stage computes it alike)."""
    up, down = (torch.tensor(w, dtype=f.dtype, device=f.device)[inner] for w in zip(*BENDS, strict=True))
    shape = (-1,) + (1,) * (f.dim() - 1)
    return (f[2:] - f[1:-1]) * up.view(shape) - (f[1:-1] - f[:-2]) * down.view(shape)


SAMPLES = (
    0.0, 2.0**-11, 2.0**-7, 2.0**-3, 0.25, 0.375, 0.5,
    0.625, 0.75, 1 - 2.0**-3, 1 - 2.0**-7, 1 - 2.0**-11, 1.0,
)  # fmt: skip
"""Where the count stage samples a smooth piece, as fractions of it: its eighths from 1/4 to 3/4
(a bend at a strip's centre, near θ = -1, lies between quarters), and graded by 16 towards both
ends, where φ bends hardest; exact in binary. They keep every pixel within the tolerance on the
hard cases of ``tests/test_mesh.py`` (θ of either sign up to ±0.97, against polylines of 4096
segments) and on its strips, up to ±0.99; equal steps along a piece do not resolve every bend
held by one end or one point nearer ±1."""

BENDS = tuple(
    (2 / (h1 + h2) / h2, 2 / (h1 + h2) / h1)
    for h1, h2 in (
        (SAMPLES[s] - SAMPLES[s - 1], SAMPLES[s + 1] - SAMPLES[s]) for s in range(1, len(SAMPLES) - 1)
    )
)
"""The second difference at inner sample ``s`` of [`SAMPLES`][] (of three unequally spaced values):
``(f[s + 1] − f[s]) · BENDS[s − 1][0] − (f[s] − f[s − 1]) · BENDS[s − 1][1]``, the weights
``2 / ((h₋ + h₊) h₊)`` and ``2 / ((h₋ + h₊) h₋)`` of its steps ``h₋``, ``h₊``."""

#: The most segments a smooth piece of an edge is cut into by default (``max_subdiv``): a
#: learnable 4x4 or strip layout near θ = ±1 asks up to about 13 000 at the integrators' default
#: tolerance for float images (2⁻¹²), and 4096 let its θ-gradient err by 2.5x ``tol`` there (8x at
#: 1e-4; tests/test_mesh.py). At 1e-5 (``pixel_mesh``'s own default) such strips ask for more,
#: and the cap binds for their values too.
MAX_SUBDIV = 1 << 14

#: Segments per chunk when the mesh's vertices are mapped (bounds φ's temporaries and its input).
PHI_CHUNK = 1 << 16

MESHES: LRU[PixelMesh] = LRU("meshes", 4)
"""Meshes of fixed layouts of registered families, the last four used (see [`pixel_mesh`][] and
[`layoutwarp.caches`][])."""


def _cache_key(layout: Layout, size, tol, max_subdiv, dtype, theta: Tensor) -> tuple | None:
    """A key that identifies the mesh, or ``None`` where caching is unsafe: θ needs a gradient,
    or the layout is not a registered family (whose ``to_config`` holds all its state)."""
    identity = None if theta.requires_grad else layout_key(layout)
    if identity is None:
        return None
    values = tuple(theta.detach().double().cpu().tolist())
    return (identity, values, size, tol, max_subdiv, dtype, theta.device)


def pixel_mesh(
    layout: Layout,
    size: tuple[int, int],
    *,
    tol: float | None = 1e-5,
    max_subdiv: int = MAX_SUBDIV,
    subdivisions: Tensor | int | None = None,
    dtype: torch.dtype | None = None,
    theta: Tensor | None = None,
    cache: bool = True,
) -> PixelMesh:
    """Build the pixel polygon mesh of ``layout`` for a sensor of ``size = (H, W)``.

    Args:
        layout: the pixel layout (its θ is used with autograd, so the mesh vertices are
            differentiable in θ).
        size: sensor size ``(H, W)``.
        tol: what the polylines of curved edges may cost an integral over the pixels: the
            bound on every pixel's box-radiance mean, relative to the image's value range (a
            unitless fraction: the area between polyline and curve, over the pixel's area, is at
            most ``tol``), and on the polylines' error in ``∂φ/∂θ`` when θ requires grad (see
            `_edge_parameters`). The default ``1e-5`` is a geometric reference; the
            integrators pass what the data needs
            ([`data_tolerance`][layoutwarp.tolerance.data_tolerance]). ``None``:
            one segment per edge. Ignored for straight-edged layouts, which always use one
            segment per straight piece (between the cuts of
            [`Layout.edge_breakpoints`][layoutwarp.layouts.base.Layout.edge_breakpoints]).
        max_subdiv: cap on segments per smooth piece of an edge (``MAX_SUBDIV``). Where the
            cap binds (very fine ``tol`` with long, strongly curved edges: few large pixels, θ
            near ±1) the error can exceed ``tol``; raise it for such references.
        subdivisions: force the segment counts instead of the adaptive choice, with a vertex on
            every kink: an int for every smooth piece, an ``(E,)`` tensor per edge (for each of
            its pieces), or a ``(pieces,)`` tensor per smooth piece in the order of
            [`smooth_pieces`][] (e.g.
            ``layoutwarp.export.distance_subdivisions``). Used for references
            (smooth in θ, for finite differences) and fabrication masks.
        dtype: vertex dtype (default: θ's dtype).
        theta: use this θ instead of the layout's own (see
            [`Layout.resolve_theta`][layoutwarp.layouts.base.Layout.resolve_theta]).
        cache: ``False``: a mesh this call builds is not kept (a kept one is still returned):
            for a caller that keeps what it derives from the mesh instead.

    Returns:
        a [`PixelMesh`][] on θ's device. The meshes of fixed layouts (θ without gradient)
        of registered families are cached ([`MESHES`][]), so simulating many
        images with one fixed layout builds its mesh once; do not modify a returned mesh.

    Examples:
        >>> from layoutwarp import CurvLayout
        >>> mesh = pixel_mesh(CurvLayout((0.5, 0.2)), (3, 4), tol=1e-4, dtype=torch.float64)
        >>> round(float(mesh.areas().sum()), 12)
        4.0
    """
    h, w = check_size(size)
    if theta is None and dtype is not None:  # a fixed layout's exact θ where the mesh is the finer
        theta = layout.theta_as(torch.promote_types(dtype, layout.dtype))
    theta = layout.resolve_theta(theta)
    dtype = dtype or theta.dtype
    key = None if subdivisions is not None else _cache_key(layout, (h, w), tol, max_subdiv, dtype, theta)

    def build() -> PixelMesh:
        mesh = _build_mesh(layout, (h, w), theta, tol, max_subdiv, subdivisions, dtype)
        if torch.finfo(dtype).bits < 64:  # a valid layout whose pixels the dtype cannot hold: refused
            _check_resolved(mesh, dtype)
        return mesh

    return build() if key is None else MESHES.get(key, build, keep=cache)


def _check_resolved(mesh: PixelMesh, dtype: torch.dtype) -> None:
    """Refuse, in one line, a mesh whose vertices ``dtype`` rounds into pixels of no positive
    area (θ near ±1 makes the border pixels narrower than float32 resolves)."""
    areas = mesh.areas().detach()
    if bool((areas <= 0).any()):
        n, name = int((areas <= 0).sum()), str(dtype).removeprefix("torch.")
        raise ValueError(
            f"pixel_mesh: {n} pixels of this layout are narrower than {name} resolves (smallest "
            f"area {float(areas.min()):.3g}): make the mesh in float64 (dtype=torch.float64)"
        )


def _build_mesh(
    layout: Layout,
    size: tuple[int, int],
    theta: Tensor,
    tol: float | None,
    max_subdiv: int,
    subdivisions: Tensor | int | None,
    dtype: torch.dtype,
) -> PixelMesh:
    h, w = size
    device = theta.device
    topo = MeshTopology((h, w))
    ne = topo.num_edges
    ends = topo.edge_ends(device=device)
    if subdivisions is not None:  # equal parameter steps on every smooth piece
        edge, lo, hi = smooth_pieces(layout, *ends, theta=theta)
        m = torch.as_tensor(subdivisions, dtype=torch.long, device=device)
        if m.ndim == 0 or m.numel() == ne:
            m = m.expand(ne)[edge]
        elif m.numel() != edge.numel():
            raise ValueError(
                f"subdivisions must be an int, one count per edge ({ne}) or per smooth piece "
                f"({edge.numel()}), got {m.numel()} values"
            )
        if bool((m < 1).any()):
            raise ValueError(f"subdivisions must be >= 1, got {subdivisions!r}")
    elif layout.straight_edges:  # one segment per straight piece
        edge, lo, hi = smooth_pieces(layout, *ends, theta=theta)
        m = torch.ones_like(edge)
    elif tol is None:  # one segment per edge
        edge, lo, hi = torch.arange(ne, device=device), ends[0].new_zeros(ne), ends[0].new_ones(ne)
        m = torch.ones_like(edge)
    else:
        tol = check_number(tol, "tol", 0, lo_open=True)
        with_grad = torch.is_grad_enabled() and theta.requires_grad
        edge, lo, hi, m = _edge_parameters(layout, (h, w), theta, tol, max_subdiv, with_grad)
    # segments: piece p holds m[p] equal parameter steps of [lo[p], hi[p]]; the pieces of an
    # edge are contiguous and in order, so its segments are too
    offsets = torch.zeros(ne + 1, dtype=torch.long, device=device)
    offsets[1:] = torch.cumsum(torch.zeros(ne, dtype=torch.long, device=device).index_add_(0, edge, m), 0)
    nseg = int(offsets[-1])
    seg_edge = torch.repeat_interleave(edge, m)
    # every segment but an edge's first starts at a new (interior) vertex, numbered after the
    # corners in segment order: segment s's is ncorner + (interior segments up to s) − 1
    ncorner = (h + 1) * (w + 1)
    ea, eb = topo.edge_corners(device)
    interior = torch.ones(nseg, dtype=torch.bool, device=device)
    interior[offsets[:-1]] = False
    last = torch.zeros(nseg, dtype=torch.bool, device=device)
    last[offsets[1:] - 1] = True
    after = ncorner + torch.cumsum(interior, 0)
    seg_start = torch.where(interior, after - 1, ea[seg_edge])
    seg_end = torch.where(last, eb[seg_edge], after)
    del after, last
    # the interior vertices chunk by chunk of segments: their parameters, the points and φ's
    # temporaries stay chunk-sized
    cu = topo.corners(dtype, device)
    th = theta.to(dtype)
    piece_end, span = torch.cumsum(m, 0), hi - lo
    verts = [layout.phi(cu, th)]
    for s0 in range(0, nseg, PHI_CHUNK):
        s = torch.arange(s0, min(nseg, s0 + PHI_CHUNK), device=device)[interior[s0 : s0 + PHI_CHUNK]]
        p = torch.searchsorted(piece_end, s, right=True)  # the piece of each segment
        k = s - (piece_end[p] - m[p])  # its step within the piece
        t = (lo[p] + span[p] * (k.to(lo.dtype) / m[p].to(lo.dtype))).to(dtype)
        ua, ub = cu[ea[edge[p]]], cu[eb[edge[p]]]
        verts.append(layout.phi(ua + t[:, None] * (ub - ua), th))
    verts = torch.cat(verts)
    return PixelMesh(
        size=(h, w),
        vertices=verts,
        seg_start=seg_start,
        seg_end=seg_end,
        seg_edge=seg_edge,
        edge_offsets=offsets,
    )
