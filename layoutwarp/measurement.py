"""The sensor's measurement: pixel means to what a sensor records (steps 3–8 of
[`layoutwarp.physics`][]), as [`measure`][] and the torch operators it runs
(``layoutwarp::measure``, ``full_well``, ``patterns``, ``draws``): one compiled pass on the CPU
(`sensor_measure`, or its plain twin while that compiles), one kernel on a CUDA device, or torch
operations where a gradient is needed."""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from typing import Any

import numpy as np
import torch
from torch import Tensor

from . import jit, kernels
from .caches import LRU, tensor_token
from .checks import ArgumentError, check_choice, check_generator, check_shape, check_tensor
from .kernels.device import fall_back, stream_of
from .kernels.noise import measure_on_device
from .operators import base as ops
from .operators.base import random_seed
from .physics import OUTPUTS, SensorPhysics, as_physics, physics_of

__all__ = ["device_arguments", "kernel_arguments", "measure", "noise_seed"]

#: The noise models' codes in the compiled kernel.
NOISE_CODES = {"none": 0, "poisson": 1, "gaussian": 2}


@functools.lru_cache(maxsize=8)
def _standard_patterns(seed: int, size: tuple[int, int]) -> Tensor:
    """``(2, h, w)`` float64 standard normals from ``seed``, drawn once per sensor (do not modify)."""
    return torch.randn(2, *size, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)


def noise_seed(
    physics: SensorPhysics, generator: torch.Generator | None = None, seed: Tensor | None = None
) -> Tensor:
    """The 0-d int64 tensor the measurement's temporal noise is drawn from: ``seed`` (e.g. a
    [`SensorLayer`][layoutwarp.sensor.SensorLayer]'s seeded sequence), else a draw of
    ``generator``, else ``physics.seed``'s (the same noise every call), else a fresh draw."""
    if seed is not None:
        return seed
    if generator is None and physics.seed is not None:
        return torch.tensor(physics._noise_seed, dtype=torch.int64)
    return random_seed(generator)


def measure(
    mean: Tensor,
    areas: Tensor,
    physics: SensorPhysics,
    *,
    output: str = "radiance",
    generator: torch.Generator | None = None,
    seed: Tensor | None = None,
) -> Tensor:
    """Steps 3–8 of the module docstring: pixel means ``(N, h, w)`` to a recorded sensor image.

    Args:
        mean: the integrators' mean radiance per pixel (image units; 1.0 is ``photons_per_um2``).
        areas: pixel areas ``(h, w)`` in sensor units (the square ``[-1, 1]²``: they sum to 4),
            e.g. [`areas`][layoutwarp.mesh.PixelMesh.areas]; differentiable in θ.
        physics: the camera (or its dict,
            [`SensorPhysics.to_dict`][layoutwarp.physics.SensorPhysics.to_dict]).
        output: ``"radiance"`` (the ISP's estimate of ``mean``), ``"electrons"`` (after the full
            well, before the ADC) or ``"dn"`` (the ADC's digital numbers).
        generator: the noise's random generator (default: ``physics.seed``'s draws, or torch's
            global generator when that is ``None``).
        seed: instead, a 0-d int64 tensor the noise is drawn from ([`noise_seed`][]).

    Returns:
        ``(N, h, w)`` in ``mean``'s dtype.

    Raises:
        ArgumentError: an argument of the wrong kind or shape (naming it), or a full well below
            the read noise in the smallest pixel (a ``ValueError``).
    """
    physics, seed = _check_measure(mean, areas, physics, output, generator, seed)
    seed = noise_seed(physics, generator, seed)
    if torch.is_grad_enabled() and (mean.requires_grad or areas.requires_grad):
        return _measure_torch(mean, areas, physics, output, seed)
    return torch.ops.layoutwarp.measure(mean, areas, physics.token, output, seed)


def _check_measure(
    mean: Any, areas: Any, physics: Any, output: str, generator: Any, seed: Any
) -> tuple[SensorPhysics, Tensor | None]:
    """[`measure`][]'s arguments checked, each in one line naming it: the camera (a dict of
    one too) and the seed as [`measure`][] takes them."""
    check_shape(mean, "* h w", "mean")
    if not mean.is_floating_point():
        raise ArgumentError("mean", f"mean must be a floating-point tensor, got {mean.dtype}")
    check_tensor(areas, "areas")
    if tuple(areas.shape) != tuple(mean.shape[-2:]) or not areas.is_floating_point():
        raise ArgumentError(
            "areas",
            f"areas must be the pixels' floating-point (h, w) = {tuple(mean.shape[-2:])} of mean "
            f"(..., h, w), got {tuple(areas.shape)} {areas.dtype}",
        )
    camera = as_physics(physics)
    if camera is None:
        raise ArgumentError("physics", "physics must be a SensorPhysics or its dict, got None")
    check_choice(output, OUTPUTS, "output")
    check_generator(generator, seed=seed)
    if seed is not None and not (isinstance(seed, Tensor) and seed.ndim == 0 and seed.dtype == torch.int64):
        what = f"a {seed.dtype} tensor of shape {tuple(seed.shape)}" if isinstance(seed, Tensor) else seed
        raise ArgumentError("seed", f"seed must be a 0-d int64 tensor (noise_seed), got {what!s:.60}")
    return camera, seed


@torch.library.custom_op("layoutwarp::measure", mutates_args=())
def _measure(mean: Tensor, areas: Tensor, physics: str, output: str, seed: Tensor) -> Tensor:
    """[`measure`][] without gradient: one compiled pass on the CPU (`sensor_measure`), one kernel
    on a CUDA device, or the torch path; the camera as its
    [`token`][layoutwarp.physics.SensorPhysics.token]."""
    if mean.ndim < 2 or areas.shape != mean.shape[-2:]:
        ops.refuse(
            "measure",
            "areas",
            f"must be the pixels' (h, w) = {tuple(mean.shape[-2:])}, got {tuple(areas.shape)}",
        )
    camera = physics_of(physics)
    kernel_dtype = mean.dtype if mean.dtype == torch.float32 else torch.float64  # its two builds
    if ops.backend(mean, "measure", name=_DEVICE_MEASURE) == "cuda":
        args = device_arguments(camera, areas, mean.device, output, ops.seed_value(seed))
        try:
            return _measure_on_device(mean, args)
        except Exception as err:  # numba-cuda could not compile or launch it: the torch path, said once
            fall_back(_DEVICE_MEASURE, err)
    kernel = None  # on the CPU the noise's draws come from compiled code (compiled here if need be)
    if mean.device.type == "cpu":
        kernel = jit.compiled("measure", kernel_dtype, kernels.sensor_measure, kernels.sensor_measure_plain)
    if kernel is not None:
        return _measure_compiled(mean, kernel_arguments(camera, areas, output, ops.seed_value(seed)), kernel)
    return _measure_torch(mean, areas, camera, output, seed).contiguous()


@_measure.register_fake
def _(mean, areas, physics, output, seed):
    return mean.new_empty(mean.shape)


ops.register(_measure)
_DEVICE_MEASURE = "the sensor's measurement"


def _measure_torch(mean: Tensor, areas: Tensor, physics: SensorPhysics, output: str, seed: Tensor) -> Tensor:
    """[`measure`][] in torch operations, differentiable in the means and the areas (the noise
    reparameterised, the ADC's rounding straight through); the draws from ``seed``."""
    needs_grad = torch.is_grad_enabled() and (mean.requires_grad or areas.requires_grad)
    mode = physics.noise
    if mode == "auto":
        mode = "gaussian" if needs_grad else "poisson"
    a_um2 = areas.to(mean) * physics.um2_per_unit()
    full = None
    if physics.full_well_per_um2 is not None:
        full = torch.ops.layoutwarp.full_well(physics.full_well_per_um2 * a_um2, physics.token)
    eta = physics.quantum_efficiency
    photons = physics.photons_per_um2 * physics.fill_factor * mean * a_um2
    signal, dark = eta * photons, physics.dark_e_per_um2 * a_um2
    if physics.prnu or physics.dsnu:
        prnu, dsnu = torch.ops.layoutwarp.patterns(
            physics.pattern_seed, *mean.shape[-2:], mean.detach()
        ).unbind(0)
        signal = signal * (1 + physics.prnu * prnu)
        dark = dark + physics.dsnu * dsnu
    electrons = signal + dark
    rate = electrons.clamp_min(0)
    if mode != "none":
        shot, read = torch.ops.layoutwarp.draws(rate.detach(), seed, mode, bool(physics.read_noise_e))
        if mode == "poisson":  # the count, the gradient of the mean (0 where it is ±inf)
            electrons = shot + (electrons - electrons.detach()).nan_to_num(0.0)
        else:
            electrons = electrons + torch.sqrt(rate.clamp_min(1e-12)) * shot * (rate > 0)
        if physics.read_noise_e:
            electrons = electrons + physics.read_noise_e * read
    if full is not None:
        electrons = torch.minimum(electrons, full)
    if output == "electrons":
        return electrons
    k = _gain(physics, a_um2)
    dn = k * electrons + physics.black_level_dn
    if physics.adc_bits is not None:
        top = 2**physics.adc_bits - 1
        rounded = dn.detach().round().clamp(0, top)
        # straight through: the value rounded, the gradient kept (0 where dn is ±inf)
        dn = rounded + (dn - dn.detach()).nan_to_num(0.0)
    if output == "dn":
        return dn
    recovered = (dn - physics.black_level_dn) / k - physics.dark_e_per_um2 * a_um2
    return recovered / (eta * physics.photons_per_um2 * physics.fill_factor * a_um2)


def _gain(physics: SensorPhysics, a_um2: Tensor) -> float | Tensor:
    """[`SensorPhysics.gain`][layoutwarp.physics.SensorPhysics.gain] for pixels of areas
    ``a_um2`` (µm²): a tensor where it depends on the largest (read in the graph, not on the
    host)."""
    if (
        physics.gain_dn_per_e is None
        and physics.adc_bits is not None
        and physics.full_well_per_um2 is not None
    ):
        return (2**physics.adc_bits - 1 - physics.black_level_dn) / (
            physics.full_well_per_um2 * a_um2.detach().max()
        )
    return physics.gain(1.0)


@torch.library.custom_op("layoutwarp::full_well", mutates_args=())
def _full_well_op(full: Tensor, physics: str) -> Tensor:
    """Each pixel's full well in electrons ``full`` (a copy), after the check of
    [`SensorPhysics.full_well`][layoutwarp.physics.SensorPhysics.full_well]:
    a full well not above the read noise is refused. Its gradient passes through."""
    camera = physics_of(physics)
    camera.full_well(full.detach() / camera.full_well_per_um2)
    return full.clone()


@_full_well_op.register_fake
def _(full, physics):
    return torch.empty_like(full)


def _full_well_grad(ctx: Any, grad: Tensor) -> tuple:
    return grad, None


_full_well_op.register_autograd(_full_well_grad, setup_context=ops.no_context)
ops.register(_full_well_op)


@torch.library.custom_op("layoutwarp::patterns", mutates_args=())
def _patterns_op(pattern_seed: int, height: int, width: int, like: Tensor) -> Tensor:
    """The fixed PRNU and DSNU patterns ``(2, h, w)`` (standard normal, from ``pattern_seed``) in
    ``like``'s dtype and on its device."""
    return _standard_patterns(pattern_seed, (height, width)).to(like, copy=True)


@_patterns_op.register_fake
def _(pattern_seed, height, width, like):
    return like.new_empty(2, height, width)


ops.register(_patterns_op)


@torch.library.custom_op("layoutwarp::draws", mutates_args=())
def _draws(rate: Tensor, seed: Tensor, mode: str, read: bool) -> tuple[Tensor, Tensor]:
    """The temporal noise's draws for electron rates ``rate``, from a generator on its device
    seeded with ``seed``: Poisson counts (``mode="poisson"``) or standard normals
    (``"gaussian"``) for the shot noise, then standard normals for the read noise (``read``;
    else zeros)."""
    generator = ops.generator_of(seed, rate.device)
    if mode == "poisson":  # a NaN or infinite mean passed through, as the compiled sampler does;
        # beyond 2⁶² electrons (torch's int64 counts overflow) the count is the mean, rounded down
        drawn = torch.isfinite(rate) & (rate < 2.0**62)
        shot = torch.poisson(torch.where(drawn, rate, 0.0), generator=generator)
        shot = torch.where(drawn, shot, rate.floor())
    else:
        shot = torch.randn(rate.shape, generator=generator, dtype=rate.dtype, device=rate.device)
    if not read:
        return shot.contiguous(), rate.new_zeros(rate.shape)
    return shot.contiguous(), torch.randn(
        rate.shape, generator=generator, dtype=rate.dtype, device=rate.device
    )


@_draws.register_fake
def _(rate, seed, mode, read):
    return rate.new_empty(rate.shape), rate.new_empty(rate.shape)


ops.register(_draws)


#: The compiled measurement's per-sensor inputs, for the last eight (camera, pixel areas) pairs
#: (see [`_compiled_sensor`][] and [`layoutwarp.caches`][]).
SENSORS: LRU[tuple[np.ndarray, ...]] = LRU("sensors", 8)


def _compiled_sensor(physics: SensorPhysics, areas: Tensor) -> tuple[np.ndarray, ...]:
    """The kernel's inputs that depend on the camera and the pixel areas alone: areas in µm²,
    the PRNU and DSNU patterns (float64, flat) and the parameter vector. Kept in [`SENSORS`][],
    the areas tensor recognised by identity and version ([`tensor_token`][layoutwarp.caches.tensor_token]:
    a fixed layout's cached mesh gives the same tensor every call), so a repeated call costs no
    torch operation."""
    return SENSORS.get((physics, tensor_token(areas)), lambda: _sensor_arrays(physics, areas))


def _sensor_arrays(physics: SensorPhysics, areas: Tensor) -> tuple[np.ndarray, ...]:
    a = areas.detach().to("cpu", torch.float64).flatten() * physics.um2_per_unit()
    physics.full_well(a)
    prnu, dsnu = _standard_patterns(physics.pattern_seed, tuple(areas.shape[-2:]))
    none = np.zeros(0)  # a pattern of gain 0 is not read: one cold array less per call
    prnu, dsnu = (z.flatten().numpy() if g else none for z, g in ((prnu, physics.prnu), (dsnu, physics.dsnu)))
    params = np.array(
        [
            physics.photons_per_um2 * physics.fill_factor,
            physics.quantum_efficiency,
            physics.prnu,
            physics.dsnu,
            physics.dark_e_per_um2,
            physics.read_noise_e,
            physics.full_well_per_um2 if physics.full_well_per_um2 is not None else math.inf,
            physics.gain(float(a.max())),
            physics.black_level_dn,
            2**physics.adc_bits - 1 if physics.adc_bits is not None else math.inf,
        ]
    )
    return a.numpy(), prnu, dsnu, params


def kernel_arguments(physics: SensorPhysics, areas: Tensor, output: str = "radiance", seed: int = 0) -> tuple:
    """The arguments of `sensor_measure` after the means, for
    [`measure`][] without gradient on the CPU (``noise="auto"``: exact Poisson draws): the
    pixels' inputs (kept per camera and areas), the noise's ``seed`` ([`noise_seed`][]'s value),
    the noise model's and ``output``'s codes."""
    check_choice(output, OUTPUTS, "output")
    mode = "poisson" if physics.noise == "auto" else physics.noise
    return (*_compiled_sensor(physics, areas), int(seed), NOISE_CODES[mode], OUTPUTS.index(output))


#: The pixel inputs of [`kernel_arguments`][] copied to a device, for the last eight (camera,
#: pixel areas, device) triples ([`layoutwarp.caches`][]).
ON_DEVICE: LRU[tuple[Tensor, ...]] = LRU("sensors on devices", 8)


def device_arguments(
    physics: SensorPhysics,
    areas: Tensor,
    device: torch.device,
    output: str = "radiance",
    seed: int = 0,
) -> tuple:
    """[`kernel_arguments`][] with the pixel inputs (areas in µm², fixed patterns, parameters) as
    float64 tensors on ``device``, copied there once per camera and areas (a repeated call
    copies nothing): what the CUDA kernels of the measurement take."""
    host = kernel_arguments(physics, areas, output, seed)
    key = (physics, tensor_token(areas), str(device))
    pixels = ON_DEVICE.get(key, lambda: tuple(torch.from_numpy(a).to(device) for a in host[:4]))
    return (*pixels, *host[4:])


def _measure_on_device(mean: Tensor, args: tuple) -> Tensor:
    """[`measure`][] without gradient on a CUDA device (or in the simulator): one kernel, one
    thread per element, the same draws as the CPU kernel's ([`measured_value`][
    layoutwarp.kernels.noise.measured_value])."""
    x = mean.detach()
    if x.dtype not in (torch.float32, torch.float64) or not x.is_contiguous():
        x = x.to(torch.float64).contiguous()
    flat = x.view(-1, args[0].numel())
    out = torch.empty_like(flat)
    measure_on_device(flat, *args, out, stream_of(flat))
    res = out.view(mean.shape)
    return res if res.dtype == mean.dtype else res.to(mean.dtype)


def _measure_compiled(mean: Tensor, args: tuple, kernel: Callable) -> Tensor:
    """[`measure`][] without gradient on the CPU: the fused kernel
    `sensor_measure` (``kernel``, see [`compiled`][layoutwarp.jit.compiled]) with
    [`kernel_arguments`][]' ``args``."""
    x = mean.detach() if mean.requires_grad else mean
    if x.dtype not in (torch.float32, torch.float64) or not x.is_contiguous():
        x = x.to(torch.float64).contiguous()  # the kernel's two builds: float32 and float64
    flat = x.numpy().reshape(-1, args[0].size)  # numpy's views: a torch call each costs more
    out = np.empty(flat.shape, flat.dtype)
    kernel(flat, *args, out, kernels.threads(flat.size))  # threads bounded by torch's
    res = torch.from_numpy(out.reshape(mean.shape))
    return res if res.dtype == mean.dtype else res.to(mean.dtype)
