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

import torch
from torch import Tensor

from .checks import (
    check_choice,
    check_float_dtype,
    check_int,
    check_shape,
    check_size,
    floating_dtype,
)
from .coords import pixel_centers
from .green import GreenPieces, exact_on_mesh, green_pieces, segment_cells
from .layouts import Layout, gradient_asked
from .maps import sample_points
from .mesh import PixelMesh
from .operators import base as ops
from .operators.exact import NUMBA_NEEDS, exact_call
from .operators.flux import Radiance, flux_call, sample_radiance
from .operators.separable import axis_weights, separable_edges
from .tolerance import data_tolerance

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
    (see [`layoutwarp.mesh.pixel_mesh`][layoutwarp.mesh.pixel_mesh]). Differentiable in the image
    (autograd through the prefix tables) and, through the mesh vertices, in θ, with the exact Reynolds
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
        means = exact_on_mesh(work, mesh, kernel_ok).to(dtype)
        return (means, mesh.areas()) if return_areas else means
    tol = data_tolerance(image.dtype)[0] if tol is None else tol
    # θ as the operator takes it: a fixed layout's as it was set (float64), a learnable one's ρ
    param, bounds = (
        layout.theta_source() if theta is None else (theta, theta.new_empty(0, dtype=torch.float64))
    )
    if image.requires_grad and backend == "numba":
        raise ValueError(NUMBA_NEEDS)
    which = "torch" if image.requires_grad else backend
    # a batched ρ (vmap over θ) reports no requires_grad: what it wraps says whether a gradient is asked
    jacobian = gradient_asked(param) and torch.is_grad_enabled()
    call = exact_call(
        ops.layout_token(layout), check_size(size), float(tol), which, jacobian, not allow_nonfinite, dtype
    )
    means, areas, _, _ = torch.ops.layoutwarp.exact(param, work, bounds, call)
    return (means, areas) if return_areas else means


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
    # θ in float64 (a fixed layout's exactly as set; a learnable one's from ρ, differentiable)
    theta = layout.theta_as(torch.float64) if theta is None else theta
    ex, ey = separable_edges(layout, check_size(size), (hs, ws), theta)
    work = image.to(floating_dtype(image.dtype)).contiguous()
    means = torch.ops.layoutwarp.separable(work, ex, ey, not allow_nonfinite)
    if not return_areas:
        return means
    return means, torch.outer(ey.diff() * (2 / hs), ex.diff() * (2 / ws))


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
    return sample_radiance(image, layout.phi(c, theta), radiance)


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
    vals = sample_radiance(image, p, radiance)  # (N, h*s, w*s)
    n = vals.shape[0]
    num = (vals * wdet.to(vals.dtype)).reshape(n, h, s, w, s).sum((2, 4))
    den = wdet.reshape(h, s, w, s).sum((1, 3)).to(vals.dtype)
    out = num / den
    if grad == "reynolds" and theta.requires_grad and theta.numel() > 0:
        vol = den * (4 / (h * w * s * s))  # Monte Carlo pixel areas, consistent with ``out``
        is_fn = callable(image) and not isinstance(image, Tensor)
        source, fn = (theta.new_empty(0), ops.object_token(image)) if is_fn else (image, "")
        edge_seed = ops.random_seed(generator, None if seed is None else seed + 1)
        call = flux_call(ops.layout_token(layout), size, s, radiance, fn)
        out = torch.ops.layoutwarp.flux(out, theta, vol.detach(), source, edge_seed, call)
    return out
