"""Integrators: the mean radiance over every deformed pixel (paper eq. 7).

All functions take a source ``image`` of shape ``(N, H, W)`` (channels flattened into
``N``; callers reshape ``(B, C, H, W)``) in a floating dtype and return ``(N, h, w)``.
Source pixel ``(r, c)`` covers ``[c, c + 1) × [r, r + 1)`` in source pixel units, which map
to the sensor square by ``X = (x + 1) · W / 2``, ``Y = (y + 1) · H / 2``.

* :func:`integrate_exact` — box radiance over polygonal pixels by Green's theorem,
  ``∬_A L = ∮_∂A P dY`` with ``P`` the row prefix integral. Cost grows with the pixel
  perimeter; each shared edge is integrated once. Tables are float64.
* :func:`integrate_separable` — rectangular layouts: per-axis overlap weights (the
  weights ``cv2.resize(INTER_AREA)`` uses for the uniform layout).
* :func:`integrate_montecarlo` — the paper's stratified Monte Carlo, with the Reynolds
  transport (boundary flux) or the autograd gradient estimator.
* :func:`integrate_point` — one sample per pixel at the deformed centre.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
import torch.nn.functional as F
from torch import Tensor

from .layouts import Layout
from .mesh import PixelMesh, combine_edges, pixel_centers, pixel_mesh, sample_points, sensor_to_pixels

__all__ = [
    "Radiance",
    "axis_weights",
    "integrate_exact",
    "integrate_montecarlo",
    "integrate_point",
    "integrate_separable",
]

#: A black-box radiance: points ``(..., 2)`` in sensor coordinates to values ``(..., N)``.
Radiance = Callable[[Tensor], Tensor]


# ----------------------------------------------------------------------------------------
# Exact: Green's theorem over polygon pixels
# ----------------------------------------------------------------------------------------
def _row_tables(image: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Prefix tables of a piecewise-constant image ``(N, H, W)``, padded to width ``W + 1``.

    ``S[r, c] = Σ_{c' < c} L[r, c']`` (the row prefix ``P`` at integer ``X = c``) and
    ``T[r, c] = ∫_0^c P_r(X) dX = Σ_{c' < c} (S[r, c'] + L[r, c'] / 2)``.
    """
    lpad = F.pad(image, (0, 1))
    s = F.pad(torch.cumsum(image, -1), (1, 0))
    t = F.pad(torch.cumsum(s[..., :-1] + image / 2, -1), (1, 0))
    return lpad, s, t


def _split_rows(a: Tensor, b: Tensor, rows: int) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Cut segments ``a → b`` (source pixel units, ``(S, 2)``) at integer ``Y``.

    Horizontal segments (``ΔY = 0``) are dropped: they contribute nothing to ``∮ P dY``.

    Returns:
        ``(seg, row, x0, x1, dy)`` per piece: parent segment index, source row, the piece's
        ``X`` at its two ends ordered by increasing ``Y``, and the signed ``ΔY``.
    """
    ya, yb = a[:, 1], b[:, 1]
    keep = torch.nonzero(ya != yb).squeeze(1)
    a, b, ya, yb = a[keep], b[keep], ya[keep], yb[keep]
    ylo, yhi = torch.minimum(ya, yb), torch.maximum(ya, yb)
    r0 = ylo.detach().floor().clamp(0, rows - 1).long()
    r1 = (yhi.detach().ceil().long() - 1).clamp(0, rows - 1)
    r1 = torch.maximum(r1, r0)
    count = r1 - r0 + 1
    piece = torch.repeat_interleave(torch.arange(keep.numel(), device=a.device), count)
    first = torch.cumsum(count, 0) - count
    row = r0[piece] + (torch.arange(piece.numel(), device=a.device) - first[piece])
    rowf = row.to(a.dtype)
    lo = torch.maximum(ylo[piece], rowf)
    hi = torch.minimum(yhi[piece], rowf + 1)
    # X along the segment at a given Y
    pa, pb = a[piece], b[piece]
    inv = 1 / (pb[:, 1] - pa[:, 1])
    x_lo = pa[:, 0] + (lo - pa[:, 1]) * inv * (pb[:, 0] - pa[:, 0])
    x_hi = pa[:, 0] + (hi - pa[:, 1]) * inv * (pb[:, 0] - pa[:, 0])
    sign = torch.sign(pb[:, 1] - pa[:, 1])
    return keep[piece], row, x_lo, x_hi, sign * (hi - lo)


def _mean_prefix(tables: tuple[Tensor, Tensor, Tensor], row: Tensor, x0: Tensor, x1: Tensor) -> Tensor:
    """Mean of the row prefix ``P_row(X)`` over ``[x0, x1]`` (either order), ``(N, pieces)``.

    ``P`` is piecewise linear, so within one source cell the mean is ``P`` at the midpoint;
    across cells it is split into a partial first cell, whole cells (from ``T``) and a partial
    last cell, a convex combination with no cancellation for short intervals.
    """
    lpad, s, t = tables
    n, _, wp = s.shape
    w = wp - 1
    xa, xb = torch.minimum(x0, x1), torch.maximum(x0, x1)
    ca = xa.detach().floor().clamp(0, w - 1).long()
    cb = xb.detach().floor().clamp(0, w - 1).long()
    base = row * wp
    lflat, sflat, tflat = lpad.reshape(n, -1), s.reshape(n, -1), t.reshape(n, -1)

    def g(table: Tensor, col: Tensor) -> Tensor:
        return table[:, base + col]

    la, lb = g(lflat, ca), g(lflat, cb)
    sa, sb = g(sflat, ca), g(sflat, cb)
    fa = (xa - ca.to(xa.dtype))[None]
    fb = (xb - cb.to(xb.dtype))[None]
    same = (ca == cb)[None]
    # same cell: P at the midpoint
    p_mid = sa + 0.5 * (fa + fb) * la
    # different cells
    sa1 = g(sflat, ca + 1)
    first = (1 - fa) * (sa + fa * la + sa1) / 2
    middle = g(tflat, cb) - g(tflat, ca + 1)
    last = fb * (sb + (sb + fb * lb)) / 2
    dx = (xb - xa)[None]
    p_span = (first + middle + last) / torch.where(same, torch.ones_like(dx), dx)
    return torch.where(same, p_mid, p_span)


def integrate_exact(
    image: Tensor,
    layout: Layout,
    size: tuple[int, int],
    *,
    tol: float | None = 1e-5,
    mesh: PixelMesh | None = None,
) -> Tensor:
    """Exact mean of a piecewise-constant (box) image over every polygonal pixel.

    Uses Green's theorem ``∬_A L dA = ∮_∂A P dY`` with ``P(X, Y) = ∫_0^X L(s, Y) ds``: each
    boundary segment is cut at source rows, and its integral over one row is a closed form
    in a few look-ups of float64 prefix tables. Exact for straight-edged pixels; curved
    pixel edges are polylines within ``tol`` (see :func:`layoutwarp.mesh.pixel_mesh`).
    Differentiable in the image and (through the mesh vertices) in θ; the derivative w.r.t.
    the vertices is the Reynolds boundary term, exactly.

    Args:
        image: ``(N, H, W)`` floating source image.
        layout: the pixel layout.
        size: sensor size ``(h, w)``.
        tol: polyline tolerance (relative pixel-value error) for curved edges.
        mesh: a precomputed mesh (overrides ``layout``/``tol`` for the geometry).

    Returns:
        ``(N, h, w)`` in float64.
    """
    n, hs, ws = image.shape
    if mesh is None:
        mesh = pixel_mesh(layout, size, tol=tol, dtype=torch.float64)
    verts = sensor_to_pixels(mesh.vertices.double(), (hs, ws))
    verts = torch.stack([verts[:, 0].clamp(0, ws), verts[:, 1].clamp(0, hs)], -1)
    a, b = verts[mesh.seg_start], verts[mesh.seg_end]
    seg, row, x0, x1, dy = _split_rows(a, b, hs)
    tables = _row_tables(image.double())
    contrib = dy[None] * _mean_prefix(tables, row, x0, x1)  # (N, pieces)
    per_seg = contrib.new_zeros(n, mesh.num_segments).index_add(1, seg, contrib)
    integral = mesh.combine_edges(mesh.sum_over_edges(per_seg))
    # polygon areas in source pixel units, from the same polyline
    area_seg = (b[:, 1] - a[:, 1]) * (a[:, 0] + b[:, 0]) / 2
    area = mesh.combine_edges(mesh.sum_over_edges(area_seg))
    return integral / area


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
    c1 = torch.maximum(c1, c0)
    count = c1 - c0 + 1
    dst = torch.repeat_interleave(torch.arange(lo.numel(), device=edges.device), count)
    first = torch.cumsum(count, 0) - count
    src = c0[dst] + (torch.arange(dst.numel(), device=edges.device) - first[dst])
    cf = src.to(edges.dtype)
    overlap = (torch.minimum(hi[dst], cf + 1) - torch.maximum(lo[dst], cf)).clamp_min(0)
    return dst, src, overlap / (hi - lo)[dst]


def _separable_edges(
    layout: Layout, size: tuple[int, int], src: tuple[int, int], dtype
) -> tuple[Tensor, Tensor]:
    h, w = size
    hs, ws = src
    theta = layout.theta.to(dtype)
    gx, gy = _lines(w, dtype, theta.device), _lines(h, dtype, theta.device)
    px = layout.phi(torch.stack([gx, torch.zeros_like(gx)], -1), theta)[:, 0]
    py = layout.phi(torch.stack([torch.zeros_like(gy), gy], -1), theta)[:, 1]
    return ((px + 1) * (ws / 2)).clamp(0, ws), ((py + 1) * (hs / 2)).clamp(0, hs)


def integrate_separable(image: Tensor, layout: Layout, size: tuple[int, int]) -> Tensor:
    """Exact box-radiance mean over the rectangular pixels of a separable layout.

    Two sparse passes: rows (``H → h``), then columns (``W → w``). For the uniform layout
    this is area resampling, identical to ``cv2.resize(..., interpolation=cv2.INTER_AREA)``
    when downscaling.

    Args:
        image: ``(N, H, W)`` floating source image.
        layout: a layout with ``separable = True``.
        size: sensor size ``(h, w)``.

    Returns:
        ``(N, h, w)`` in the image's dtype (float64 weights are used for float64 input).
    """
    if not layout.separable:
        raise ValueError(f"integrate_separable needs a separable layout, got {type(layout).__name__}")
    n, hs, ws = image.shape
    h, w = size
    dtype = torch.float64 if image.dtype == torch.float64 else torch.float32
    ex, ey = _separable_edges(layout, size, (hs, ws), torch.float64)
    dy_, sy_, wy_ = axis_weights(ey, hs)
    dx_, sx_, wx_ = axis_weights(ex, ws)
    img = image.to(dtype)
    rows = img.index_select(1, sy_) * wy_.to(dtype)[None, :, None]
    out = img.new_zeros(n, h, ws).index_add(1, dy_, rows)
    cols = out.index_select(2, sx_) * wx_.to(dtype)[None, None, :]
    return out.new_zeros(n, h, w).index_add(2, dx_, cols)


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


def integrate_point(
    image: Tensor | Radiance, layout: Layout, size: tuple[int, int], *, radiance: str = "bilinear"
) -> Tensor:
    """One sample per pixel at the deformed pixel centre ``φ(c_k)``: the aliasing baseline.

    Returns ``(N, h, w)``; differentiable in the image and (for bilinear or callable
    radiance) in θ.
    """
    c = pixel_centers(size, dtype=layout.theta.dtype, device=layout.theta.device)
    return _sample(image, layout(c), radiance)


class _FluxGrad(torch.autograd.Function):
    """Identity on ``value``; its θ-gradient is the Reynolds boundary flux (paper eq. 16).

    ``∂I_k/∂θ = (1/|A_k|) ∮_∂A_k (L − I_k) ⟨∂r/∂θ, n⟩ ds`` (constant sensitivity ``W``, so
    the interior term vanishes), estimated with stratified jittered samples along every
    edge; each shared edge is sampled once and used with opposite signs by its two pixels.
    Needs no gradient of ``L``. The work is done in the backward pass only.
    """

    @staticmethod
    def forward(ctx, value, theta, vol, image, layout, size, samples, radiance, generator):
        ctx.args = (image, layout, size, samples, radiance, generator)
        ctx.save_for_backward(value, theta, vol)
        return value.clone()

    @staticmethod
    def backward(ctx, grad_out):
        value, theta, vol = ctx.saved_tensors
        image, layout, size, samples, radiance, generator = ctx.args
        f_pix, g_pix = _flux_derivative(image, layout, theta.detach(), size, samples, radiance, generator)
        d_value = (f_pix - value.detach().to(f_pix.dtype)[..., None] * g_pix) / vol[..., None]
        grad_theta = (grad_out[..., None].to(d_value.dtype) * d_value).sum((0, 1, 2))
        return grad_out, grad_theta.to(theta.dtype), None, None, None, None, None, None, None


def _flux_derivative(image, layout: Layout, theta: Tensor, size, m: int, radiance, generator):
    """Boundary fluxes of every pixel: ``(∮ L ⟨∂r/∂θ, n⟩ ds, ∮ ⟨∂r/∂θ, n⟩ ds)``.

    Returns ``(N, h, w, P)`` and ``(h, w, P)``. Along an edge ``r(t) = φ(γ(t))`` the outward
    normal line element of the positively oriented pixel boundary is ``n ds = (ṙ_y, −ṙ_x) dt``
    with ``ṙ = J_φ γ̇``.
    """
    h, w = size
    dtype, dev = theta.dtype, theta.device
    gx, gy = _lines(w, dtype, dev), _lines(h, dtype, dev)
    t = (torch.arange(m, dtype=dtype) + torch.rand(m, generator=generator, dtype=dtype)).to(dev) / m
    hx = gx[:-1, None] + t * (2 / w)  # (w, m)
    vy = gy[:-1, None] + t * (2 / h)  # (h, m)
    edges = (  # (points (E1, E2, m, 2), γ̇): horizontal edges run +x, vertical edges +y
        (torch.stack([hx.expand(h + 1, w, m), gy[:, None, None].expand(h + 1, w, m)], -1), (2 / w, 0.0)),
        (
            torch.stack([gx[None, :, None].expand(h, w + 1, m), vy[:, None, :].expand(h, w + 1, m)], -1),
            (0.0, 2 / h),
        ),
    )
    f_edges, g_edges = [], []
    for pts, gdot in edges:
        r = layout.phi(pts, theta)
        rdot = layout.phi_jacobian(pts, theta) @ torch.tensor(gdot, dtype=dtype, device=dev)
        drdth = layout.phi_dtheta(pts, theta)  # (..., 2, P)
        flux = drdth[..., 0, :] * rdot[..., 1:2] - drdth[..., 1, :] * rdot[..., 0:1]  # (..., P)
        lv = _sample(image, r.flatten(0, 1), radiance).to(dtype).unflatten(1, pts.shape[:2])
        f_edges.append((lv[..., None] * flux).mean(-2).flatten(1, 2))  # (N, E_k, P)
        g_edges.append(flux.mean(-2).flatten(0, 1))  # (E_k, P)
    f_pix = combine_edges(torch.cat(f_edges, 1).movedim(-1, 1), size).movedim(1, -1)
    g_pix = combine_edges(torch.cat(g_edges, 0).T, size).movedim(0, -1)
    return f_pix, g_pix


def _lines(n: int, dtype, dev) -> Tensor:
    return (2 * torch.arange(n + 1, dtype=dtype, device=dev) - n) / n


def integrate_montecarlo(
    image: Tensor | Radiance,
    layout: Layout,
    size: tuple[int, int],
    *,
    samples: int = 4,
    radiance: str = "bilinear",
    grad: str = "reynolds",
    generator: torch.Generator | None = None,
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

    Returns:
        ``(N, h, w)``.
    """
    h, w = size
    s = int(samples)
    theta = layout.theta
    dtype = theta.dtype if not isinstance(image, Tensor) else torch.promote_types(theta.dtype, image.dtype)
    u = sample_points(size, s, jitter=True, generator=generator, dtype=dtype, device=theta.device)
    if grad == "autograd":
        if radiance == "box" and isinstance(image, Tensor):
            raise ValueError(
                "grad='autograd' needs a differentiable radiance; box radiance has zero "
                "spatial gradient almost everywhere: use grad='reynolds'"
            )
        th = theta.to(dtype)
    elif grad == "reynolds":
        th = theta.detach().to(dtype)
    else:
        raise ValueError(f"grad must be 'reynolds' or 'autograd', got {grad!r}")
    p = layout.phi(u, th)
    wdet = torch.linalg.det(layout.phi_jacobian(u, th)).abs()
    vals = _sample(image, p, radiance)  # (N, h*s, w*s)
    n = vals.shape[0]
    num = (vals * wdet.to(vals.dtype)).reshape(n, h, s, w, s).sum((2, 4))
    den = wdet.reshape(h, s, w, s).sum((1, 3)).to(vals.dtype)
    out = num / den
    if grad == "reynolds" and theta.requires_grad and theta.numel() > 0:
        vol = den * (4 / (h * w * s * s))  # Monte Carlo pixel areas, consistent with ``out``
        out = _FluxGrad.apply(out, theta, vol.detach(), image, layout, size, s, radiance, generator)
    return out
