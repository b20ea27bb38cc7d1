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
elsewhere torch's ``poisson`` and ``randn``. The measurement is [`layoutwarp.measurement`][]'s.
"""

from __future__ import annotations

import functools
import json
import math
from dataclasses import asdict, dataclass, fields
from typing import Any

import torch
from torch import Tensor

from .caches import LRU
from .checks import (
    SEED_MAX,
    ArgumentError,
    check_choice,
    check_extent,
    check_int,
    check_number,
)
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
    "physics_of",
    "pixel_snr",
    "psf_kernels",
]

#: Point spread functions of the optics.
PSFS = ("gaussian", "airy")
#: What [`measure`][layoutwarp.measurement.measure] returns: radiance units (the ISP's output),
#: electrons or digital numbers.
OUTPUTS = ("radiance", "electrons", "dn")
#: Shot-noise models (see the module docstring).
NOISE = ("auto", "poisson", "gaussian", "none")
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
_INTEGERS = {"adc_bits": (1, 32, True), "pattern_seed": (0, SEED_MAX, False), "seed": (0, SEED_MAX, True)}


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

    def full_well(self, a_um2: Tensor) -> Tensor | None:
        """The full well in electrons of pixels of areas ``a_um2`` (µm²); ``None`` without
        saturation.

        Raises:
            ArgumentError: a full well not above the read noise in the smallest pixel.
        """
        if self.full_well_per_um2 is None:
            return None
        full = self.full_well_per_um2 * a_um2
        smallest = float(full.detach().min())
        if smallest <= self.read_noise_e:
            raise ArgumentError(
                "full_well_per_um2",
                f"full_well_per_um2 = {self.full_well_per_um2:g} gives the smallest pixel a full well of "
                f"{smallest:.3g} e⁻, not above the read noise {self.read_noise_e:g} e⁻",
            )
        return full

    def psf_sigma(self) -> float:
        """The Gaussian PSF's standard deviation in µm."""
        return self.psf_sigma_um or GAUSS_AIRY_SIGMA * self.wavelength_um * self.f_number

    def airy_zero_um(self) -> float:
        """The radius of the Airy pattern's first dark ring, ``1.22 λ N``, in µm."""
        return AIRY_FIRST_ZERO / math.pi * self.wavelength_um * self.f_number


@functools.lru_cache(maxsize=64)
def _kernel_seed(seed: int) -> int:
    """The compiled kernel's seed for ``physics.seed``: the first draw of a generator seeded with
    it (what a fresh ``torch.Generator().manual_seed(seed)`` gives every call), kept."""
    return int(torch.randint(0, 2**62, (), generator=torch.Generator().manual_seed(seed)))


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


def physics_of(text: str) -> SensorPhysics | None:
    """The camera of a [`SensorPhysics.token`][] text (``""``: none), kept per text: how a
    camera comes out of an operator's arguments."""
    if not text:
        return None
    return _PHYSICS.get(text, lambda: SensorPhysics.from_json(text))


_PHYSICS: LRU[SensorPhysics] = LRU("cameras of operators", 16)
