"""Photons, noise, pixel apertures and optics: the measurement equation beyond its mean.

The integrators give each pixel's mean radiance ``L̄_k`` (the paper's noise-free sensor). A
real pixel records light in proportion to its area, with noise; [`SensorPhysics`][] holds
the camera in physical units, and [`simulate`][layoutwarp.sensor.simulate] (``physics=``) runs, in this
order, in the notation of the EMVA 1288 standard (release 4.0):

1. optics: the lens's point spread function blurs the *source* image ([`apply_psf`][]; its
   width in µm becomes source pixels through the image's extent on the sensor, ``sensor_um``);
2. the integrators (unchanged): ``L̄_k``, the mean over the pixel ``A_k``;
3. photons: ``μ_p,k = photons_per_um2 · L̄_k · a_k · fill_factor`` with ``a_k`` the pixel's
   area in µm² (from the pixel polygons, differentiable in θ: the exact and separable
   integrators return it with the means, ``return_areas=True``);
4. electrons: ``μ_e,k = η μ_p,k (1 + prnu · z_k) + μ_d,k`` with ``η`` the quantum efficiency,
   ``z_k`` a fixed standard-normal pattern (PRNU) and the dark signal
   ``μ_d,k = dark_e_per_um2 · a_k + dsnu · z'_k`` (DSNU, a second fixed pattern);
5. shot noise (Poisson: variance = mean in electrons) and read noise (Gaussian, ``σ_d``
   = ``read_noise_e``);
6. full-well clipping at ``full_well_per_um2 · a_k``;
7. the ADC: ``y = round(K e + black_level_dn)`` clipped to ``[0, 2^adc_bits − 1]`` (``K``:
   system gain in DN per electron; quantisation variance ``1/12`` DN²);
8. the ISP, back to radiance units: ``(y − black_level_dn)/K − dark_e_per_um2 · a_k``, divided by
   ``photons_per_um2 · η · a_k · fill_factor`` (the paper's ``1/vol(A_k)``).

Below saturation and without the fixed patterns, the output's expectation is the noise-free
mean ``L̄_k`` (up to the ADC's rounding, which noise dithers); its temporal variance is
``σ_y² = K² σ_d² + σ_q² + K (μ_y − μ_y.dark)`` in DN, so a pixel's SNR grows as ``√a_k`` in the
shot-noise regime and as ``a_k`` where read noise dominates.

Noise and gradients: ``noise="auto"`` samples exact Poisson shot noise when no gradient is
needed, and the reparameterised Gaussian ``μ + √μ ε`` (and a straight-through rounding in the
ADC) when the image or θ requires grad, so that training gets unbiased gradients through the
noise; ``"poisson"``/``"gaussian"`` force one, ``"none"`` keeps the expectation. The fixed
patterns come from ``pattern_seed`` alone (one sensor, the same in every frame); temporal noise
from ``seed`` (the same seed and input give the same noise; every image of a batch, and every
channel, gets its own). Where no gradient is needed on the CPU, steps 3–8 are one compiled pass
(`sensor_measure`): exact Poisson draws by Ahrens and Dieter's
algorithm PD (multiplication of uniforms below a mean of 10), normals by the ziggurat, each
pixel's noise from counter-based streams of its own, so the thread count does not change it;
elsewhere torch's ``poisson`` and ``randn``.
"""

from __future__ import annotations

import functools
import json
import math
from collections.abc import Callable
from dataclasses import asdict, dataclass, fields
from typing import Any

import numpy as np
import torch
from torch import Tensor

from . import jit, kernels
from .caches import LRU, tensor_token
from .checks import (
    ArgumentError,
    check_choice,
    check_extent,
    check_int,
    check_number,
)
from .kernels.device import fall_back, stream_of
from .kernels.noise import measure_on_device
from .operators import base as ops
from .operators.base import random_seed
from .optics import airy_profile, apply_psf, check_psf_width, psf_kernels

__all__ = [
    "NOISE",
    "OUTPUTS",
    "PSFS",
    "SensorPhysics",
    "airy_profile",
    "apply_psf",
    "as_physics",
    "check_output",
    "device_arguments",
    "kernel_arguments",
    "measure",
    "noise_seed",
    "pixel_snr",
    "psf_kernels",
]

#: Point spread functions of the optics.
PSFS = ("gaussian", "airy")
#: What [`measure`][] returns: radiance units (the ISP's output), electrons or digital numbers.
OUTPUTS = ("radiance", "electrons", "dn")
#: Shot-noise models (see the module docstring).
NOISE = ("auto", "poisson", "gaussian", "none")
#: The noise models' codes in the compiled kernel.
NOISE_CODES = {"none": 0, "poisson": 1, "gaussian": 2}
#: The standard deviation of the Gaussian that best fits the Airy core, in units of ``λ N``.
GAUSS_AIRY_SIGMA = 0.42
#: The first zero of the Airy pattern's ``2 J1(x)/x``.
AIRY_FIRST_ZERO = 3.8317059702075125


#: [`SensorPhysics`][]' number fields and their ranges ``(lo, hi, lo open, hi open)``.
_RANGES = {
    "photons_per_um2": (0, None, True, False),
    "quantum_efficiency": (0, 1, True, False),
    "fill_factor": (0, 1, True, False),
    "full_well_per_um2": (0, None, True, False),
    "read_noise_e": (0, None, False, False),
    "dark_e_per_um2": (0, None, False, False),
    "gain_dn_per_e": (0, None, True, False),
    "black_level_dn": (0, None, False, False),
    "prnu": (0, 1, False, False),
    "dsnu": (0, None, False, False),
    "f_number": (0, None, True, False),
    "wavelength_um": (0, None, True, False),
    "psf_sigma_um": (0, None, True, False),
    "psf_energy": (0.5, 1, False, True),
}
#: The number fields that may be ``None``.
_OPTIONAL = {"full_well_per_um2", "gain_dn_per_e", "psf_sigma_um"}
#: The integer fields: ``(lo, hi, may be None)``.
_INTEGERS = {"adc_bits": (1, 32, True), "pattern_seed": (0, None, False), "seed": (0, None, True)}


@dataclass(frozen=True)
class SensorPhysics:
    """A camera in physical units: light, sensor, electronics and optics (see the module docstring).

    Attributes:
        sensor_um: the sensor's extent ``(H_um, W_um)`` in µm (as in
            [`export_layout`][layoutwarp.export.export_layout]).
        photons_per_um2: mean photons per µm² per exposure where the image's value is 1.0 (the
            exposure: light level times exposure time).
        quantum_efficiency: ``η``, electrons per photon, in ``(0, 1]``.
        fill_factor: the share of each pixel's area that collects light, in ``(0, 1]``.
        full_well_per_um2: electrons a pixel holds per µm² of its area (``None``: no saturation).
        read_noise_e: temporal dark noise ``σ_d`` in electrons (rms).
        dark_e_per_um2: mean dark electrons per µm² of pixel area per exposure.
        adc_bits: the ADC's resolution (``None``: no quantisation, no clipping at the ADC).
        gain_dn_per_e: the system gain ``K`` in DN per electron (``None``: 1, or with
            ``adc_bits`` and a full well, the gain at which the largest pixel's full well fills
            the ADC's range above the black level).
        black_level_dn: the offset added before the ADC (and removed by the ISP), in DN.
        prnu: photo-response non-uniformity, the relative rms of a fixed per-pixel gain pattern.
        dsnu: dark-signal non-uniformity, the rms of a fixed per-pixel dark offset, in electrons.
        pattern_seed: seeds the fixed PRNU/DSNU patterns (one physical sensor).
        psf: ``None``, ``"gaussian"`` (separable; width ``psf_sigma_um``) or ``"airy"``
            (diffraction at ``f_number`` and ``wavelength_um``).
        f_number, wavelength_um: the optics' ``N`` and ``λ`` (µm).
        psf_sigma_um: the Gaussian's standard deviation in µm (``None``: ``0.42 λ N``, the
            Gaussian that best fits the Airy core).
        psf_energy: the share of the Airy pattern's energy its truncated kernel keeps (the
            rest, in the far rings, is the approximation's error; the kernel is renormalised).
        seed: seeds the temporal noise (``None``: fresh noise every call).
        noise: ``"auto"``, ``"poisson"``, ``"gaussian"`` or ``"none"``.
    """

    sensor_um: tuple[float, float]
    photons_per_um2: float
    quantum_efficiency: float = 1.0
    fill_factor: float = 1.0
    full_well_per_um2: float | None = None
    read_noise_e: float = 0.0
    dark_e_per_um2: float = 0.0
    adc_bits: int | None = None
    gain_dn_per_e: float | None = None
    black_level_dn: float = 0.0
    prnu: float = 0.0
    dsnu: float = 0.0
    pattern_seed: int = 0
    psf: str | None = None
    f_number: float = 5.6
    wavelength_um: float = 0.55
    psf_sigma_um: float | None = None
    psf_energy: float = 0.95
    seed: int | None = None
    noise: str = "auto"

    def __post_init__(self) -> None:
        # checked and stored as plain Python numbers (a numpy or torch scalar, or an int, becomes
        # a float or an int: the physics compares, hashes and writes to JSON the same way)
        object.__setattr__(self, "sensor_um", check_extent(self.sensor_um))
        for name, (lo, hi, lo_open, hi_open) in _RANGES.items():
            v = getattr(self, name)
            if v is not None or name not in _OPTIONAL:
                object.__setattr__(
                    self, name, check_number(v, name, lo, hi, lo_open=lo_open, hi_open=hi_open)
                )
        for name, (lo, hi, optional) in _INTEGERS.items():
            object.__setattr__(self, name, check_int(getattr(self, name), name, lo, hi, optional=optional))
        if self.psf is not None:
            check_choice(self.psf, PSFS, "psf")
            check_psf_width(self)
        check_choice(self.noise, NOISE, "noise")
        # what an operator takes of the camera, made once (a compiled graph reads them as constants)
        object.__setattr__(self, "_token", json.dumps(self.to_dict(), sort_keys=True))
        object.__setattr__(self, "_noise_seed", None if self.seed is None else _kernel_seed(self.seed))

    @property
    def token(self) -> str:
        """The camera as compact JSON text: how it enters layoutwarp's operators."""
        return self._token

    # -- files ---------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        """The physics as a JSON-able dict (``sensor_um`` as a list)."""
        d = asdict(self)
        d["sensor_um"] = list(self.sensor_um)
        return d

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> SensorPhysics:
        """Rebuild from [`to_dict`][] (unknown keys are refused, naming them)."""
        if not isinstance(data, dict):
            raise ValueError(f"sensor physics must be a JSON object, got {type(data).__name__}")
        names = {f.name for f in fields(cls)}
        unknown = sorted(set(data) - names)
        if unknown:
            raise ValueError(f"unknown sensor physics field(s) {unknown}; known: {sorted(names)}")
        values = dict(data)
        if isinstance(values.get("sensor_um"), list):
            values["sensor_um"] = tuple(values["sensor_um"])
        try:
            return cls(**values)
        except TypeError as exc:
            raise ValueError(f"sensor physics: {exc}") from None

    def to_json(self) -> str:
        """The physics as JSON text (what ``--physics FILE`` and [`from_json`][] read)."""
        return json.dumps(self.to_dict(), indent=2)

    @classmethod
    def from_json(cls, text: str) -> SensorPhysics:
        """Rebuild from [`to_json`][]'s text (``ValueError`` for text that is not JSON)."""
        try:
            values = json.loads(text)
        except (TypeError, json.JSONDecodeError) as exc:
            raise ArgumentError(
                "text", f"sensor physics must be JSON text (SensorPhysics.to_json), {exc}"
            ) from None
        if not isinstance(values, dict):
            raise ArgumentError("text", f"sensor physics must be a JSON object, got {type(values).__name__}")
        return cls.from_dict(values)

    # -- derived -------------------------------------------------------------------
    def um2_per_unit(self) -> float:
        """µm² per unit of sensor area (the square ``[-1, 1]²`` is ``sensor_um``)."""
        return self.sensor_um[0] * self.sensor_um[1] / 4

    def gain(self, largest_area_um2: float) -> float:
        """The system gain ``K`` (DN per electron) for a sensor whose largest pixel is that big."""
        if self.gain_dn_per_e is not None:
            return self.gain_dn_per_e
        if self.adc_bits is not None and self.full_well_per_um2 is not None:
            return (2**self.adc_bits - 1 - self.black_level_dn) / (self.full_well_per_um2 * largest_area_um2)
        return 1.0

    def psf_sigma(self) -> float:
        """The Gaussian PSF's standard deviation in µm."""
        return self.psf_sigma_um or GAUSS_AIRY_SIGMA * self.wavelength_um * self.f_number

    def airy_zero_um(self) -> float:
        """The radius of the Airy pattern's first dark ring, ``1.22 λ N``, in µm."""
        return AIRY_FIRST_ZERO / math.pi * self.wavelength_um * self.f_number


# ----------------------------------------------------------------------------------------
# Photons to numbers
# ----------------------------------------------------------------------------------------
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
        physics: the camera.
        output: ``"radiance"`` (the ISP's estimate of ``mean``), ``"electrons"`` (after the full
            well, before the ADC) or ``"dn"`` (the ADC's digital numbers).
        generator: the noise's random generator (default: ``physics.seed``'s draws, or torch's
            global generator when that is ``None``).
        seed: instead, a 0-d int64 tensor the noise is drawn from ([`noise_seed`][]).

    Returns:
        ``(N, h, w)`` in ``mean``'s dtype.

    Raises:
        ValueError: a full well below the read noise in the smallest pixel.
    """
    check_choice(output, OUTPUTS, "output")
    seed = noise_seed(physics, generator, seed)
    if torch.is_grad_enabled() and (mean.requires_grad or areas.requires_grad):
        return _measure_torch(mean, areas, physics, output, seed)
    return torch.ops.layoutwarp.measure(mean, areas, physics.token, output, seed)


@torch.library.custom_op("layoutwarp::measure", mutates_args=())
def _measure(mean: Tensor, areas: Tensor, physics: str, output: str, seed: Tensor) -> Tensor:
    """[`measure`][] without gradient: one compiled pass on the CPU (`sensor_measure`), one kernel
    on a CUDA device, or the torch path; the camera as its [`token`][SensorPhysics.token]."""
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
        if mode == "poisson":
            electrons = shot + (electrons - electrons.detach())
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
        dn = dn + (rounded - dn.detach())  # straight through: the value rounded, the gradient kept
    if output == "dn":
        return dn
    recovered = (dn - physics.black_level_dn) / k - physics.dark_e_per_um2 * a_um2
    return recovered / (eta * physics.photons_per_um2 * physics.fill_factor * a_um2)


def _gain(physics: SensorPhysics, a_um2: Tensor) -> float | Tensor:
    """[`SensorPhysics.gain`][] for pixels of areas ``a_um2`` (µm²): a tensor where it depends on
    the largest (read in the graph, not on the host)."""
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
    """Each pixel's full well in electrons ``full`` (a copy), after the check of [`_full_well`][]:
    a full well not above the read noise is refused. Its gradient passes through."""
    camera = physics_of(physics)
    _full_well(camera, full.detach() / camera.full_well_per_um2)
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
    if mode == "poisson":
        shot = torch.poisson(rate, generator=generator)
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


def as_physics(physics: SensorPhysics | dict | None) -> SensorPhysics | None:
    """A camera given as a [`SensorPhysics`][], its dict ([`SensorPhysics.to_dict`][]) or
    ``None``: the one rule of [`simulate`][layoutwarp.sensor.simulate] and
    [`SensorLayer`][layoutwarp.sensor.SensorLayer].

    Raises:
        TypeError: anything else.
    """
    if physics is None or isinstance(physics, SensorPhysics):
        return physics
    if isinstance(physics, dict):
        return SensorPhysics.from_dict(physics)
    raise TypeError(f"physics must be a SensorPhysics, its dict or None, got {type(physics).__name__}")


def check_output(output: str, physics: SensorPhysics | None) -> str:
    """``output`` if it is one of `OUTPUTS` and a sensor records it: electrons and digital
    numbers need ``physics`` (without it a sensor gives the noise-free mean, in radiance units)."""
    check_choice(output, OUTPUTS, "output")
    if physics is None and output != "radiance":
        raise ArgumentError(
            "output", f"output={output!r} needs physics (a SensorPhysics); without it the output is radiance"
        )
    return output


def pixel_snr(areas_um2: Tensor, physics: SensorPhysics, level: float = 1.0) -> dict[str, Tensor]:
    """Each pixel's full well and its SNR for a flat field at ``level`` (image units, 1.0 is
    ``photons_per_um2``), from the EMVA 1288 formula
    ``SNR = μ_e / √(σ_d² + σ_q²/K² + μ_e)`` with ``σ_d² = read_noise_e² + μ_d`` (the dark signal's
    shot noise) and the signal capped at the full well; no fixed patterns.

    Returns:
        ``{"full_well_e", "signal_e", "snr"}``, each shaped like ``areas_um2`` (full well ``inf``
        without one).
    """
    check_number(level, "level", 0)
    a = areas_um2.to(torch.float64)
    full = (
        physics.full_well_per_um2 * a
        if physics.full_well_per_um2 is not None
        else torch.full_like(a, math.inf)
    )
    dark = physics.dark_e_per_um2 * a
    signal = torch.minimum(
        physics.quantum_efficiency * physics.photons_per_um2 * physics.fill_factor * level * a, full - dark
    )
    quant = 1 / 12 / physics.gain(float(a.max())) ** 2 if physics.adc_bits is not None else 0.0
    snr = signal / torch.sqrt(physics.read_noise_e**2 + dark + quant + signal)
    return {"full_well_e": full, "signal_e": signal, "snr": snr}


def _full_well(physics: SensorPhysics, a_um2: Tensor) -> Tensor | None:
    """Each pixel's full well in electrons (``None``: no saturation).

    Raises:
        ArgumentError: a full well not above the read noise in the smallest pixel.
    """
    if physics.full_well_per_um2 is None:
        return None
    full = physics.full_well_per_um2 * a_um2
    smallest = float(full.detach().min())
    if smallest <= physics.read_noise_e:
        raise ArgumentError(
            "full_well_per_um2",
            f"full_well_per_um2 = {physics.full_well_per_um2:g} gives the smallest pixel a full well of "
            f"{smallest:.3g} e⁻, not above the read noise {physics.read_noise_e:g} e⁻",
        )
    return full


def physics_of(text: str) -> SensorPhysics | None:
    """The camera of a [`SensorPhysics.token`][] text (``""``: none), kept per text: how a
    camera comes out of an operator's arguments."""
    if not text:
        return None
    return _PHYSICS.get(text, lambda: SensorPhysics.from_json(text))


_PHYSICS: LRU[SensorPhysics] = LRU("cameras of operators", 16)


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
    _full_well(physics, a)
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


@functools.lru_cache(maxsize=64)
def _kernel_seed(seed: int) -> int:
    """The compiled kernel's seed for ``physics.seed``: the first draw of a generator seeded with
    it (what a fresh ``torch.Generator().manual_seed(seed)`` gives every call), kept."""
    return int(torch.randint(0, 2**62, (), generator=torch.Generator().manual_seed(seed)))


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
