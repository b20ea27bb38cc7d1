"""``layoutwarp::flux`` and its backward: the identity on a Monte Carlo estimate whose θ-gradient
is the Reynolds boundary flux (paper eq. 16), estimated along every shared edge once; and
[`sample_radiance`][], how the sampling integrators read an image or a callable radiance."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor

from ..layouts import Layout
from ..mesh import MeshTopology
from . import base as ops

__all__ = ["Radiance", "flux_call", "sample_radiance"]

#: A black-box radiance: points ``(..., 2)`` in sensor coordinates to values ``(..., N)``.
Radiance = Callable[[Tensor], Tensor]


def sample_radiance(image: Tensor | Radiance, points: Tensor, radiance: str) -> Tensor:
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


def flux_call(layout: str, size: tuple[int, int], samples: int, radiance: str, radiance_fn: str = "") -> str:
    """The description ``layoutwarp::flux`` takes: the layout's token, the sensor's ``size``, the
    ``samples`` per pixel side, the ``radiance`` model and, for a callable radiance, its
    [`object_token`][layoutwarp.operators.base.object_token] (``radiance_fn``; ``""``: the
    image)."""
    return ops.describe_call(
        layout=layout, size=size, samples=samples, radiance=radiance, radiance_fn=radiance_fn
    )


@torch.library.custom_op("layoutwarp::flux", mutates_args=())
def _flux(value: Tensor, theta: Tensor, vol: Tensor, image: Tensor, seed: Tensor, call: str) -> Tensor:
    """Identity on ``value``; its θ-gradient is the Reynolds boundary flux (paper eq. 16).

    ``∂I_k/∂θ = (1/|A_k|) ∮_∂A_k (L − I_k) ⟨∂r/∂θ, n⟩ ds`` (constant sensitivity ``W``, so
    the interior term vanishes), estimated with stratified jittered samples along every
    edge (drawn from ``seed``); each shared edge is sampled once and used with opposite signs by
    its two pixels. ``call`` ([`flux_call`][]) holds the layout, the sensor's size, the samples
    and the radiance model. Needs no gradient of ``L`` (the image, or the callable of
    ``call``'s ``radiance_fn``). The work is done in the backward pass only (``call`` is read
    here, so a bad one is refused at once)."""
    _read_flux_call(call, "flux")
    return value.clone()


@_flux.register_fake
def _(value, theta, vol, image, seed, call):
    _read_flux_call(call, "flux")
    return torch.empty_like(value)


def _read_flux_call(call: str, op: str) -> ops.CallSettings:
    """``call``'s settings, each of [`flux_call`][]'s read (one it lacks refused in one line)."""
    c = ops.read_call(call, op)
    _ = (c.layout, c.size, c.samples, c.radiance, c.radiance_fn)
    return c


@torch.library.custom_op("layoutwarp::flux_backward", mutates_args=())
def _flux_backward(
    grad: Tensor, value: Tensor, theta: Tensor, vol: Tensor, image: Tensor, seed: Tensor, call: str
) -> Tensor:
    """θ's gradient of ``layoutwarp::flux``: [`_flux_gradient`][] with the weights ``grad / vol``."""
    c = _read_flux_call(call, "flux_backward")
    source = ops.object_of(c.radiance_fn) if c.radiance_fn else image
    generator = ops.generator_of(seed, theta.device)
    with ops.autograd_inside():
        g = _flux_gradient(
            source, ops.layout_of(c.layout), theta.detach(), c.size, c.samples, c.radiance, generator,
            grad / vol, value,
        )  # fmt: skip
    return g.to(theta.dtype)


@_flux_backward.register_fake
def _(grad, value, theta, *rest):
    return torch.empty_like(theta)


def _flux_setup(ctx: Any, inputs: tuple, output: Tensor) -> None:
    *tensors, call = inputs
    ctx.save_for_backward(*tensors)
    ctx.call = call


def _flux_grad(ctx: Any, grad: Tensor) -> tuple:
    g_theta = _flux_backward(grad, *ctx.saved_tensors, ctx.call) if ctx.needs_input_grad[1] else None
    return grad, g_theta, None, None, None, None


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
    lv = sample_radiance(image, r.detach(), radiance).to(dtype)  # (N, E, m)
    w = weight.to(dtype)
    per_edge = topo.combine_adjoint(w)  # (N, E): Σ_k ±weight[n, k] over the edge's two pixels
    offset = topo.combine_adjoint(w * value.to(dtype)).sum(0)  # (E,): the same of weight · I
    c = ((lv * per_edge[..., None]).sum(0) - offset[:, None]) / m  # (E, m)
    cot = torch.stack([c * rdot[..., 1], -c * rdot[..., 0]], -1)  # (E, m, 2)
    (grad,) = torch.autograd.grad(r, th, cot, allow_unused=True)
    return torch.zeros_like(theta) if grad is None else grad
