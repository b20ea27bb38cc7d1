"""Pixel meshes and dense remap maps of a layout.

A sensor of size ``(H, W)`` has ``(H + 1) × (W + 1)`` pixel corners; the uniform corner
``(i, j)`` (row ``i``, column ``j``) sits at ``x = (2j − W)/W``, ``y = (2i − H)/H`` and the
layout moves it to ``φ(corner)``. Pixel edges are the images of the uniform grid lines:
straight for rectangular layouts (one segment), curved for curvilinear ones (a polyline,
subdivided only as much as its curvature and the requested tolerance need).

Every pixel is bounded by four edges, and every interior edge is shared by two pixels
with opposite orientation; :class:`PixelMesh` keeps each edge once, so a boundary integral
``E_e`` is computed once per edge and pixel ``(i, j)`` collects
``E_h[i, j] − E_h[i + 1, j] + E_v[i, j + 1] − E_v[i, j]`` (top, bottom, right, left; positive
orientation in ``(x, y)``).

Dense maps follow OpenCV's ``remap`` convention: float32 ``map_x``, ``map_y`` in source pixel
units with pixel centres at integers, i.e. ``X = (x + 1) · W_src / 2 − 0.5``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

from .layouts import Layout

__all__ = [
    "Maps",
    "PixelMesh",
    "check_size",
    "combine_edges",
    "edge_ends",
    "forward_maps",
    "inverse_maps",
    "pixel_centers",
    "pixel_mesh",
    "pixels_to_sensor",
    "sample_points",
    "sensor_to_pixels",
    "uniform_corners",
]


def check_size(size, name: str = "size") -> tuple[int, int]:
    """Validate an ``(H, W)`` size and return it as a tuple of two positive ints."""
    try:
        h, w = (int(v) for v in size)
        ok = all(float(v) == int(v) for v in size)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a pair (H, W) of positive integers, got {size!r}") from None
    if not ok or h <= 0 or w <= 0:
        raise ValueError(f"{name} must be a pair (H, W) of positive integers, got {size!r}")
    return h, w


def grid_lines(n: int, dtype: torch.dtype, device=None) -> Tensor:
    """The ``n + 1`` uniform cell boundaries ``(2k − n)/n`` of ``[-1, 1]`` (exactly ±1 at the ends)."""
    k = torch.arange(n + 1, dtype=dtype, device=device)
    return (2 * k - n) / n


def uniform_corners(size: tuple[int, int], dtype: torch.dtype = torch.float64, device=None) -> Tensor:
    """Uniform pixel corners, shape ``(H + 1, W + 1, 2)`` holding ``(x, y)``."""
    h, w = check_size(size)
    ys, xs = grid_lines(h, dtype, device), grid_lines(w, dtype, device)
    return torch.stack(torch.meshgrid(xs, ys, indexing="xy"), -1)


def edge_ends(size: tuple[int, int], dtype: torch.dtype = torch.float64) -> tuple[Tensor, Tensor]:
    """Uniform end points ``(a, b)``, each ``(E, 2)``, of every pixel edge in :class:`PixelMesh`
    order: horizontal edges (row-major, running +x), then vertical ones (running +y)."""
    cu = uniform_corners(size, dtype)
    a = torch.cat([cu[:, :-1].reshape(-1, 2), cu[:-1, :].reshape(-1, 2)])
    b = torch.cat([cu[:, 1:].reshape(-1, 2), cu[1:, :].reshape(-1, 2)])
    return a, b


def pixel_centers(size: tuple[int, int], dtype: torch.dtype = torch.float64, device=None) -> Tensor:
    """Uniform pixel centres, shape ``(H, W, 2)`` holding ``(x, y)``."""
    h, w = check_size(size)
    xs = (2 * torch.arange(w, dtype=dtype, device=device) + 1 - w) / w
    ys = (2 * torch.arange(h, dtype=dtype, device=device) + 1 - h) / h
    return torch.stack(torch.meshgrid(xs, ys, indexing="xy"), -1)


def sensor_to_pixels(p: Tensor, size: tuple[int, int]) -> Tensor:
    """Sensor coordinates ``(x, y)`` to continuous pixel coordinates of an ``(H, W)`` image.

    Pixel ``c`` covers ``[c, c + 1)``: ``X = (x + 1) · W / 2``, ``Y = (y + 1) · H / 2``.
    """
    h, w = size
    scale = torch.tensor([w / 2, h / 2], dtype=p.dtype, device=p.device)
    return (p + 1) * scale


def pixels_to_sensor(p: Tensor, size: tuple[int, int]) -> Tensor:
    """Inverse of :func:`sensor_to_pixels`."""
    h, w = size
    scale = torch.tensor([2 / w, 2 / h], dtype=p.dtype, device=p.device)
    return p * scale - 1


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
            its edge (horizontal edges run in +x, vertical edges in +y in uniform space).
        seg_edge: ``(S,)`` edge index of each segment: horizontal edge ``(i, j)`` (corner
            row ``i``, ``0 <= i <= H``; column ``j < W``) is ``i · W + j``, vertical edge
            ``(i, j)`` (``i < H``, ``0 <= j <= W``) is ``(H + 1) W + i (W + 1) + j``.
        edge_offsets: ``(E + 1,)`` start of each edge's (contiguous) segments.
    """

    size: tuple[int, int]
    vertices: Tensor
    seg_start: Tensor
    seg_end: Tensor
    seg_edge: Tensor
    edge_offsets: Tensor

    @property
    def num_edges(self) -> int:
        h, w = self.size
        return (h + 1) * w + h * (w + 1)

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
        return combine_edges(edge_values, self.size)

    def areas(self) -> Tensor:
        """Polygon area of every pixel, ``(H, W)``, in sensor units (they sum to 4)."""
        a, b = self.vertices[self.seg_start], self.vertices[self.seg_end]
        seg = (b[:, 1] - a[:, 1]) * (a[:, 0] + b[:, 0]) / 2  # ∮ x dy, exact for a polyline
        return self.combine_edges(self.sum_over_edges(seg))

    def edge_vertices(self, e: int) -> Tensor:
        """Ordered polyline vertices ``(n + 1, 2)`` of edge ``e``."""
        lo, hi = int(self.edge_offsets[e]), int(self.edge_offsets[e + 1])
        idx = torch.cat([self.seg_start[lo:hi], self.seg_end[hi - 1 : hi]])
        return self.vertices[idx]

    def polygons(self) -> list[np.ndarray]:
        """Every pixel's closed polygon as a float64 ``(n, 2)`` array, row-major order.

        Vertices run top edge (+x), right edge (+y), bottom edge (−x), left edge (−y): positive
        orientation in ``(x, y)`` (clockwise on screen, where y points down); the first vertex
        is not repeated at the end.
        """
        h, w = self.size
        nh = (h + 1) * w
        verts = self.vertices.detach().double().cpu().numpy()
        start = self.seg_start.cpu().numpy()
        end = self.seg_end.cpu().numpy()
        off = self.edge_offsets.cpu().numpy()

        def chain(e: int) -> np.ndarray:  # vertex indices of edge e without its last vertex
            return start[off[e] : off[e + 1]]

        def last(e: int) -> int:
            return int(end[off[e + 1] - 1])

        polys = []
        for i in range(h):
            for j in range(w):
                top, bottom = i * w + j, (i + 1) * w + j
                left, right = nh + i * (w + 1) + j, nh + i * (w + 1) + j + 1
                idx = np.concatenate(
                    [
                        chain(top),
                        chain(right),
                        np.append(chain(bottom)[1:], last(bottom))[::-1],
                        np.append(chain(left)[1:], last(left))[::-1],
                    ]
                )
                polys.append(verts[idx])
        return polys

    def subdivisions(self) -> Tensor:
        """Number of segments of every edge, ``(E,)``."""
        return self.edge_offsets.diff()


def combine_edges(edge_values: Tensor, size: tuple[int, int]) -> Tensor:
    """Pixel boundary integrals ``(..., H, W)`` from oriented edge integrals ``(..., E)``.

    Edges are ordered as in :class:`PixelMesh`; pixel ``(i, j)`` gets
    ``E_h[i, j] − E_h[i + 1, j] + E_v[i, j + 1] − E_v[i, j]``.
    """
    h, w = size
    nh = (h + 1) * w
    eh = edge_values[..., :nh].unflatten(-1, (h + 1, w))
    ev = edge_values[..., nh:].unflatten(-1, (h, w + 1))
    return (eh[..., :-1, :] - eh[..., 1:, :]) + (ev[..., :, 1:] - ev[..., :, :-1])


def _shoelace(poly: Tensor) -> Tensor:
    x, y = poly[..., 0], poly[..., 1]
    return 0.5 * (x * y.roll(-1, -1) - x.roll(-1, -1) * y).sum(-1)


def _edge_parameters(
    layout: Layout, size: tuple[int, int], tol: float, max_subdiv: int, with_grad: bool = False
) -> tuple[Tensor, Tensor]:
    """Polyline parameters of every edge so that pixel values stay within ``tol``.

    Each uniform edge ``a → b`` is first cut where φ is not smooth along it
    (:meth:`Layout.edge_breakpoints`, e.g. the unit circle of φ_curv), so that a polyline
    vertex sits on every kink. A smooth piece with chord ``ℓ`` and sagitta ``e`` cut into
    ``n`` equal parameter steps deviates by about ``e / n²`` from the curve and changes the
    area next to it by at most ``(2/3) ℓ e / n²``. Giving each of a pixel's four edges a
    quarter of the budget ``tol · A`` (``A`` the smaller adjacent pixel area), shared along
    the edge in proportion to length, bounds every pixel's value error by ``tol`` times the
    radiance range. Sagittas are measured perpendicular to the chord at the middle of each
    piece (with a safety factor 2), so straight edges get exactly one segment. With
    ``with_grad``, the parameter velocity ``∂φ/∂θ`` along each edge is held to the same
    bound, so that θ-gradients are as accurate as values.

    Returns:
        ``(n, t)``: segments per edge ``(E,)`` and the parameter in ``[0, 1)`` of every
        segment's start vertex ``(S,)``, edge by edge.
    """
    h, w = size
    th = layout.theta.detach().double()
    cu = uniform_corners(size)
    cd = layout.phi(cu, th)
    quads = torch.stack([cd[:-1, :-1], cd[:-1, 1:], cd[1:, 1:], cd[1:, :-1]], -2)
    area = _shoelace(quads).abs()  # (H, W)
    inf = torch.full((1, w), math.inf, dtype=area.dtype)
    area_h = torch.minimum(torch.cat([inf, area]), torch.cat([area, inf]))  # (H+1, W)
    inf = torch.full((h, 1), math.inf, dtype=area.dtype)
    area_v = torch.minimum(torch.cat([inf, area], 1), torch.cat([area, inf], 1))  # (H, W+1)
    ua, ub = edge_ends(size)
    amin = torch.cat([area_h.flatten(), area_v.flatten()])
    ne = ua.shape[0]
    brk = layout.edge_breakpoints(ua, ub).to(ua.dtype).reshape(ne, -1)
    brk = torch.where(torch.isfinite(brk) & (brk > 1e-6) & (brk < 1 - 1e-6), brk, torch.ones_like(brk))
    bounds = torch.cat([torch.zeros(ne, 1, dtype=ua.dtype), brk, torch.ones(ne, 1, dtype=ua.dtype)], 1)
    bounds = bounds.sort(1).values
    nonempty = bounds[:, 1:] - bounds[:, :-1] > 1e-12  # (E, P) pieces between breakpoints
    edge, k = torch.nonzero(nonempty, as_tuple=True)  # row-major: pieces in edge order
    lo, hi = bounds[edge, k], bounds[edge, k + 1]
    a0, d = ua[edge], (ub - ua)[edge]
    # K + 1 samples per piece: the chord, and second differences for the curvature. An
    # S-shaped piece or one whose bend sits near an end has no sagitta at its middle, so the
    # bound uses max |φ''⊥| / 8, the sagitta of a parabola with the piece's largest curvature.
    k_s = 8
    s_t = torch.linspace(0, 1, k_s + 1, dtype=ua.dtype)
    pts = a0[:, None] + (lo[:, None] + (hi - lo)[:, None] * s_t)[..., None] * d[:, None]  # (pieces, K+1, 2)
    pts = pts.transpose(0, 1)  # (K+1, pieces, 2)
    ends = layout.phi(pts, th)
    chord = ends[-1] - ends[0]
    length = torch.sqrt(chord[:, 0] ** 2 + chord[:, 1] ** 2)
    unit = chord / length.clamp_min(1e-300)[:, None]

    def normal_curvature(f: Tensor) -> Tensor:  # (K+1, pieces, 2) -> (K-1, pieces)
        d2 = (f[2:] - 2 * f[1:-1] + f[:-2]) * k_s**2
        return (unit[:, 0] * d2[..., 1] - unit[:, 1] * d2[..., 0]).abs()

    sag = normal_curvature(ends).amax(0) / 8
    if with_grad and th.numel():
        # the θ-gradient moves each edge by ∂φ/∂θ, which bends it even where φ does not
        # (e.g. at θ = 0): bound the curvature of that field the same way
        v = layout.phi_dtheta(pts, th)  # (K+1, pieces, 2, P)
        d2 = (v[2:] - 2 * v[1:-1] + v[:-2]) * k_s**2  # (K-1, pieces, 2, P)
        normal = (unit[:, 0, None] * d2[..., 1, :] - unit[:, 1, None] * d2[..., 0, :]).abs()
        sag = torch.maximum(sag, normal.amax(0).amax(-1) / 8)
    edge_len = torch.zeros(ne, dtype=ua.dtype).index_add_(0, edge, length)
    budget = 3 * tol * amin[edge] / (8 * edge_len[edge].clamp_min(1e-300))
    n = torch.sqrt(2 * sag / budget).ceil().clamp(1, max_subdiv)
    n = torch.where(sag <= 1e-15 * length, torch.ones_like(n), n).long()
    counts = torch.zeros(ne, dtype=torch.long).index_add_(0, edge, n)
    piece, kk = ranges(torch.zeros_like(n), n)
    lo_f, hi_f, n_f = lo[piece], hi[piece], n[piece].to(lo.dtype)
    return counts, lo_f + (hi_f - lo_f) * kk.to(lo.dtype) / n_f


def ranges(lo: Tensor, count: Tensor) -> tuple[Tensor, Tensor]:
    """Expand runs: for ``count[i]`` consecutive integers from ``lo[i]``, the pair
    ``(parent index i, integer)`` of every element, in order."""
    parent = torch.repeat_interleave(torch.arange(count.numel(), device=count.device), count)
    first = torch.cumsum(count, 0) - count
    return parent, lo[parent] + (torch.arange(parent.numel(), device=count.device) - first[parent])


def pixel_mesh(
    layout: Layout,
    size: tuple[int, int],
    *,
    tol: float | None = 1e-5,
    max_subdiv: int = 4096,
    subdivisions: Tensor | int | None = None,
    dtype: torch.dtype | None = None,
) -> PixelMesh:
    """Build the pixel polygon mesh of ``layout`` for a sensor of ``size = (H, W)``.

    Args:
        layout: the pixel layout (its θ is used with autograd, so the mesh vertices are
            differentiable in θ).
        size: sensor size ``(H, W)``.
        tol: polyline tolerance as a bound on the relative pixel-value error (see
            :func:`_edge_parameters`), and on the θ-gradient's when θ requires grad;
            ignored for straight-edged layouts, which always use one segment per edge.
        max_subdiv: cap on segments per edge.
        subdivisions: force a segment count per edge (an int, or an ``(E,)`` tensor) instead
            of the adaptive choice; used for reference computations.
        dtype: vertex dtype (default: θ's dtype).

    Returns:
        a :class:`PixelMesh`.
    """
    h, w = check_size(size)
    theta = layout.theta
    dtype = dtype or theta.dtype
    device = theta.device
    ne = (h + 1) * w + h * (w + 1)
    if subdivisions is not None:
        n = torch.as_tensor(subdivisions, dtype=torch.long).expand(ne).clone()
        if bool((n < 1).any()):
            raise ValueError("subdivisions must be >= 1")
        t_start = None
    elif layout.straight_edges or tol is None:
        n = torch.ones(ne, dtype=torch.long)
        t_start = None
    else:
        if not (tol > 0):
            raise ValueError(f"tol must be > 0, got {tol!r}")
        with_grad = torch.is_grad_enabled() and theta.requires_grad
        n, t_start = _edge_parameters(layout, (h, w), float(tol), max_subdiv, with_grad)
    ncorner = (h + 1) * (w + 1)
    cid = torch.arange(ncorner).view(h + 1, w + 1)
    # endpoint corner ids of every edge, in edge order
    ea = torch.cat([cid[:, :-1].flatten(), cid[:-1, :].flatten()])
    eb = torch.cat([cid[:, 1:].flatten(), cid[1:, :].flatten()])
    offsets = torch.zeros(ne + 1, dtype=torch.long)
    offsets[1:] = torch.cumsum(n, 0)
    nseg = int(offsets[-1])
    seg_edge, k = ranges(torch.zeros_like(n), n)  # k: segment index within its edge
    nn_ = n[seg_edge]
    # interior vertices: segment k > 0 starts at a new vertex
    interior = k > 0
    vid = torch.full((nseg,), -1, dtype=torch.long)
    vid[interior] = ncorner + torch.arange(int(interior.sum()))
    seg_start = torch.where(interior, vid, ea[seg_edge])
    nxt = torch.roll(vid, -1)
    last = k == nn_ - 1
    seg_end = torch.where(last, eb[seg_edge], nxt)
    # uniform positions of all vertices
    cu = uniform_corners((h, w), dtype=dtype, device=device).reshape(-1, 2)
    if t_start is None:  # equal parameter steps
        frac = k[interior].to(dtype) / nn_[interior].to(dtype)
    else:
        frac = t_start[interior].to(dtype)
    frac = frac.to(device)[:, None]
    ua, ub = cu[ea[seg_edge[interior]]], cu[eb[seg_edge[interior]]]
    upts = torch.cat([cu, ua + frac * (ub - ua)])
    verts = layout.phi(upts, theta.to(dtype))
    return PixelMesh(
        size=(h, w),
        vertices=verts,
        seg_start=seg_start.to(device),
        seg_end=seg_end.to(device),
        seg_edge=seg_edge.to(device),
        edge_offsets=offsets,
    )


# ----------------------------------------------------------------------------------------
# Dense maps
# ----------------------------------------------------------------------------------------
class Maps(NamedTuple):
    """A pair of float32 remap maps ``(map_x, map_y)``, each ``(H, W)``, OpenCV convention."""

    map_x: Tensor
    map_y: Tensor

    def numpy(self) -> tuple[np.ndarray, np.ndarray]:
        """The maps as contiguous float32 numpy arrays for ``cv2.remap``."""
        return (
            np.ascontiguousarray(self.map_x.detach().cpu().numpy(), dtype=np.float32),
            np.ascontiguousarray(self.map_y.detach().cpu().numpy(), dtype=np.float32),
        )


def _to_maps(points: Tensor, size: tuple[int, int]) -> Maps:
    px = sensor_to_pixels(points, size) - 0.5
    return Maps(px[..., 0].float(), px[..., 1].float())


def sample_points(
    size: tuple[int, int],
    samples: int = 1,
    *,
    jitter: bool = False,
    generator: torch.Generator | None = None,
    dtype: torch.dtype = torch.float64,
    device=None,
) -> Tensor:
    """Stratified sample points in the uniform cells, shape ``(H·s, W·s, 2)``.

    Cell ``(i, j)`` gets an ``s × s`` grid of strata; the sample of stratum ``(a, b)`` sits at
    its centre, or uniformly at random inside it with ``jitter=True``. Row ``i·s + a``,
    column ``j·s + b`` of the result belongs to pixel ``(i, j)``.
    """
    h, w = check_size(size)
    if int(samples) < 1:
        raise ValueError(f"samples must be >= 1, got {samples!r}")
    s = int(samples)
    if jitter:
        off = torch.rand(h * s, w * s, 2, generator=generator, dtype=dtype).to(device)
    else:
        off = torch.full((h * s, w * s, 2), 0.5, dtype=dtype, device=device)
    xs = torch.arange(w * s, dtype=dtype, device=device)
    ys = torch.arange(h * s, dtype=dtype, device=device)
    base = torch.stack(torch.meshgrid(xs, ys, indexing="xy"), -1)
    scale = torch.tensor([2 / (w * s), 2 / (h * s)], dtype=dtype, device=device)
    return (base + off) * scale - 1


def forward_maps(
    layout: Layout,
    size: tuple[int, int],
    src_size: tuple[int, int],
    *,
    samples: int = 1,
    jitter: bool = False,
    generator: torch.Generator | None = None,
) -> Maps:
    """Where each sample of each sensor pixel looks in the source image.

    Args:
        layout: the pixel layout.
        size: sensor size ``(h, w)``.
        src_size: source image size ``(H, W)``.
        samples: ``s``: an ``s × s`` stratified grid per pixel (1: the deformed pixel centres).
        jitter: jitter each sample inside its stratum (else stratum centres).
        generator: random generator for the jitter.

    Returns:
        :class:`Maps` of shape ``(h·s, w·s)`` in OpenCV ``remap`` convention, for ``cv2.remap``
        and ``kornia.geometry.transform.remap(..., align_corners=True)``. Average each
        ``s × s`` block of the remapped image for a (uniform-weight) pixel estimate.
    """
    size, src_size = check_size(size), check_size(src_size, "src_size")
    with torch.no_grad():
        u = sample_points(size, samples, jitter=jitter, generator=generator)
        q = layout.phi(u, layout.theta.detach().double())
    return _to_maps(q, src_size)


def inverse_maps(layout: Layout, size: tuple[int, int], target_size: tuple[int, int]) -> Maps:
    """Which sensor-pixel coordinate each target pixel centre falls on.

    Args:
        layout: the pixel layout.
        size: sensor size ``(h, w)`` (the image being sampled).
        target_size: output size ``(H, W)`` (e.g. the ground-truth resolution).

    Returns:
        :class:`Maps` of shape ``(H, W)`` with coordinates on the sensor image in OpenCV
        convention: target pixel centre ``q`` maps to ``(φ⁻¹(q) + 1) · (w, h) / 2 − 0.5``, so
        ``floor(map + 0.5)`` is the index of the sensor pixel that contains ``q``.
    """
    size, target_size = check_size(size), check_size(target_size, "target_size")
    with torch.no_grad():
        q = pixel_centers(target_size)
        p = layout.phi_inverse(q, layout.theta.detach().double())
    return _to_maps(p, size)
