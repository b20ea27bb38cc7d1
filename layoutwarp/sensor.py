"""The differentiable sensor: [`simulate`][] and its [`SensorLayer`][] module."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import torch
from torch import Tensor, nn

from .checks import (
    SEED_MAX,
    ArgumentError,
    check_bool,
    check_choice,
    check_generator,
    check_int,
    check_memory,
    check_number,
    check_shape,
    check_size,
    warn_if_elsewhere,
    warn_if_finer,
)
from .doctor import RANK_SEEDS, world
from .integrators import (
    RADIANCES,
    Radiance,
    data_tolerance,
    integrate_exact,
    integrate_montecarlo,
    integrate_point,
    integrate_separable,
)
from .layoutfile import load_layout, save_layout
from .layouts import Layout, make_layout, wants_grad
from .measurement import measure, noise_seed
from .operators.areas import areas_call
from .operators.base import (
    backend,
    layout_token,
    operator_theta,
    plain_eager,
    random_seed,
    refuse_forward_ad,
    refuse_grad_transforms,
)
from .physics import SensorPhysics, apply_psf, as_physics, check_output
from .resampler import RESAMPLERS, area_call, area_product, resampler_for

__all__ = ["METHODS", "SensorLayer", "SimulationPlan", "plan_simulation", "simulate"]

_NO_SEED = torch.zeros((), dtype=torch.int64)  # the seed of an operator that draws nothing
#: The integrators [`simulate`][] runs.
METHODS = ("exact", "separable", "montecarlo", "point")
_OPTIONS = {"radiance", "tol", "samples", "grad", "seed", "generator", "allow_nonfinite"}


@dataclass(frozen=True)
class SimulationPlan:
    """What [`simulate`][] does for a layout, size and options, and why.

    Attributes:
        method: the integrator that runs (``"separable"``, ``"exact"``, ``"montecarlo"``,
            ``"point"``).
        radiance: ``"box"``, ``"bilinear"`` or ``"callable"``.
        error_bound: guaranteed bound on each pixel's error relative to the image's value
            range (0 for exact straight-edged pixels; ``tol`` for curved ones; ``None`` for
            the sampling integrators, whose error depends on the image).
        details: integrator-specific numbers (segments, subdivisions, samples).
        reason: one line on why this method was chosen.
    """

    method: str
    radiance: str
    error_bound: float | None
    details: dict[str, Any] = field(default_factory=dict)
    reason: str = ""


def plan_simulation(
    layout: Layout,
    size: tuple[int, int],
    method: str = "exact",
    *,
    radiance: str | None = None,
    tol: float | None = None,
    samples: int = 4,
    callable_radiance: bool = False,
    dtype: torch.dtype = torch.float32,
) -> SimulationPlan:
    """Choose the integrator for ``method`` (see [`simulate`][]) without running it.

    ``dtype`` is the input image's dtype; with ``tol=None`` it sets the tolerance
    ([`data_tolerance`][]).

    Examples:
        >>> from layoutwarp import CurvLayout
        >>> plan_simulation(CurvLayout((0.3, 0.1)), (8, 8), tol=1e-4).error_bound
        0.0001
    """
    check_size(size)
    check_choice(method, METHODS, "method")
    if radiance is not None:
        check_choice(radiance, RADIANCES, "radiance")
    if tol is None:
        tol, why = data_tolerance(dtype)
    else:
        tol, why = check_number(tol, "tol", 0, lo_open=True), "tol given"
    rad = "callable" if callable_radiance else radiance
    if method in ("exact", "separable"):
        if callable_radiance:
            raise ValueError(
                f"method={method!r} integrates a pixel image exactly; a callable radiance "
                "needs method='montecarlo' or 'point'"
            )
        if rad not in (None, "box"):
            raise ValueError(
                f"method={method!r} integrates box radiance (piecewise-constant pixels); "
                f"radiance={radiance!r} needs method='montecarlo' or 'point'"
            )
        if layout.separable:
            return SimulationPlan(
                "separable", "box", 0.0, {}, "separable layout: per-axis overlap weights, exact"
            )
        if method == "separable":
            raise ValueError(
                "method='separable' needs a separable layout (uniform, rect or spline), "
                f"got {type(layout).__name__}"
            )
        if layout.straight_edges:
            return SimulationPlan(
                "exact", "box", 0.0, {"segments_per_piece": 1}, "straight edges (between kinks): exact"
            )
        return SimulationPlan(
            "exact", "box", float(tol), {"tol": float(tol)}, f"curved edges: polylines within tol ({why})"
        )
    samples = check_int(samples, "samples", 1)
    rad = rad or "bilinear"
    if method == "montecarlo":
        return SimulationPlan(
            "montecarlo", rad, None, {"samples_per_pixel": int(samples) ** 2}, "stratified Monte Carlo"
        )
    return SimulationPlan("point", rad, None, {}, "one sample at each deformed pixel centre")


def _prepare(image: Tensor) -> tuple[Tensor, torch.dtype, tuple[int, ...]]:
    if not isinstance(image, Tensor):
        kind = type(image).__name__
        raise TypeError(f"image must be a torch.Tensor (B, C, H, W) or a callable, got {kind}")
    if image.ndim not in (3, 4):  # the pattern parsed only to word the error (it cost a small call 10 %)
        check_shape(image, "B C H W|C H W", "image")
    if image.shape[-1] == 0 or image.shape[-2] == 0:
        raise ValueError(f"image height and width must be >= 1, got {tuple(image.shape[-2:])}")
    lead = tuple(image.shape[:-2])
    if image.dtype == torch.uint8:
        out_dtype = torch.float32
        work = image.to(torch.float32) / 255
    elif image.is_floating_point():
        out_dtype = image.dtype
        work = image if image.dtype in (torch.float32, torch.float64) else image.to(torch.float32)
    else:
        raise TypeError(f"image dtype must be floating point or uint8, got {image.dtype}")
    return work.reshape(-1, *work.shape[-2:]), out_dtype, lead


def simulate(
    image: Tensor | Radiance,
    layout: Layout,
    size: tuple[int, int],
    method: str = "exact",
    *,
    radiance: str | None = None,
    tol: float | None = None,
    samples: int = 4,
    grad: str = "reynolds",
    seed: int | None = None,
    generator: torch.Generator | None = None,
    allow_nonfinite: bool = False,
    physics: SensorPhysics | dict | None = None,
    output: str = "radiance",
    return_plan: bool = False,
    noise: Tensor | None = None,
) -> Tensor | tuple[Tensor, SimulationPlan]:
    """Simulate a sensor with pixel layout ``layout``: the mean radiance over every pixel, or,
    with ``physics``, what a real sensor records of it (optics, photons, noise, full well, ADC).

    Args:
        image: ``(B, C, H, W)`` (or ``(C, H, W)``) radiance image, float or uint8 (uint8 is
            scaled to ``[0, 1]``; float16/bfloat16 are computed in float32, and so is
            everything inside an autocast (mixed-precision) context); or a callable
            radiance ``L(points (..., 2)) -> (..., C)`` in sensor coordinates (the paper's
            black box, e.g. a renderer), for ``"montecarlo"`` and ``"point"``.
        layout: the pixel layout (θ may be learnable; gradients flow to it).
        size: sensor size ``(h, w)``.
        method: ``"exact"`` (box radiance over the exact pixel polygons; runs the cheaper
            ``"separable"`` integrator for rectangular layouts), ``"separable"``,
            ``"montecarlo"`` or ``"point"``.
        radiance: ``"box"`` (each source pixel a constant square; the only choice for exact
            methods) or ``"bilinear"`` (the paper's choice, default for sampling methods).
        tol: the accuracy a scene needs: bound on each pixel's error relative to the
            image's value range, spent on the polyline approximation of curved edges;
            default: what the image's dtype needs ([`data_tolerance`][]: 0.25/255 for
            uint8, 2⁻¹² for float32). The plan states the bound and why.
        samples: ``s`` for Monte Carlo (``s²`` samples per pixel).
        grad: Monte Carlo θ-gradient estimator, ``"reynolds"`` or ``"autograd"``.
        seed: the call's randomness: the Monte Carlo jitter's draws (those of a generator seeded
            with it on the image's device, so one seed gives other samples on another device) and,
            with ``physics`` and no ``physics.seed``, the noise's. The same seed, the same output,
            eager or under ``torch.compile``.
        generator: instead of ``seed`` (not with it), a generator the Monte Carlo jitter and the
            physics' noise draw from (eager only: a generator object cannot enter a compiled
            graph; pass ``seed``).
        allow_nonfinite: let NaN/Inf through instead of raising ``ValueError``.
        physics: a [`SensorPhysics`][] or its dict (see [`layoutwarp.physics`][]): the PSF
            blurs the image, the pixel means become photons in proportion to each pixel's area,
            then noisy electrons, clipped at the full well and quantised. ``None``: the
            noise-free mean, bit for bit as without physics.
        output: with ``physics``: ``"radiance"`` (default: the ISP's estimate in the image's
            units, whose expectation is the noise-free mean), ``"electrons"`` or ``"dn"``
            (these two need ``physics``).
        return_plan: also return the [`SimulationPlan`][] that ran.
        noise: with ``physics``, a 0-d int64 tensor the noise is drawn from (what a
            [`SensorLayer`][]'s seeded sequence passes; see
            [`noise_seed`][layoutwarp.measurement.noise_seed]).

    Returns:
        ``(B, C, h, w)`` (or ``(C, h, w)``) in the image's floating dtype (float32 for uint8);
        with ``return_plan``, ``(output, plan)``. Empty batches or channel counts give empty
        outputs of the right shape.
    """
    if not torch.compiler.is_compiling() and torch.is_inference_mode_enabled():  # the caches' tensors
        with torch.inference_mode(False), torch.no_grad():  # must serve autograd later: made outside it
            return simulate(**locals())
    # every option at its default (tested one by one, not with all(): a small call's microseconds)
    defaults = radiance is None and tol is None and physics is None and noise is None
    defaults = defaults and seed is None and generator is None
    if defaults and method == "exact" and output == "radiance" and return_plan is False:  # no plan
        out = _fixed_plain(image, layout, size, allow_nonfinite)
        if out is not None:
            warn_if_finer(size, (image.shape[-2], image.shape[-1]))  # (its stack level: the caller)
            return out
    size = check_size(size)
    check_memory(size)
    refuse_grad_transforms()
    if not isinstance(layout, Layout):
        raise TypeError(f"layout must be a layoutwarp Layout, got {type(layout).__name__}")
    refuse_forward_ad(image, layout.rho)
    if layout.learnable_param:  # a step may have made its θ no layout (a fixed θ was checked when set)
        layout.check_theta_now()
    allow_nonfinite, return_plan = (
        check_bool(allow_nonfinite, "allow_nonfinite"),
        check_bool(return_plan, "return_plan"),
    )
    generator = check_generator(generator, seed=seed)
    seed = check_int(seed, "seed", 0, SEED_MAX, optional=True)
    is_callable = callable(image) and not isinstance(image, Tensor)
    dtype = image.dtype if isinstance(image, Tensor) else torch.float32
    plan = plan_simulation(
        layout,
        size,
        method,
        radiance=radiance,
        tol=tol,
        samples=samples,
        callable_radiance=is_callable,
        dtype=dtype,
    )
    # the tolerance every geometry of this call uses: the plan's for curved edges, else the data's
    # (meshes of straight edges ignore it; area weights and physics' pixel areas are keyed by it)
    tol = plan.details.get("tol", data_tolerance(dtype)[0] if tol is None else tol)
    physics = as_physics(physics)
    check_output(output, physics)
    if physics is not None:
        if is_callable and physics.psf is not None:
            raise ValueError("physics.psf blurs a source image; a callable radiance must include its optics")
    run = _Integration(
        plan, layout, size, tol, samples, grad, generator, seed, noise, physics, output, allow_nonfinite
    ).integrate
    if is_callable:
        out = run(image)[None]
        return (out, plan) if return_plan else out
    work, out_dtype, lead = _prepare(image)
    warn_if_finer(size, tuple(work.shape[-2:]))
    if layout.rho.numel():  # a layout with a θ to copy
        warn_if_elsewhere(layout.rho.device, work.device)
    if work.shape[0] == 0:
        out = work.new_zeros(*lead, *size).to(out_dtype)
        # nothing to integrate, but the output stays in θ's and the image's graph, as a module's would
        ties = [t.sum() for t in (layout.rho, work) if torch.is_grad_enabled() and t.requires_grad]
        if ties:
            out = out + (sum(ties) * 0).to(out_dtype)
    else:
        out = run(work)  # exact methods check their means
        if not (allow_nonfinite or plan.method in ("exact", "separable")):  # samples may miss a bad
            out = torch.ops.layoutwarp.guard_finite(out, work, "image")  # pixel: look at the input
        out = (out if out.dtype == out_dtype else out.to(out_dtype)).reshape(*lead, *size)
    return (out, plan) if return_plan else out


_FLOAT32_TOL = data_tolerance(torch.float32)[0]


def _fixed_plain(image: Any, layout: Any, size: Any, allow_nonfinite: Any) -> Tensor | None:
    """A fixed layout's means of float32 CPU images by its kept weights' compiled product, where
    the call needs nothing of [`simulate`][]'s plan (method ``"exact"`` and its defaults, an eager
    call that no gradient, transform or mode follows): most inference, preprocessing and
    DataLoader calls, whose small images' time went mostly to the plan. The route the plan would
    choose, the same resampler (so the same values, bit for bit); ``None`` where any of that does
    not hold, and the plan decides."""
    if not (type(image) is Tensor and image.dtype == torch.float32 and image.device.type == "cpu"):
        return None
    if image.ndim not in (3, 4) or not image.numel() or type(allow_nonfinite) is not bool:
        return None
    if not (type(size) is tuple and len(size) == 2 and type(size[0]) is int and type(size[1]) is int):
        return None
    if size[0] <= 0 or size[1] <= 0:
        return None
    rho = layout.rho if isinstance(layout, Layout) else None
    if rho is None or rho.device.type != "cpu" or RESAMPLERS.maxsize == 0:
        return None
    if (torch.is_grad_enabled() and wants_grad(rho)) or not plain_eager(image):
        return None
    if torch.is_autocast_enabled("cpu") or layout_token(layout).startswith("object:"):
        return None
    if layout.learnable_param:  # used without gradient (evaluation): its θ as a step left it
        layout.check_theta_now()
    if backend(image, "fixed") != "numba":  # the compiled product ready (not numba's CUDA simulator)
        return None
    refuse_forward_ad(image, rho)  # a tangent is refused, as the plan's route refuses it
    check_memory(size)
    src = (image.shape[-2], image.shape[-1])
    res = resampler_for(layout, size, src, _FLOAT32_TOL, "cpu")
    out = res.compiled_product(image.reshape(-1, src[0] * src[1]), not allow_nonfinite)
    return out.view(*image.shape[:-2], *size)


@dataclass(frozen=True)
class _Integration:
    """One [`simulate`][] call's integrator, with the options its plan needs."""

    plan: SimulationPlan
    layout: Layout
    size: tuple[int, int]
    tol: float
    samples: int
    grad: str
    generator: torch.Generator | None
    seed: int | None
    noise: Tensor | None = None
    physics: SensorPhysics | None = None
    output: str = "radiance"
    allow_nonfinite: bool = True

    def integrate(self, work: Tensor | Radiance) -> Tensor:
        """Integrate ``work`` (``(N, H, W)`` or a callable radiance) with autocast off: the sensor
        integrates in float32 (float64 for float64 input) inside any mixed-precision context, as
        its tolerances assume. With physics: the PSF first, the measurement after."""
        device = work.device.type if isinstance(work, Tensor) else self.layout.rho.device.type
        route = self._route(work)  # decided once: nothing below asks again
        if device in ("cpu", "cuda", "mps", "xpu") and torch.is_autocast_enabled(device):
            with torch.autocast(device_type=device, enabled=False):
                return self._measured(work, route)
        return self._measured(work, route)

    def _route(self, work: Tensor | Radiance) -> str:
        """This call's route: ``"weights"`` (a fixed layout's cached area weights,
        [`resampler_for`][]: the exact or separable method, θ needing no gradient, a registered
        family, float32 images and a cache that keeps weights), else the plan's integrator."""
        method = self.plan.method
        # a ρ batched under vmap too: the learnable path, whose θ reaches autograd (the weights'
        # would leave θ without gradient)
        fixed = not (torch.is_grad_enabled() and wants_grad(self.layout.rho))
        if method not in ("exact", "separable") or not fixed or RESAMPLERS.maxsize == 0:
            return method
        if not (isinstance(work, Tensor) and work.dtype == torch.float32):
            return method
        return method if layout_token(self.layout).startswith("object:") else "weights"

    def _measured(self, work: Tensor | Radiance, route: str) -> Tensor:
        if self.physics is None:
            return self._dispatch(work, route)
        if not (isinstance(work, Tensor) and self.physics.psf is not None):
            return self._recorded(work, route)
        # the blur spreads a bad value over its neighbours: the record checked against the source
        out = replace(self, allow_nonfinite=True)._recorded(apply_psf(work, self.physics), route)
        return out if self.allow_nonfinite else torch.ops.layoutwarp.guard_finite(out, work, "image")

    def _noise_seed(self) -> Tensor:
        """The 0-d tensor the physics' noise is drawn from (see [`simulate`][]'s ``seed``)."""
        seed = self.noise
        if seed is None and self.generator is None and self.seed is not None and self.physics.seed is None:
            seed = random_seed(None, self.seed + 2)  # the jitter and its boundary flux take seed, seed + 1
        return noise_seed(self.physics, self.generator, seed)

    def _recorded(self, work: Tensor | Radiance, route: str) -> Tensor:
        """What the sensor records of ``work`` (after the optics)."""
        seed = self._noise_seed()
        grad = torch.is_grad_enabled() and isinstance(work, Tensor) and work.requires_grad
        if route == "weights" and not grad:  # the cached weights and the measurement, fused
            out, _ = self._area(work, self.physics.token, seed, False)
            return out
        if self.plan.method in ("exact", "separable"):  # the integrator's own areas (a learnable
            mean, areas = self._dispatch(work, route, with_areas=True)  # compiled path: no torch mesh)
        else:  # the sampling integrators: the areas of the polygons the pixels are
            mean = self._dispatch(work, route)
            call = areas_call(layout_token(self.layout), self.size, float(self.tol))
            areas = torch.ops.layoutwarp.pixel_areas(operator_theta(self.layout), call)
        return measure(mean, areas, self.physics, output=self.output, seed=seed)

    def _area(self, work: Tensor, physics: str, seed: Tensor, with_areas: bool) -> tuple[Tensor, Tensor]:
        """``layoutwarp::area`` on ``work``: the means (or, with ``physics``, the record) and areas."""
        theta = operator_theta(self.layout)
        token, check = layout_token(self.layout), not self.allow_nonfinite
        call = area_call(token, self.size, float(self.tol), physics, self.output, check, with_areas)
        op = area_product if plain_eager(work, theta, seed) else torch.ops.layoutwarp.area
        return op(work, theta, seed, call)

    def _dispatch(
        self, work: Tensor | Radiance, route: str, with_areas: bool = False
    ) -> Tensor | tuple[Tensor, Tensor]:
        """The pixel means (and, for the exact and separable methods ``with_areas``, the pixels'
        areas in sensor units, from the integrator). An exact method's are checked for NaN/Inf
        inside its operator (unless ``allow_nonfinite``): every source pixel reaches some sensor
        pixel with positive weight, so a bad input value always reaches its (small) output."""
        plan, layout, size = self.plan, self.layout, self.size
        if plan.method in ("separable", "exact"):
            if route == "weights":  # one sparse product: the exact integral of a fixed layout
                means, areas = self._area(work, "", _NO_SEED, with_areas)
                return (means, areas) if with_areas else means
            check = {"allow_nonfinite": self.allow_nonfinite, "return_areas": with_areas}
            if plan.method == "separable":
                return integrate_separable(work, layout, size, **check)
            dtype = work.dtype if self.physics is None else torch.float64  # the means the output keeps
            return integrate_exact(work, layout, size, tol=self.tol, dtype=dtype, **check)
        radiance = "bilinear" if plan.radiance == "callable" else plan.radiance  # ignored for callables
        if plan.method == "montecarlo":
            return integrate_montecarlo(
                work,
                layout,
                size,
                samples=self.samples,
                radiance=radiance,
                grad=self.grad,
                generator=self.generator,
                seed=self.seed,
            )
        return integrate_point(work, layout, size, radiance=radiance)


class SensorLayer(nn.Module):
    """A drop-in sensor: high-resolution image in, sensor image of ``size`` out.

    θ starts at 0 (the uniform layout) unless ``theta`` is given, and is trained with the
    network when ``learn=True``; ``learn=False`` freezes it (the uniform baseline).

    Args:
        size: sensor size ``(h, w)``.
        layout: a registered family name (``"rect"``, ``"curv"``, ``"uniform"``, ...) or a
            [`Layout`][] (used as it is, learnable or not).
        method: integrator (see [`simulate`][]).
        learn: train θ (for a family name; default ``True``).
        theta: initial θ (for a family name; default 0, the uniform layout).
        bound: bound on ``|θ|`` (for a family name; default 1). With a [`Layout`][], these three
            are refused: the layout brings its own.
        physics: a [`SensorPhysics`][] (or its dict, as files store it): the
            layer records what a real sensor would (see [`simulate`][]). With ``physics.seed``
            the layer's noise is a seeded sequence (new noise every call, the same sequence in
            every run; each rank of a torch.distributed process group a sequence of its own);
            without, fresh noise.
        output: with ``physics``: ``"radiance"``, ``"electrons"`` or ``"dn"`` (these two need ``physics``).
        **options: further [`simulate`][] options (``tol``, ``samples``, ``radiance``, ...).

    Examples:
        >>> layer = SensorLayer((4, 4), "curv")
        >>> layer(torch.rand(8, 1, 28, 28)).shape
        torch.Size([8, 1, 4, 4])
    """

    def __init__(
        self,
        size: tuple[int, int],
        layout: str | Layout = "rect",
        method: str = "exact",
        *,
        learn: bool | None = None,
        theta: Sequence[float] | Tensor | None = None,
        bound: float | None = None,
        physics: SensorPhysics | dict | None = None,
        output: str = "radiance",
        **options: Any,
    ) -> None:
        super().__init__()
        self.size = check_size(size)
        check_memory(self.size)
        self.physics = as_physics(physics)
        self.output = check_output(output, self.physics)
        # the seeded noise's place in its sequence (a tensor: a compiled graph counts it in place)
        self.register_buffer("noise_calls", torch.zeros((), dtype=torch.int64), persistent=False)
        if isinstance(layout, Layout):
            given = {k: v for k, v in (("learn", learn), ("theta", theta), ("bound", bound)) if v is not None}
            if given:
                raise ArgumentError(
                    next(iter(given)),
                    f"{', '.join(f'{k}={v!r}' for k, v in given.items())} set up a layout made by name; "
                    f"a {type(layout).__name__} brings its own (set θ with layout.set_theta, learning "
                    "with learn= when making it)",
                )
            self.layout = layout
        else:
            learn = True if learn is None else learn
            self.layout = make_layout(layout, theta, bound=1.0 if bound is None else bound, learn=learn)
        self.method = check_choice(method, METHODS, "method")
        unknown = sorted(set(options) - _OPTIONS)
        if unknown:
            raise TypeError(f"unknown simulate option(s) {unknown}; expected some of {sorted(_OPTIONS)}")
        self.options = options
        check_generator(options.get("generator"), seed=options.get("seed"))
        self.describe()  # refuse bad options now, not at the first batch

    @property
    def theta(self) -> Tensor:
        """The layout's constrained parameters θ."""
        return self.layout.theta

    def forward(self, image: Tensor) -> Tensor:
        """``(B, C, H, W)`` image to ``(B, C, h, w)`` sensor image.

        A learnable layout is first pulled back into its valid set
        ([`Layout.guard_`][layoutwarp.layouts.base.Layout.guard_]:
        a no-op for the paper's families, the fold guard of a
        [`GridLayout`][layoutwarp.layouts.grid.GridLayout]),
        so any training loop gets the guarded step.
        """
        if self.layout.learnable:
            self.layout.guard_()
        if self.physics is None:
            return simulate(image, self.layout, self.size, self.method, **self.options)
        options = dict(self.options)
        if self.physics.seed is not None and "generator" not in options and "seed" not in options:
            seed = (self.physics.seed + world()[0] * RANK_SEEDS) % (SEED_MAX + 1)
            options["noise"] = torch.ops.layoutwarp.seed_sequence(self.noise_calls, seed)
            self.noise_calls.add_(1)  # a seeded sequence: new noise every call, the same every run
        return simulate(
            image, self.layout, self.size, self.method, physics=self.physics, output=self.output, **options
        )

    def describe(self, dtype: torch.dtype = torch.float32) -> SimulationPlan:
        """The plan the layer runs with its current settings for images of ``dtype``."""
        return plan_simulation(
            self.layout,
            self.size,
            self.method,
            radiance=self.options.get("radiance"),
            tol=self.options.get("tol"),
            samples=self.options.get("samples", 4),
            dtype=dtype,
        )

    def save_layout(self, path: str | Path, **extra: Any) -> Path:
        """Write the layer's layout, sensor size, method and physics (when set) to a JSON file
        (see [`save_layout`][])."""
        if self.physics is not None:
            extra = {"physics": self.physics.to_dict(), **extra}
        return save_layout(self.layout, path, self.size, method=self.method, **extra)

    @classmethod
    def from_layout_file(
        cls, path: str | Path, size: tuple[int, int] | None = None, *, learn: bool = False, **kwargs: Any
    ) -> SensorLayer:
        """A layer with the layout saved at ``path`` (θ frozen unless ``learn``).

        ``size`` defaults to the sensor size stored in the file; ``method`` to the stored
        method, else ``"exact"``; ``physics`` to the stored physics, if any; other keyword
        arguments go to [`SensorLayer`][].
        """
        layout, info = load_layout(path, learn=learn)
        size = size if size is not None else info["size_hw"]
        if size is None:
            raise ValueError(f"{path} stores no sensor size; pass size=(h, w)")
        extra = info.get("extra") or {}
        kwargs.setdefault("method", extra.get("method", "exact"))
        if extra.get("physics") is not None:
            kwargs.setdefault("physics", extra["physics"])
        return cls(tuple(size), layout, **kwargs)

    def extra_repr(self) -> str:
        h, w = self.size
        light = "" if self.physics is None else f", physics={self.physics.photons_per_um2:g} photons/µm²"
        return f"size=({h}, {w}), method={self.method!r}{light}"
