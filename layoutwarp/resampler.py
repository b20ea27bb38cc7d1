"""The exact integrator as a sparse matrix, for fixed layouts.

For a fixed layout nothing needs gradients, so the exact integrator (Green's theorem over the
pixel polygons, [`integrate_exact`][layoutwarp.integrators.integrate_exact]) becomes a sparse matrix
of area weights: for every sensor pixel, the fraction of its area that falls in every source cell
([`layoutwarp.weights`][]). [`AreaResampler`][] builds them once per source size, held as runs of
cells ([`Runs`][layoutwarp.kernels.runs.Runs]), and applies them to any number of images with one
pass each (CPU or CUDA); preprocessing, label maps and fixed-layout simulation use it.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from . import jit, kernels
from .caches import LRU
from .checks import (
    ArgumentError,
    all_finite,
    check_device,
    check_generator,
    check_number,
    check_size,
    raise_nonfinite,
)
from .integrators import data_tolerance
from .kernels.device import device_checks, fall_back, stream_of
from .kernels.runs import runs_apply_on_device
from .labels import labels_to_sensor
from .layouts import Layout, check_layout
from .measurement import device_arguments, kernel_arguments, measure, noise_seed
from .operators import base as ops
from .operators.base import layout_token
from .operators.exact import exact_call
from .physics import SensorPhysics, physics_of
from .weights import fixed_runs

if TYPE_CHECKING:
    import scipy.sparse

__all__ = ["RESAMPLERS", "AreaResampler", "area_call", "area_product", "resampler_for"]


class AreaResampler:
    """Exact sensor resampling for a fixed layout and source size (precomputed weights).

    Args:
        layout: the pixel layout (its current θ is frozen in the weights).
        size: sensor size ``(h, w)``.
        src_size: source image size ``(H, W)``.
        tol: the accuracy, as [`area_weights`][layoutwarp.weights.area_weights] (default: what
            ``dtype`` images need).
        dtype: the dtype of the images the weights are for.
        device: where the sparse products run.
        progress: the weights build's progress bar on or off (``None``: on a terminal, once the
            build has run [`PROGRESS_AFTER_S`][layoutwarp.weights.PROGRESS_AFTER_S]).

    Call with an ``(H, W)`` or ``(H, W, C)`` numpy image of any real dtype; returns a float32
    ``(h, w)`` / ``(h, w, C)`` array in the input's units (no rescaling of uint8/uint16).
    The product runs on ``device`` (the weights are built on the CPU once, by a compiled walk over
    each pixel's boundary where the fixed layout's kernels run, then moved):
    CPU or CUDA; a CUDA product sums in another order, so its float32 values can differ from
    the CPU's in the last bits (a rounded integer output by one level, rarely).

    Attributes:
        runs: the weights as [`Runs`][layoutwarp.kernels.runs.Runs] (what the products read: each
            source cell once).
        weights: the ``(h · w, H · W)`` float32 ``scipy.sparse.csr_matrix`` of
            [`area_weights`][layoutwarp.weights.area_weights], made from `runs` on first use (the
            image gradient, label maps and torch's product read it).
        areas: the pixels' areas ``(h, w)``, float64, in sensor units (the square ``[-1, 1]²``),
            on ``device`` (what sensor physics needs besides the means).
    """

    def __init__(
        self,
        layout: Layout,
        size: tuple[int, int],
        src_size: tuple[int, int],
        *,
        tol: float | None = None,
        dtype: torch.dtype | np.dtype | type = np.float32,
        device: str | torch.device = "cpu",
        progress: bool | None = None,
    ):
        self.size, self.src_size = check_size(size), check_size(src_size, "src_size")
        self.layout = check_layout(layout)
        try:
            tol_needed = data_tolerance(dtype)[0]
        except TypeError:
            raise ArgumentError("dtype", f"dtype must be a numpy or torch dtype, got {dtype!r}") from None
        self.tol = tol_needed if tol is None else check_number(tol, "tol", 0, lo_open=True)
        self.device = check_device(device)
        self.runs, areas = fixed_runs(self.layout, self.size, self.src_size, self.tol, progress)
        self.areas = areas.to(device)
        self._weights: scipy.sparse.csr_matrix | None = None
        self._csr: torch.Tensor | None = None
        self._csr_t: torch.Tensor | None = None
        self._device_runs: tuple[torch.Tensor, ...] | None = None

    @property
    def weights(self) -> scipy.sparse.csr_matrix:
        """The weights as a float32 CSR matrix, made from the
        [`Runs`][layoutwarp.kernels.runs.Runs] on first use and kept."""
        if self._weights is None:
            self._weights = self.runs.csr()
        return self._weights

    @property
    def sparse(self) -> torch.Tensor:
        """The weights as a torch sparse CSR tensor on `device`, built on first use (the CPU's
        compiled product reads `weights` itself, so a CPU resampler that needs no image
        gradient never holds this second copy)."""
        if self._csr is None:
            self._csr = _torch_csr(self.weights, self.device)
        return self._csr

    @property
    def sparse_t(self) -> torch.Tensor:
        """The transposed weights ``(H · W, h · w)`` as a torch sparse CSR tensor on `device`
        (built on the first image gradient)."""
        if self._csr_t is None:
            self._csr_t = _torch_csr(self.weights.transpose().tocsr(), self.device)
        return self._csr_t

    def __call__(self, image: np.ndarray) -> np.ndarray:
        if not isinstance(image, np.ndarray):
            what = (
                "a torch tensor: use apply() for (N, H, W) tensors"
                if isinstance(image, torch.Tensor)
                else type(image).__name__
            )
            raise ArgumentError("image", f"image must be a numpy (H, W) or (H, W, C) array, got {what}")
        if image.dtype.kind not in "biuf":  # bool, integers, floats
            raise ArgumentError(
                "image", f"image must hold real numbers (integers or floats), got {image.dtype}"
            )
        if image.ndim not in (2, 3) or image.shape[:2] != self.src_size:
            raise ArgumentError(
                "image",
                f"image must be {self.src_size} (H, W), optionally with channels, got shape {image.shape}",
            )
        if image.dtype.kind == "f" and not all_finite(torch.from_numpy(np.ascontiguousarray(image))):
            raise ArgumentError("image", "image has NaN or Inf values, which would spread into its pixels")
        planes = image.reshape(*self.src_size, -1).transpose(2, 0, 1)  # (C, H, W): made contiguous below
        x = torch.from_numpy(np.ascontiguousarray(planes, np.float32)).to(self.device)
        with torch.no_grad():
            out = self.product(x, None, "radiance", None, True)
        return out.permute(1, 2, 0).reshape(*self.size, *image.shape[2:]).cpu().numpy()

    def apply(
        self,
        images: torch.Tensor,
        physics: SensorPhysics | None = None,
        *,
        output: str = "radiance",
        generator: torch.Generator | None = None,
        seed: torch.Tensor | None = None,
        allow_nonfinite: bool = True,
    ) -> torch.Tensor:
        """The weights applied to ``(N, H, W)`` float32 images on this resampler's device:
        ``(N, h, w)``, differentiable in the images (the compiled row-parallel product on the
        CPU without gradient; torch's sparse product, plane by plane, otherwise).

        With ``physics``: what that sensor records of the pixel means
        ([`measure`][] with `areas`, ``output``, and ``generator`` or ``seed``);
        on the CPU without gradient, the product and the measurement are one compiled call
        (`measured_runs_apply`).

        ``allow_nonfinite=False`` raises ``ValueError`` where NaN/Inf in the images reach the
        means (as [`simulate`][layoutwarp.sensor.simulate] does by default); ``True`` passes them through."""
        self._check_planes(images, "images", self.src_size)
        check_generator(generator, seed=seed)
        needs_grad = torch.is_grad_enabled() and images.requires_grad
        if physics is not None and needs_grad:  # the means with their gradient, then the measurement
            mean = self.apply(images, allow_nonfinite=allow_nonfinite)
            return measure(mean, self.areas, physics, output=output, generator=generator, seed=seed)
        seed = None if physics is None else noise_seed(physics, generator, seed)
        return self.product(images, physics, output, seed, allow_nonfinite)

    def product(
        self,
        images: torch.Tensor,
        physics: SensorPhysics | None,
        output: str,
        seed: torch.Tensor | None,
        allow_nonfinite: bool,
    ) -> torch.Tensor:
        """[`apply`][]'s product (and, with ``physics``, the measurement fused into it, its
        noise drawn from ``seed``), eagerly: the work of ``layoutwarp::area``."""
        n = images.shape[0]
        flat = images.reshape(n, images.shape[-2] * images.shape[-1])  # sizes named: an empty batch too
        seed_value = 0 if seed is None or physics is None else ops.seed_value(seed)
        which = ops.backend(flat, "fixed", name=_DEVICE_PRODUCT)
        if which == "cuda" and not flat.requires_grad:
            if physics is None:
                none = flat.new_empty(0, dtype=torch.float64)  # not read
                measured = (none, none, none, none, 0, 0, 0)
            else:  # the arguments checked before the launch: a bad one is the caller's error
                measured = device_arguments(physics, self.areas, flat.device, output, seed_value)
            if not allow_nonfinite:  # an earlier checked call's NaN, found on the device, raises
                device_checks(flat.device).look()
            try:
                out = self._apply_on_device(flat, measured, physics is not None, not allow_nonfinite)
            except Exception as err:  # numba-cuda could not compile or launch it: torch's, said once
                fall_back(_DEVICE_PRODUCT, err)
            else:
                return out.view(n, *self.size)  # checked on the device: no wait here
        # compiled unless its kernels are still compiling; the measurement fused where it is compiled
        cpu = flat.device.type == "cpu" and not (torch.is_grad_enabled() and flat.requires_grad)
        fused = cpu and physics is not None and jit.ready("measure", flat.dtype)
        if fused or (cpu and which == "numba"):  # checked there
            camera = kernel_arguments(physics, self.areas, output, seed_value) if fused else ()
            mean, ok = self.compiled_product(flat, not allow_nonfinite, camera), True
        else:
            cols = [self.sparse @ flat[k].unsqueeze(1) for k in range(n)]  # contiguous planes: no transpose
            mean = (
                torch.cat(cols, 1).T.reshape(n, *self.size).contiguous()
                if n
                else flat.new_zeros(0, *self.size)
            )
            ok = allow_nonfinite or all_finite(mean)
        if not ok:
            raise_nonfinite(images)
        if physics is None or fused:
            return mean
        return measure(mean, self.areas, physics, output=output, seed=seed)

    def compiled_product(self, flat: torch.Tensor, check: bool, camera: tuple = ()) -> torch.Tensor:
        """The compiled product of float32 CPU planes ``(N, H·W)`` that need no gradient (the fixed
        unit loaded: ``jit.ready("fixed")``): the means ``(N, h, w)``; with ``camera`` (a camera's
        ``measurement.kernel_arguments``, its unit loaded) what that sensor records of them, measured
        in place (`measured_runs_apply`). ``check``: raise ``ValueError`` where NaN/Inf reach the
        means."""
        n = flat.shape[0]
        out = torch.empty((n, *self.size), dtype=torch.float32)
        src = flat.detach() if flat.requires_grad else flat
        x = np.ascontiguousarray((src.resolve_neg() if src.is_neg() else src).numpy())  # a -x view too
        threads = kernels.threads(x.size)  # one for a small image
        planes = out.numpy().reshape(n, self.runs.shape[0])  # (an empty batch too)
        if camera:  # the buffer is this call's own
            bad = kernels.measured_runs_apply(self.runs.arrays(), x, planes, *camera, planes, threads)
        else:
            bad = kernels.runs_apply(self.runs.arrays(), x, planes, threads)
        if bad and check:
            raise_nonfinite(flat)
        return out

    def adjoint(self, grad: torch.Tensor) -> torch.Tensor:
        """The transposed weights applied to ``(N, h, w)``: ``(N, H, W)``, the images' gradient
        of [`apply`][] without physics."""
        self._check_planes(grad, "grad", self.size)
        n = grad.shape[0]
        flat = grad.reshape(n, grad.shape[-2] * grad.shape[-1]).to(torch.float32)
        if n == 0:  # an empty batch
            return grad.new_zeros(0, *self.src_size)
        cols = [self.sparse_t @ flat[k].unsqueeze(1) for k in range(n)]
        return torch.cat(cols, 1).T.reshape(n, *self.src_size).to(grad.dtype).contiguous()

    @staticmethod
    def _check_planes(x: Any, name: str, size: tuple[int, int]) -> None:
        """Refuse, in one line, planes that are not a real ``(N, *size)`` tensor: the products read
        exactly ``size``'s cells of each."""
        if not isinstance(x, torch.Tensor) or x.ndim != 3 or tuple(x.shape[1:]) != size:
            got = f"shape {tuple(x.shape)}" if isinstance(x, torch.Tensor) else type(x).__name__
            raise ArgumentError(name, f"{name} must be a (N, {size[0]}, {size[1]}) tensor, got {got}")
        if x.dtype.is_complex or x.dtype == torch.bool:
            raise ArgumentError(name, f"{name} must hold real numbers, got {x.dtype}")

    def _apply_on_device(
        self, flat: torch.Tensor, measured: tuple, measure: bool, check: bool
    ) -> torch.Tensor:
        """[`apply`][]'s product on a CUDA device (or in the simulator), the measurement fused
        where ``measure`` (``measured``: its arguments, [`device_arguments`][]), NaN and Inf
        checked there with ``check``: one launch."""
        if self._device_runs is None:
            self._device_runs = tuple(torch.from_numpy(a).to(flat.device) for a in self.runs.arrays())
        out = flat.new_empty(flat.shape[0], self.runs.shape[0])
        x = flat.contiguous()
        runs_apply_on_device(self._device_runs, x, out, measured, measure, stream_of(x), check)
        return out

    def labels(self, label: np.ndarray, rule: str = "nearest") -> np.ndarray:
        """Move an integer label map ``(H, W)`` to the sensor grid by ``rule`` (``"nearest"`` or
        ``"majority"``, see [`labels_to_sensor`][]; majority uses these
        weights)."""
        if label.ndim != 2 or label.shape != self.src_size:
            raise ValueError(f"label map must be {self.src_size} (H, W), got shape {label.shape}")
        return labels_to_sensor(label, self.layout, self.size, rule, area=self._area)

    def _area(self, x: torch.Tensor) -> torch.Tensor:
        """The weights applied to ``(K, H, W)`` images: ``(K, h, w)``."""
        flat = x.reshape(x.shape[0], -1).T.to(torch.float32).contiguous().cpu()
        with torch.no_grad():
            out = self.sparse @ flat.to(self.device)
        return out.T.reshape(x.shape[0], *self.size).cpu()


def _torch_csr(w: Any, device: torch.device) -> torch.Tensor:
    """A scipy CSR matrix as a torch sparse CSR tensor on ``device``."""
    with warnings.catch_warnings():  # "sparse CSR support is in beta"
        warnings.simplefilter("ignore", UserWarning)
        return torch.sparse_csr_tensor(
            torch.from_numpy(w.indptr.astype(np.int64)),
            torch.from_numpy(w.indices.astype(np.int64)),
            torch.from_numpy(w.data),
            size=w.shape,
            check_invariants=False,
        ).to(device)


_DEVICE_PRODUCT = "a fixed layout's product"
#: Resamplers of fixed layouts that [`simulate`][layoutwarp.sensor.simulate] keeps, the last four used
#: (see [`resampler_for`][] and [`layoutwarp.caches`][]); ``maxsize`` 0 keeps none, and a fixed
#: layout's every call then runs the compiled exact walk.
RESAMPLERS: LRU[AreaResampler] = LRU("resamplers", 4)


def resampler_for(
    layout: Layout, size: tuple[int, int], src_size: tuple[int, int], tol: float, device: torch.device | str
) -> AreaResampler | None:
    """The [`AreaResampler`][] of a fixed layout of a registered family, built on first use
    and kept ([`RESAMPLERS`][]); ``None`` for a layout whose state its description does not hold
    (an unregistered family), or when the cache keeps none.

    This is how [`simulate`][layoutwarp.sensor.simulate] runs the exact integrator for a fixed layout
    (θ needs no gradient) on float32 images: one sparse product per call after the first. An
    entry holds its weights, about 8 bytes per source pixel (0.87 copies of a float32 RGB image);
    with ``RESAMPLERS.maxsize = 0`` none is built (``None``), and every call runs the compiled walk
    instead, slower (about 6x at 2048x1024 → 257x129: the bench's cached-weights line) but
    holding no weights. A learnable layout's (used without gradient) are its θ's as a training
    step computes it ([`operator_theta`][layoutwarp.operators.base.operator_theta]).
    """
    token, values = layout_token(layout), ops.layout_theta_values(layout)

    def build() -> Layout:  # at the key's θ, not the layout's now: a thread may have set it since
        return ops.layout_of(token, torch.tensor(values, dtype=torch.float64))

    return _kept(token, values, size, src_size, tol, device, build)


def _kept(
    token: str,
    values: tuple[float, ...],
    size: tuple[int, int],
    src: tuple[int, int],
    tol: float,
    device: torch.device | str,
    layout: Callable[[], Layout],
) -> AreaResampler | None:
    """The [`AreaResampler`][] kept in [`RESAMPLERS`][] for the layout of a
    [`layout_token`][layoutwarp.operators.base.layout_token] at θ of ``values`` (keyed by the token
    and them: no layout is made, ``layout()``, for a resampler already kept); ``None`` for an
    unregistered family, or when the cache keeps none."""
    if RESAMPLERS.maxsize == 0 or token.startswith("object:"):
        return None
    key = ((token, values), tuple(size), tuple(src), float(tol), torch.device(device))
    return RESAMPLERS.get(key, lambda: AreaResampler(layout(), size, src, tol=tol, device=device))


# ----------------------------------------------------------------------------------------
# A fixed layout's product as a torch operator
# ----------------------------------------------------------------------------------------
def _check_float32(image: torch.Tensor) -> None:
    """The area weights are float32: ``layoutwarp::area`` takes float32 images (as
    [`simulate`][layoutwarp.sensor.simulate] sends them)."""
    torch._check(
        image.dtype == torch.float32, lambda: f"layoutwarp::area takes float32 images, got {image.dtype}"
    )


def area_call(
    layout: str,
    size: tuple[int, int],
    tol: float,
    physics: str = "",
    output: str = "radiance",
    check: bool = False,
    with_areas: bool = False,
) -> str:
    """The description ``layoutwarp::area`` takes (see [`area_product`][]): the fixed layout's
    token, the sensor's ``size``, ``tol``, the camera's ``physics`` token (``""``: none) and its
    ``output``, whether to ``check`` for NaN/Inf, and whether to return the areas
    (``with_areas``)."""
    return ops.describe_call(
        layout=layout, size=size, tol=tol, physics=physics, output=output, check=check, with_areas=with_areas
    )


def area_product(
    image: torch.Tensor, theta: torch.Tensor, seed: torch.Tensor, call: str
) -> tuple[torch.Tensor, torch.Tensor]:
    """``layoutwarp::area``, the operator of a fixed layout's product (called directly where
    ``operators.base.plain_eager``): the exact means ``(N, h, w)`` of the fixed layout
    ``layout`` (a [`layout_token`][layoutwarp.operators.base.layout_token]) at ``theta`` over
    float32 images ``(N, H, W)`` by its cached area weights ([`resampler_for`][]), where
    ``call`` ([`area_call`][]) holds ``layout``, the sensor's ``size``, ``tol``, ``physics``,
    ``output``, ``check`` and ``with_areas``; with ``with_areas`` also the pixels' areas
    ``(h, w)`` (float64, sensor units; else an empty tensor); with ``physics`` (a camera's
    [`token`][layoutwarp.physics.SensorPhysics.token], ``""``: none) what that sensor records
    in ``output``'s units, fused, its noise drawn from ``seed``. ``check``: raise
    ``ValueError`` where NaN/Inf reach the output. Differentiable in the images (without
    physics: the transposed weights), twice (the product is linear)."""
    _check_float32(image)
    c = ops.read_call(call, "area")
    src = tuple(image.shape[-2:])
    camera = physics_of(c.physics)
    values = ops.theta_values(theta)
    res = _kept(c.layout, values, c.size, src, c.tol, image.device, lambda: ops.layout_of(c.layout, theta))
    if res is None:  # the cache keeps none: the exact walk (and the measurement)
        exact = exact_call(c.layout, c.size, c.tol, check=c.check, dtype=image.dtype)
        means, areas, _, _ = torch.ops.layoutwarp.exact(theta, image, theta.new_empty(0), exact)
        out = means if camera is None else measure(means, areas, camera, output=c.output, seed=seed)
    else:
        out, areas = res.product(image, camera, c.output, seed, not c.check), res.areas
    return out, (areas.clone() if c.with_areas else areas.new_empty(0))


_area = torch.library.custom_op("layoutwarp::area", area_product, mutates_args=())


@_area.register_fake
def _(image, theta, seed, call):
    _check_float32(image)
    c = ops.read_call(call, "area")
    areas = c.size if c.with_areas else (0,)
    return image.new_empty(image.shape[0], *c.size), image.new_empty(areas, dtype=torch.float64)


@torch.library.custom_op("layoutwarp::area_backward", mutates_args=())
def _area_backward(
    grad: torch.Tensor, theta: torch.Tensor, call: str, src_height: int, src_width: int
) -> torch.Tensor:
    """The images' gradient of ``layoutwarp::area`` (without physics) for its ``call``: the
    transposed weights applied to ``grad`` ``(N, h, w)``, ``(N, H, W)``."""
    c = ops.read_call(call, "area_backward")
    src = (src_height, src_width)
    values = ops.theta_values(theta)
    res = _kept(c.layout, values, c.size, src, c.tol, grad.device, lambda: ops.layout_of(c.layout, theta))
    if res is None:
        raise RuntimeError(
            "layoutwarp::area: the area weights' cache was emptied between forward and backward"
        )
    return res.adjoint(grad)


@_area_backward.register_fake
def _(grad, theta, call, src_height, src_width):
    return grad.new_empty(grad.shape[0], src_height, src_width)


def _area_setup(ctx: Any, inputs: tuple, output: tuple) -> None:
    image, theta, _, call = inputs
    c = ops.read_call(call, "area")
    ctx.refused = bool(c.physics)
    if ctx.refused:
        return
    ctx.save_for_backward(theta)
    ctx.args = (area_call(c.layout, c.size, c.tol), image.shape[-2], image.shape[-1])


def _area_grad(ctx: Any, grad: torch.Tensor, grad_areas: torch.Tensor) -> tuple:
    if ctx.refused:
        raise RuntimeError("layoutwarp::area with physics has no gradient; measure(apply(images)) has")
    (theta,) = ctx.saved_tensors
    return _area_backward(grad, theta, *ctx.args), None, None, None


def _area_backward_setup(ctx: Any, inputs: tuple, output: torch.Tensor) -> None:
    _, theta, call, *_ = inputs
    ctx.save_for_backward(theta)
    ctx.call = call


def _area_backward_grad(ctx: Any, grad: torch.Tensor) -> tuple:
    (theta,) = ctx.saved_tensors
    seed = torch.zeros((), dtype=torch.int64)
    forward, _ = torch.ops.layoutwarp.area(grad, theta, seed, ctx.call)
    return forward, None, None, None, None


_area.register_autograd(_area_grad, setup_context=_area_setup)
_area_backward.register_autograd(_area_backward_grad, setup_context=_area_backward_setup)
ops.register(_area, fold=0, outputs=("image", "shared"))
ops.register(_area_backward)
