"""``layoutwarp::separable`` and its backward: the mean over the rectangular pixels of a
separable layout as two sparse passes of per-axis overlap weights (``cv2.resize(INTER_AREA)``'s
for the uniform layout), with the analytic boundary gradient of the pixels' edges."""

from __future__ import annotations

import warnings
from collections.abc import Sequence  # an operator's list argument (torch 2.6 reads no list[bool])
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor

from ..checks import all_finite, raise_nonfinite
from ..coords import grid_lines, sensor_to_pixels
from ..green import expand_runs
from ..layouts import Layout
from . import base as ops

__all__ = ["axis_weights", "separable_edges"]


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
    dst, src = expand_runs(c0, torch.maximum(c1, c0) - c0 + 1)
    cf = src.to(edges.dtype)
    overlap = (torch.minimum(hi[dst], cf + 1) - torch.maximum(lo[dst], cf)).clamp_min(0)
    return dst, src, overlap / (hi - lo)[dst]


def separable_edges(
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
    if n == 0:  # an empty batch
        return x.new_zeros(0, mat.shape[0], w)
    if n <= 8:
        return torch.stack([torch.sparse.mm(mat, x[k]) for k in range(n)])
    flat = x.permute(1, 0, 2).reshape(h, n * w)  # one call for many small images
    return torch.sparse.mm(mat, flat).view(-1, n, w).permute(1, 0, 2)


def _cols(x: Tensor, mat_t: Tensor) -> Tensor:
    """``x @ mat_t``: ``(N, H, W)`` times sparse ``(W, m)`` gives ``(N, H, m)``."""
    n, h, w = x.shape
    return torch.mm(x.reshape(n * h, w), mat_t).view(n, h, mat_t.shape[1])


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
    grad: Tensor, image: Tensor, ex: Tensor, ey: Tensor, out: Tensor, needs: Sequence[bool]
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
    g_image = g_ex = g_ey = None
    if needs[0]:  # linear in the image: its adjoint, an operator with exact derivatives of its own
        g_image = _separable_adjoint(grad, ex, ey, image.shape[-2], image.shape[-1])
    if needs[1] or needs[2]:
        _, g_ex, g_ey = _separable_backward(grad, image, ex, ey, out, [False, needs[1], needs[2]])
    return g_image, (g_ex if needs[1] else None), (g_ey if needs[2] else None), None


_separable.register_autograd(_separable_grad, setup_context=_separable_setup)
ops.first_order_only(_separable_backward, "separable")
ops.register(_separable, fold=0)
ops.register(_separable_backward)


@torch.library.custom_op("layoutwarp::separable_adjoint", mutates_args=())
def _separable_adjoint(grad: Tensor, ex: Tensor, ey: Tensor, src_height: int, src_width: int) -> Tensor:
    """``W_yᵀ · grad · W_x`` ``(N, H, W)``: the adjoint of ``layoutwarp::separable`` in the image
    (its image gradient), for ``grad`` ``(N, h, w)``. Linear in ``grad``, so its own derivative
    is ``layoutwarp::separable`` again: an input-gradient penalty through a fixed rectangular
    layout has its exact second derivative. (θ's second derivative is refused.)"""
    wy_t = _axis_csr(ey, src_height, grad.dtype)[1]
    wx = _axis_csr(ex, src_width, grad.dtype)[0]
    return _rows(wy_t, _cols(grad.contiguous(), wx)).contiguous()


@_separable_adjoint.register_fake
def _(grad, ex, ey, src_height, src_width):
    return grad.new_empty(grad.shape[0], src_height, src_width)


def _adjoint_setup(ctx: Any, inputs: tuple, output: Tensor) -> None:
    _, ex, ey, _, _ = inputs
    ctx.save_for_backward(ex, ey)


def _adjoint_grad(ctx: Any, grad: Tensor) -> tuple:
    if ctx.needs_input_grad[1] or ctx.needs_input_grad[2]:
        raise RuntimeError(ops.SECOND_ORDER.format(op="separable"))
    ex, ey = ctx.saved_tensors
    return _separable(grad, ex, ey, False), None, None, None, None


_separable_adjoint.register_autograd(_adjoint_grad, setup_context=_adjoint_setup)
ops.register(_separable_adjoint, fold=0)


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
