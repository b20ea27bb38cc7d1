"""``layoutwarp::pixel_areas`` and its backward: the areas of a layout's pixel polygons at θ,
differentiable in θ: what sensor physics needs beside the sampling integrators' means."""

from __future__ import annotations

import torch
from torch import Tensor

from ..mesh import pixel_mesh
from . import base as ops

__all__ = ["areas_call"]


def areas_call(layout: str, size: tuple[int, int], tol: float) -> str:
    """The description ``layoutwarp::pixel_areas`` takes: the layout's token, the sensor's
    ``size`` and the polylines' ``tol``."""
    return ops.describe_call(layout=layout, size=size, tol=tol)


@torch.library.custom_op("layoutwarp::pixel_areas", mutates_args=())
def _pixel_areas(theta: Tensor, call: str) -> Tensor:
    """The areas ``(h, w)`` (float64, sensor units) of the pixel polygons of the layout of
    ``call`` ([`areas_call`][]: its token, the sensor's size and ``tol``) at ``theta``: what
    sensor physics needs beside the sampling integrators' means. Differentiable in θ (the mesh
    built again with autograd)."""
    c = ops.read_call(call, "pixel_areas")
    mesh = pixel_mesh(ops.layout_of(c.layout), c.size, tol=c.tol, dtype=torch.float64, theta=theta.detach())
    return mesh.areas().clone()


@_pixel_areas.register_fake
def _(theta, call):
    return theta.new_empty(ops.read_call(call, "pixel_areas").size, dtype=torch.float64)


@torch.library.custom_op("layoutwarp::pixel_areas_backward", mutates_args=())
def _pixel_areas_backward(grad: Tensor, theta: Tensor, call: str) -> Tensor:
    """θ's gradient of ``layoutwarp::pixel_areas``."""
    c = ops.read_call(call, "pixel_areas_backward")
    with ops.autograd_inside():
        th = theta.detach().requires_grad_(True)
        mesh = pixel_mesh(ops.layout_of(c.layout), c.size, tol=c.tol, dtype=torch.float64, theta=th)
        (g,) = torch.autograd.grad(mesh.areas(), th, grad, allow_unused=True)
    return torch.zeros_like(theta) if g is None else g.to(theta)


@_pixel_areas_backward.register_fake
def _(grad, theta, call):
    return torch.empty_like(theta)


def _pixel_areas_setup(ctx: object, inputs: tuple, output: Tensor) -> None:
    theta, call = inputs
    ctx.save_for_backward(theta)  # type: ignore[attr-defined]
    ctx.call = call  # type: ignore[attr-defined]


def _pixel_areas_grad(ctx: object, grad: Tensor) -> tuple:
    (theta,) = ctx.saved_tensors  # type: ignore[attr-defined]
    return _pixel_areas_backward(grad, theta, ctx.call), None  # type: ignore[attr-defined]


_pixel_areas.register_autograd(_pixel_areas_grad, setup_context=_pixel_areas_setup)
ops.first_order_only(_pixel_areas_backward, "pixel_areas")
ops.register(_pixel_areas)
ops.register(_pixel_areas_backward)
