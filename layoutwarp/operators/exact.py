"""``layoutwarp::exact`` and its backward: θ (or ρ and bounds) and a box image in, the exact
means and areas of a layout's pixels out, with the exact Reynolds θ-gradient; the route (the
compiled mesh on the CPU, the device mesh, or the torch reference) chosen here, once per call."""

from __future__ import annotations

import contextlib
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch
from torch import Tensor

from .. import kernels
from ..caches import LRU
from ..checks import all_finite, raise_nonfinite
from ..green import cuda_per_segment, exact_on_mesh
from ..kernels.device import runs_on_device
from ..kernels.mesh import (
    MeshSpec,
    build_mesh_device,
    device_means,
    device_theta_gradient,
    edge_gradient,
    mesh_integrals,
    mesh_spec,
    theta_gradient,
)
from ..layouts import Layout, theta_of
from ..mesh import MeshTopology, pixel_mesh
from . import base as ops

__all__ = ["DEVICE_MESHES", "NUMBA_NEEDS", "exact_call"]

#: Why ``backend="numba"`` was refused (by [`integrate_exact`][layoutwarp.integrators.integrate_exact]
#: for an image that needs its gradient, here where the kernels cannot run).
NUMBA_NEEDS = (
    "backend='numba' needs numba installed, a CPU image or a CUDA image where numba's CUDA "
    "target runs, and no image gradient; use backend='torch'"
)


def _unit(image: Tensor) -> float:
    """A source pixel's area in sensor units (the square ``[-1, 1]²`` is 4)."""
    return 4 / (image.shape[-2] * image.shape[-1])


def _jacobian_shape(theta: Tensor, image: Tensor, height: int, width: int) -> tuple[int, int, int]:
    """The θ-Jacobian of the edge integrals a learnable step keeps: ``(N + 1, E, P)``."""
    return image.shape[0] + 1, MeshTopology((height, width)).num_edges, theta.shape[0]


def exact_call(
    layout: str,
    size: tuple[int, int],
    tol: float,
    backend: str = "auto",
    jacobian: bool = False,
    check: bool = False,
    dtype: torch.dtype = torch.float64,
) -> str:
    """The description ``layoutwarp::exact`` takes: the layout's token, the sensor's ``size``,
    ``tol``, the ``backend``, whether θ's ``jacobian`` is kept, whether to ``check`` for NaN/Inf,
    and the means' ``dtype``."""
    return ops.describe_call(
        layout=layout, size=size, tol=tol, backend=backend, jacobian=jacobian, check=check, dtype=dtype
    )


@torch.library.custom_op("layoutwarp::exact", mutates_args=())
def _exact(theta: Tensor, image: Tensor, bounds: Tensor, call: str) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """The exact means ``(N, h, w)`` (computed in float64, rounded once into ``dtype``) and
    areas ``(h, w)`` (float64, sensor units) of the pixels of ``layout`` (a
    [`layout_token`][layoutwarp.operators.base.layout_token]) at θ over the box image ``image``
    ``(N, H, W)``, where ``call`` ([`exact_call`][]) holds ``layout``, the sensor's ``size``
    ``(h, w)``, ``tol``, ``backend``, ``jacobian``, ``check`` and ``dtype``. ``theta`` is θ
    itself where ``bounds`` is empty, else the parameter ρ of ``θ = bounds · tanh(ρ)`` (float64;
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
    c = ops.read_call(call, "exact")
    _check_exact(image, c.backend)
    template = ops.layout_of(c.layout, op="exact")
    ops.check_theta("exact", theta, template, bounds)
    hs, ws = image.shape[-2:]
    which = "torch" if c.backend == "torch" else ops.backend(image, "learn", wait=c.backend == "numba")
    if c.backend == "numba" and which == "torch":
        raise ValueError(NUMBA_NEEDS)
    spec = mesh_spec(template) if which != "torch" else None
    image = image.contiguous()
    if spec is not None and which == "cuda":  # the mesh built where it is used: none crosses the bus
        held = image.new_empty((), dtype=torch.int8)  # where the image is: a graph holds no CPU tensor
        means, area, areas, dm = _device_exact(
            spec, theta, bounds, image, c.size, c.tol, c.check, c.dtype, held
        )
        if c.jacobian:  # the device mesh kept for the backward (the entry holds the means: their
            DEVICE_MESHES.put(means.data_ptr(), (means, dm, area))  # memory is not reused meanwhile)
        return means, areas, image.new_empty(0, dtype=torch.float64), held  # checked on the device
    no_jac = (  # zeros: the torch path's room for a Jacobian it does not fill
        image.new_zeros(_jacobian_shape(theta, image, *c.size), dtype=torch.float64)
        if _keeps_jacobian(image, c.jacobian)
        else image.new_empty(0, dtype=torch.float64)
    )
    held = image.new_zeros((), dtype=torch.int8)
    if spec is not None and c.jacobian:  # mesh, integrals and their θ-Jacobian, chunk by chunk
        th = theta_of(theta, bounds).detach().cpu().numpy()
        tables = kernels.prefix_tables(image.numpy(), kernels.BLOCK)
        out, j = mesh_integrals(spec, c.size, th, c.tol, tables, (hs, ws))
        pix = MeshTopology(c.size).combine(out)
        held.fill_(1)
        means, areas, jac = (torch.from_numpy(a) for a in (pix[:-1] / pix[-1], pix[-1] * _unit(image), j))
    else:
        with ops.autograd_inside() if c.jacobian else contextlib.nullcontext():  # the mesh a gradient needs
            th = theta_of(theta, bounds).detach().requires_grad_(c.jacobian)
            means, areas = _mesh_exact(
                th, image, template, c.size, c.tol, which != "torch", cache=not c.jacobian
            )
        means, areas, jac = means.detach(), areas.detach().clone(), no_jac
    means = means.to(c.dtype)
    if c.check and not all_finite(means):
        raise_nonfinite(image)
    return means, areas, jac, held


def _check_exact(image: Tensor, backend: str) -> None:
    """Refuse, in one line, an image that is not ``(N, H, W)`` or a backend of no name."""
    if image.ndim != 3:
        ops.refuse("exact", "image", f"must be (N, H, W), got shape {tuple(image.shape)}")
    if backend not in ("auto", "numba", "torch"):
        ops.refuse("exact", "backend", f"must be 'auto', 'numba' or 'torch', got {backend!r}")


@_exact.register_fake
def _(theta, image, bounds, call):
    c = ops.read_call(call, "exact")
    _check_exact(image, c.backend)
    jac = _jacobian_shape(theta, image, *c.size) if _keeps_jacobian(image, c.jacobian) else (0,)
    return (
        image.new_empty(image.shape[0], *c.size, dtype=c.dtype),
        image.new_empty(c.size, dtype=torch.float64),
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
DEVICE_MESHES: LRU[tuple] = LRU("device meshes of learnable steps", 4)


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
    per_seg = cuda_per_segment(dm.pixel_vertices, dm.mesh, dm.incl, dm.offsets)
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
    return exact_on_mesh(image, mesh, compiled), mesh.areas()


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
    bounds: Tensor,
    call: str,
    needs: Sequence[bool],
) -> tuple[Tensor, Tensor]:
    """The gradients of ``layoutwarp::exact``'s ``theta`` (θ or ρ, as ``bounds`` says) and image
    from those of its means and areas (``None``: unused) (the image's: an empty tensor unless
    ``needs[1]``; θ's, zeros unless ``needs[0]``), for the forward's ``call``: the exact
    Reynolds transport gradient, by one contraction with the kept Jacobian, by the device
    kernels, or by the mesh again with autograd."""
    c = ops.read_call(call, "exact_backward")
    theta_grad, image_grad = needs
    if (
        jac.numel() and bool(held) and not image_grad
    ):  # the compiled CPU step: the quotient rule and one contraction
        g = np.zeros(means.shape) if grad_means is None else grad_means.detach().double().cpu().numpy()
        own = None if grad_areas is None else grad_areas.detach().double().cpu().numpy() * _unit(image)
        g_edge = edge_gradient(g, means.double().cpu().numpy(), areas.cpu().numpy() / _unit(image), own)
        g_theta = theta_gradient(g_edge, jac.cpu().numpy())
        return _to_param(torch.from_numpy(g_theta), theta, bounds), image.new_empty(0)
    which = "torch" if c.backend == "torch" or image_grad else ops.backend(image, "learn")
    template = ops.layout_of(c.layout)
    spec = mesh_spec(template) if which == "cuda" else None
    if spec is not None:  # the forward's device mesh, else built again (its sizes live on the device)
        kept = DEVICE_MESHES.pop(means.data_ptr())
        if kept is None:
            zero = image.new_empty(1, dtype=torch.int8)
            _, area, _, dm = _device_exact(
                spec, theta, bounds, image.contiguous(), c.size, c.tol, False, means.dtype, zero
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
        m, a = _mesh_exact(th, img, template, c.size, c.tol, which != "torch", cache=False)
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
def _(grad_means, grad_areas, theta, image, means, areas, jac, held, bounds, call, needs):
    return torch.empty_like(theta), image.new_empty(image.shape) if needs[1] else image.new_empty(0)


def _to_param(g_theta: Tensor, param: Tensor, bounds: Tensor) -> Tensor:
    """The gradient of θ's parameter ``param`` (θ, or ρ: see
    [`theta_of`][layoutwarp.layouts.values.theta_of]) from θ's, ``g_theta`` (float64), in
    ``param``'s dtype."""
    if not bounds.numel():
        return g_theta.to(param)
    with ops.autograd_inside():
        p = param.detach().double().requires_grad_(True)
        (g,) = torch.autograd.grad(theta_of(p, bounds), p, g_theta.to(p.device))
    return g.to(param)


def _exact_setup(ctx: Any, inputs: tuple, output: tuple) -> None:
    theta, image, bounds, call = inputs
    means, areas, jac, held = output
    ctx.save_for_backward(theta, image, means, areas, jac, held, bounds)
    ctx.call = call
    ctx.set_materialize_grads(False)  # an output nobody used costs its backward nothing


def _exact_grad(ctx: Any, grad_means: Tensor, grad_areas: Tensor, *_: Tensor) -> tuple:
    if grad_means is None and grad_areas is None:
        return None, None, None, None
    needs = ctx.needs_input_grad[:2]
    g_theta, g_image = _exact_backward(grad_means, grad_areas, *ctx.saved_tensors, ctx.call, needs)
    return (g_theta if needs[0] else None), (g_image if needs[1] else None), None, None


def _exact_backward_setup(ctx: Any, inputs: tuple, output: tuple) -> None:
    theta, image, *_, bounds, call, needs = inputs[2:]
    # θ fixed: the image's gradient is the transposed product, linear in the means' gradient alone
    ctx.linear = not needs[0]
    ctx.save_for_backward(theta, bounds)
    ctx.call, ctx.dtype = call, image.dtype


def _exact_backward_grad(ctx: Any, g_theta: Tensor | None, g_image: Tensor | None) -> tuple:
    """The derivative of the image's gradient ``Wᵀ g`` of a fixed layout: ``W u`` (the forward)
    for the means' gradient, nothing for the rest; refused in one line where θ's gradient was
    taken too (its derivatives are a compiled formula's)."""
    if not ctx.linear:
        raise RuntimeError(ops.SECOND_ORDER.format(op="exact"))
    if g_image is None or g_image.numel() == 0:
        return (None,) * 11
    theta, bounds = ctx.saved_tensors
    c = ops.read_call(ctx.call, "exact")
    call = exact_call(c.layout, c.size, c.tol, c.backend, dtype=ctx.dtype)
    return torch.ops.layoutwarp.exact(theta, g_image, bounds, call)[0], *[None] * 10


_exact.register_autograd(_exact_grad, setup_context=_exact_setup)
_exact_backward.register_autograd(_exact_backward_grad, setup_context=_exact_backward_setup)
ops.register(_exact, fold=1, outputs=("image", "shared", "jacobian", "shared"))
ops.register(_exact_backward)
