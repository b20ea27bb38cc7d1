"""``layoutwarp::pixel_areas`` and its backward: the areas of a layout's pixel polygons at θ,
differentiable in θ: what sensor physics needs beside the sampling integrators' means."""

from __future__ import annotations

import torch
from torch import Tensor

from ..mesh import pixel_mesh
from . import base as ops

__all__: list[str] = []


@torch.library.custom_op("layoutwarp::pixel_areas", mutates_args=())
def _pixel_areas(theta: Tensor, layout: str, height: int, width: int, tol: float) -> Tensor:
    """The areas ``(h, w)`` (float64, sensor units) of the pixel polygons of ``layout`` (a
    [`layout_token`][layoutwarp.operators.base.layout_token]) at ``theta``: what sensor physics needs beside
    the sampling integrators' means. Differentiable in θ (the mesh built again with autograd)."""
    mesh = pixel_mesh(
        ops.layout_of(layout), (height, width), tol=tol, dtype=torch.float64, theta=theta.detach()
    )
    return mesh.areas().clone()


@_pixel_areas.register_fake
def _(theta, layout, height, width, tol):
    return theta.new_empty(height, width, dtype=torch.float64)


@torch.library.custom_op("layoutwarp::pixel_areas_backward", mutates_args=())
def _pixel_areas_backward(
    grad: Tensor, theta: Tensor, layout: str, height: int, width: int, tol: float
) -> Tensor:
    """θ's gradient of ``layoutwarp::pixel_areas``."""
    with ops.autograd_inside():
        th = theta.detach().requires_grad_(True)
        mesh = pixel_mesh(ops.layout_of(layout), (height, width), tol=tol, dtype=torch.float64, theta=th)
        (g,) = torch.autograd.grad(mesh.areas(), th, grad, allow_unused=True)
    return torch.zeros_like(theta) if g is None else g.to(theta)


@_pixel_areas_backward.register_fake
def _(grad, theta, layout, height, width, tol):
    return torch.empty_like(theta)


def _pixel_areas_setup(ctx: object, inputs: tuple, output: Tensor) -> None:
    theta, *args = inputs
    ctx.save_for_backward(theta)  # type: ignore[attr-defined]
    ctx.args = args  # type: ignore[attr-defined]


def _pixel_areas_grad(ctx: object, grad: Tensor) -> tuple:
    (theta,) = ctx.saved_tensors  # type: ignore[attr-defined]
    return _pixel_areas_backward(grad, theta, *ctx.args), None, None, None, None  # type: ignore[attr-defined]


_pixel_areas.register_autograd(_pixel_areas_grad, setup_context=_pixel_areas_setup)
ops.first_order_only(_pixel_areas_backward, "pixel_areas")
ops.register(_pixel_areas)
ops.register(_pixel_areas_backward)
