"""The optics in front of the sensor: a point spread function (a Gaussian, or the Airy pattern of
a circular aperture) applied to the source image before it is integrated, as separable or 2-D
taps sized in source pixels ([`apply_psf`][], [`psf_kernels`][]); and the check that a PSF fits
the sensor it blurs ([`check_psf_width`][])."""

from __future__ import annotations

import functools
import math
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from .checks import ArgumentError, check_available, check_size

__all__ = ["PSF_MAX_REACH", "airy_profile", "apply_psf", "check_psf_width", "psf_kernels"]

#: A camera: a [`SensorPhysics`][layoutwarp.physics.SensorPhysics], read for its optics' fields
#: (named, not imported: the camera's module imports this one).
SensorPhysics = Any


def airy_profile(r_um: Tensor, f_number: float, wavelength_um: float) -> Tensor:
    """The Airy pattern's intensity ``(2 J1(x)/x)²``, ``x = π r / (λ N)``, at radii ``r_um`` (1 at 0)."""
    x = math.pi * r_um / (wavelength_um * f_number)
    safe = torch.where(x > 0, x, torch.ones_like(x))
    return torch.where(x > 0, (2 * torch.special.bessel_j1(safe) / safe) ** 2, torch.ones_like(x))


def _gauss_taps(sigma_px: float) -> np.ndarray:
    """A Gaussian integrated over each pixel (``erf`` differences), normalised, radius ``4σ``."""
    radius = max(1, math.ceil(4 * sigma_px))
    edges = (np.arange(-radius, radius + 2) - 0.5) / (sigma_px * math.sqrt(2))
    cdf = np.array([math.erf(v) for v in edges])
    taps = np.diff(cdf) / 2
    return taps / taps.sum()


def psf_kernels(physics: SensorPhysics, src_size: tuple[int, int]) -> dict[str, Any]:
    """The PSF as source-pixel kernels: ``{"ky", "kx"}`` (separable Gaussian) or ``{"k2d"}`` (Airy),
    float64 numpy arrays that sum to 1, and ``"error"``: the Airy kernel's truncated energy (0 for
    the Gaussian, whose ``4σ`` tails hold less than 1e-4).

    The source pixel pitch is ``sensor_um / src_size`` per axis. The Airy pattern is averaged over
    each source pixel (8 × 8 samples) out to the radius that holds ``psf_energy`` of its energy
    (encircled energy ``1 − J0(x)² − J1(x)²``). The kernels of the last 16 (physics, size) pairs
    are kept (an Airy kernel takes 10–20 ms to build), so their arrays are read-only.
    """
    return _psf_kernels(physics, check_size(src_size, "src_size"))


@functools.lru_cache(maxsize=16)
def _psf_kernels(physics: SensorPhysics, src_size: tuple[int, int]) -> dict[str, Any]:
    hs, ws = src_size
    py, px = physics.sensor_um[0] / hs, physics.sensor_um[1] / ws
    if physics.psf == "gaussian":
        s = physics.psf_sigma()
        k = {"ky": _gauss_taps(s / py), "kx": _gauss_taps(s / px), "error": 0.0}
    else:
        k = {"k2d": _airy_kernel(physics, py, px), "error": 1 - physics.psf_energy}
    for v in k.values():
        if isinstance(v, np.ndarray):
            v.setflags(write=False)
    return k


def _airy_radius_um(physics: SensorPhysics) -> float:
    """The radius (µm) that holds ``psf_energy`` of the Airy pattern's energy."""
    return _airy_x(physics.psf_energy) * physics.wavelength_um * physics.f_number / math.pi


@functools.lru_cache(maxsize=8)
def _airy_x(energy: float) -> float:
    """Where the Airy pattern's encircled energy ``1 − J0(x)² − J1(x)²`` reaches ``energy``."""
    x = torch.linspace(1e-6, 400, 400_001, dtype=torch.float64)
    enc = 1 - torch.special.bessel_j0(x) ** 2 - torch.special.bessel_j1(x) ** 2
    reached = torch.nonzero(enc >= energy)
    # beyond the grid, the rings' energy falls as 1 − E(x) ≈ 2 / (π x)
    return float(x[int(reached[0])]) if len(reached) else 2 / (math.pi * (1 - energy))


#: How many sensor widths a PSF's kernel may reach (beyond, it blurs the image into its mean:
#: a mistaken f-number or width, whose kernel alone could need terabytes).
PSF_MAX_REACH = 4


def _psf_radius(physics: SensorPhysics) -> tuple[float, str]:
    """The PSF kernel's radius (µm) and the field that sets it."""
    if physics.psf == "gaussian":
        return 4 * physics.psf_sigma(), "psf_sigma_um" if physics.psf_sigma_um else "f_number"
    return _airy_radius_um(physics), "f_number"


def check_psf_width(physics: SensorPhysics) -> None:
    """Refuse a PSF whose kernel reaches over more than `PSF_MAX_REACH` sensor widths, naming
    the field that set it."""
    radius, field = _psf_radius(physics)
    extent = max(physics.sensor_um)
    if radius > PSF_MAX_REACH * extent:
        raise ArgumentError(
            field,
            f"{field} {getattr(physics, field):g} makes the {physics.psf} PSF {radius:.4g} µm in radius, "
            f"over {PSF_MAX_REACH} times the sensor's {extent:g} µm: it would blur the image into its mean",
        )


def _airy_kernel(physics: SensorPhysics, py: float, px: float) -> np.ndarray:
    """The Airy pattern averaged over source pixels of pitch ``(py, px)`` µm, truncated at the
    radius holding ``psf_energy`` of its energy, summing to 1."""
    r_um = _airy_radius_um(physics)
    ry, rx = max(1, math.ceil(r_um / py)), max(1, math.ceil(r_um / px))
    sub = 8
    check_available(  # 8 x 8 samples a kernel pixel, float64, a few temporaries
        (2 * ry + 1) * (2 * rx + 1) * sub * sub * 8 * 6,
        "f_number",
        f"f_number {physics.f_number:g} makes an Airy kernel of {2 * rx + 1}x{2 * ry + 1} source pixels",
        "8x8 float64 samples a kernel pixel",
    )
    oy = (torch.arange(-ry * sub, (ry + 1) * sub, dtype=torch.float64) + 0.5) / sub - 0.5
    ox = (torch.arange(-rx * sub, (rx + 1) * sub, dtype=torch.float64) + 0.5) / sub - 0.5
    yy, xx = torch.meshgrid(oy * py, ox * px, indexing="ij")
    r = torch.sqrt(xx**2 + yy**2)
    fine = torch.where(
        r <= r_um, airy_profile(r, physics.f_number, physics.wavelength_um), torch.zeros_like(r)
    )
    k2d = fine.reshape(2 * ry + 1, sub, 2 * rx + 1, sub).mean((1, 3)).numpy()
    return k2d / k2d.sum()


def apply_psf(image: Tensor, physics: SensorPhysics) -> Tensor:
    """Blur source images ``(N, H, W)`` with the physics' PSF (none: returned as they are).

    Borders are reflected as OpenCV's ``BORDER_REFLECT`` (the edge pixel repeated), on both
    paths, so the blur neither adds nor loses light at the image's edge; each kernel sums to 1.
    On the CPU without a gradient OpenCV filters (``sepFilter2D`` / ``filter2D``); otherwise torch
    convolutions, differentiable in the image.
    """
    if physics.psf is None:
        return image
    k = psf_kernels(physics, image.shape[-2:])
    if image.device.type == "cpu" and not image.requires_grad and image.shape[0] > 0:
        import cv2

        arr = image.detach().contiguous().numpy()
        out = np.empty_like(arr)
        for c in range(arr.shape[0]):  # plane by plane: no channels-last copy
            if "k2d" in k:
                cv2.filter2D(
                    arr[c], -1, k["k2d"].astype(arr.dtype), dst=out[c], borderType=cv2.BORDER_REFLECT
                )
            else:
                kx, ky = (k[a].astype(arr.dtype) for a in ("kx", "ky"))
                cv2.sepFilter2D(arr[c], -1, kx, ky, dst=out[c], borderType=cv2.BORDER_REFLECT)
        return torch.from_numpy(out)
    x = image[:, None]
    if "k2d" in k:
        kern = torch.tensor(k["k2d"], dtype=image.dtype, device=image.device)
        return F.conv2d(_reflected(x, *(s // 2 for s in kern.shape)), kern[None, None])[:, 0]
    ky, kx = (torch.tensor(k[a], dtype=image.dtype, device=image.device) for a in ("ky", "kx"))
    x = F.conv2d(_reflected(x, len(ky) // 2, 0), ky.view(1, 1, -1, 1))
    return F.conv2d(_reflected(x, 0, len(kx) // 2), kx.view(1, 1, 1, -1))[:, 0]


def _reflected(x: Tensor, ry: int, rx: int) -> Tensor:
    """``x`` ``(..., H, W)`` padded by ``ry`` rows and ``rx`` columns on each side as OpenCV's
    ``BORDER_REFLECT`` pads (``cba|abc…``: the edge pixel repeated, the image mirrored again where
    a pad is wider than it), by an index gather: differentiable in ``x``. Torch's
    ``F.pad(mode="reflect")`` is ``BORDER_REFLECT_101`` (``cb|abc``), which loses light at the
    edges and gave the image's gradient path other border pixels than the CPU's."""
    for dim, r in ((-2, ry), (-1, rx)):
        if r:
            n = x.shape[dim]
            i = torch.arange(-r, n + r, device=x.device) % (2 * n)
            x = x.index_select(dim, torch.where(i >= n, 2 * n - 1 - i, i))
    return x
