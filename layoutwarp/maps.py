"""Dense remap maps of a layout and stratified sample points.

Maps follow OpenCV's ``remap`` convention: float32 ``map_x``, ``map_y`` in source pixel units
with pixel centres at integers (``sensor_to_pixels(..., centered=True)``), usable with
``cv2.remap`` and ``kornia.geometry.transform.remap(..., align_corners=True)``.
"""

from __future__ import annotations

from typing import NamedTuple

import cv2
import numpy as np
import torch
from torch import Tensor

from .checks import SEED_MAX, check_generator, check_int, check_number, check_size
from .coords import pixel_centers, sensor_to_pixels
from .layouts import Layout, check_layout
from .mesh import pixel_mesh
from .operators import base as ops
from .operators.base import layout_token, random_seed

__all__ = [
    "Maps",
    "forward_maps",
    "inverse_coords",
    "inverse_maps",
    "map_points",
    "raster_index_map",
    "sample_points",
]


class Maps(NamedTuple):
    """A pair of float32 remap maps ``(map_x, map_y)``, each ``(H, W)``, OpenCV convention."""

    map_x: Tensor
    map_y: Tensor

    def numpy(self) -> tuple[np.ndarray, np.ndarray]:
        """The maps as contiguous float32 numpy arrays for ``cv2.remap``."""
        return (
            np.ascontiguousarray(self.map_x.detach().cpu().numpy(), dtype=np.float32),
            np.ascontiguousarray(self.map_y.detach().cpu().numpy(), dtype=np.float32),
        )


def _to_maps(points: Tensor, size: tuple[int, int]) -> Maps:
    px = sensor_to_pixels(points, size, centered=True)
    return Maps(px[..., 0].float(), px[..., 1].float())


def sample_points(
    size: tuple[int, int],
    samples: int = 1,
    *,
    jitter: bool = False,
    generator: torch.Generator | None = None,
    seed: int | None = None,
    dtype: torch.dtype = torch.float64,
    device: torch.device | str | None = None,
) -> Tensor:
    """Stratified sample points in the uniform cells, shape ``(H·s, W·s, 2)``.

    Cell ``(i, j)`` gets an ``s × s`` grid of strata; the sample of stratum ``(a, b)`` sits at
    its centre, or uniformly at random inside it with ``jitter=True``, drawn from ``generator``,
    or, with ``seed``, from a generator seeded with it on ``device`` (the same draws; the form a
    compiled graph takes). Row ``i·s + a``, column ``j·s + b`` of the result belongs to pixel
    ``(i, j)``.
    """
    h, w = check_size(size)
    s = check_int(samples, "samples", 1)
    generator = check_generator(generator, seed=seed if jitter else None)
    if jitter and seed is not None:
        like = torch.empty(0, dtype=dtype, device=device)
        off = torch.ops.layoutwarp.uniform(
            random_seed(None, check_int(seed, "seed", 0, SEED_MAX)), [h * s, w * s, 2], like
        )
    elif jitter:
        at = generator.device if generator is not None else device  # drawn where the generator is
        off = torch.rand(h * s, w * s, 2, generator=generator, dtype=dtype, device=at).to(device)
    else:
        off = torch.full((h * s, w * s, 2), 0.5, dtype=dtype, device=device)
    xs = torch.arange(w * s, dtype=dtype, device=device)
    ys = torch.arange(h * s, dtype=dtype, device=device)
    base = torch.stack(torch.meshgrid(xs, ys, indexing="xy"), -1)
    scale = torch.tensor([2 / (w * s), 2 / (h * s)], dtype=dtype, device=device)
    return (base + off) * scale - 1


def map_points(layout: Layout, points: Tensor, *, inverse: bool = False) -> Tensor:
    """``φ(points)`` (or ``φ⁻¹`` with ``inverse``) in float64 for the layout's current θ, without
    gradient: how every fixed-layout path (maps, back-warping, labels, keypoints) moves points.

    Args:
        layout: the pixel layout.
        points: ``(..., 2)`` sensor coordinates (moved to θ's device).
        inverse: map through ``φ⁻¹`` instead of ``φ``.

    Returns:
        ``(..., 2)`` float64 sensor coordinates on θ's device.
    """
    check_layout(layout)
    theta = layout.theta_as(torch.float64).detach()
    p = points.detach().to(device=theta.device, dtype=torch.float64)
    return torch.ops.layoutwarp.map_points(p, theta, layout_token(layout), inverse)


@torch.library.custom_op("layoutwarp::map_points", mutates_args=())
def _map_points(points: Tensor, theta: Tensor, layout: str, inverse: bool) -> Tensor:
    """``φ(points)`` or ``φ⁻¹(points)`` ``(..., 2)`` in float64 for the layout of a
    [`layout_token`][layoutwarp.operators.base.layout_token] at ``theta`` (an inverse may iterate until it
    converges: inside an operator, no compiled graph sees its loop). No gradient."""
    if points.ndim == 0 or points.shape[-1] != 2:
        ops.refuse("map_points", "points", f"must be (..., 2), got shape {tuple(points.shape)}")
    layout_ = ops.layout_of(layout, op="map_points")
    ops.check_theta("map_points", theta, layout_)
    with ops.autograd_inside():  # a generic inverse differentiates φ for Newton's Jacobian
        out = layout_.phi_inverse(points, theta) if inverse else layout_.phi(points, theta)
    return out.detach().clone() if out is points else out.detach()


@_map_points.register_fake
def _(points, theta, layout, inverse):
    return torch.empty_like(points)


ops.register(_map_points)


def inverse_coords(layout: Layout, target_size: tuple[int, int]) -> Tensor:
    """``φ⁻¹`` of every pixel centre of a uniform ``target_size = (H, W)`` grid, ``(H, W, 2)``
    float64 sensor coordinates on θ's device: where each target pixel lies on the sensor (the
    inverse coordinate map of a warp, as scikit-image's ``warp_coords``)."""
    target_size = check_size(target_size, "target_size")
    return map_points(layout, pixel_centers(target_size, device=layout.theta.device), inverse=True)


def forward_maps(
    layout: Layout,
    size: tuple[int, int],
    src_size: tuple[int, int],
    *,
    samples: int = 1,
    jitter: bool = False,
    generator: torch.Generator | None = None,
) -> Maps:
    """Where each sample of each sensor pixel looks in the source image.

    Args:
        layout: the pixel layout.
        size: sensor size ``(h, w)``.
        src_size: source image size ``(H, W)``.
        samples: ``s``: an ``s × s`` stratified grid per pixel (1: the deformed pixel centres).
        jitter: jitter each sample inside its stratum (else stratum centres).
        generator: random generator for the jitter.

    Returns:
        [`Maps`][] of shape ``(h·s, w·s)``. Average each ``s × s`` block of the remapped
        image for a (uniform-weight) pixel estimate.

    Examples:
        >>> from layoutwarp import UniformLayout
        >>> forward_maps(UniformLayout(), (1, 2), (4, 8)).map_x
        tensor([[1.5000, 5.5000]])
    """
    check_layout(layout)
    size, src_size = check_size(size), check_size(src_size, "src_size")
    u = sample_points(size, samples, jitter=jitter, generator=generator, device=layout.theta.device)
    return _to_maps(map_points(layout, u), src_size)


def inverse_maps(layout: Layout, size: tuple[int, int], target_size: tuple[int, int]) -> Maps:
    """Which sensor-pixel coordinate each target pixel centre falls on.

    Args:
        layout: the pixel layout.
        size: sensor size ``(h, w)`` (the image being sampled).
        target_size: output size ``(H, W)`` (e.g. the ground-truth resolution).

    Returns:
        [`Maps`][] of shape ``(H, W)`` with coordinates on the sensor image: target pixel
        centre ``q`` maps to ``sensor_to_pixels(φ⁻¹(q), (h, w), centered=True)``, so
        ``floor(map + 0.5)`` is the index of the sensor pixel that contains ``q``.
    """
    check_layout(layout)
    size = check_size(size)
    return _to_maps(inverse_coords(layout, target_size), size)


def raster_index_map(
    layout: Layout,
    size: tuple[int, int],
    target_size: tuple[int, int],
    *,
    tol: float = 1e-4,
    oversample: int = 3,
) -> Tensor:
    """The sensor pixel under each target pixel, by rasterising the pixel polygons with OpenCV.

    Every pixel polygon of the mesh (curved edges as polylines within ``tol``) is filled with
    ``cv2.fillPoly`` into a grid ``oversample`` times finer than the target, its value the
    pixel's row-major index, and each target pixel reads the fine pixel at its centre (an odd
    ``oversample`` puts one exactly there). This needs no inverse of φ, so it serves any layout.
    OpenCV rounds vertex rows to the nearest scan line, so a fill can reach half a fine pixel
    past a nearly horizontal edge; the result is the point-in-polygon rule (the pixel whose
    polygon contains the target centre) except for target centres near a pixel boundary: within
    ``1 / oversample`` of a target pixel (half a fine pixel of scan-line rounding, and the fill's
    own pixel rule). A target pixel that no polygon claims
    (possible only around pixels smaller than a fine pixel) takes the nearest claimed index.

    Args:
        layout: the pixel layout.
        size: sensor size ``(h, w)``.
        target_size: target size ``(H, W)``.
        tol: polyline tolerance of curved edges: the area between a polyline and its curve,
            relative to the pixel's area (unitless, as [`pixel_mesh`][]); the
            default ``1e-4`` keeps the polygons far closer to the curves than a target pixel.
        oversample: odd refinement of the drawing grid (memory: ``oversample²`` int32 per target
            pixel).

    Returns:
        ``(H, W)`` int64 tensor of sensor pixel indices ``row · w + col`` (on the CPU).
    """
    (h, w), (ht, wt) = check_size(size), check_size(target_size, "target_size")
    tol = check_number(tol, "tol", 0, lo_open=True)
    k = check_int(oversample, "oversample", 1)
    if k % 2 == 0:
        raise ValueError(f"oversample must be an odd integer >= 1, got {oversample!r}")
    theta = layout.theta_as(torch.float64).detach()
    return torch.ops.layoutwarp.raster_index_map(theta, layout_token(layout), h, w, ht, wt, tol, k)


@torch.library.custom_op("layoutwarp::raster_index_map", mutates_args=())
def _raster_index_map(
    theta: Tensor,
    layout: str,
    height: int,
    width: int,
    target_height: int,
    target_width: int,
    tol: float,
    oversample: int,
) -> Tensor:
    """[`raster_index_map`][] of the layout of a [`layout_token`][layoutwarp.operators.base.layout_token] at
    ``theta``: ``(H, W)`` int64 on the CPU."""
    (h, w), (ht, wt), k = (height, width), (target_height, target_width), oversample
    with torch.no_grad():
        mesh = pixel_mesh(ops.layout_of(layout), (h, w), tol=tol, dtype=torch.float64, theta=theta.cpu())
    shift = 8
    canvas = np.full((ht * k, wt * k), -1, dtype=np.int32)
    for index, poly in enumerate(mesh.polygons()):
        px = sensor_to_pixels(torch.from_numpy(poly), (ht * k, wt * k), centered=True).numpy()
        cv2.fillPoly(canvas, [np.round(px * (1 << shift)).astype(np.int32)], index, cv2.LINE_8, shift)
    canvas = np.ascontiguousarray(canvas[k // 2 :: k, k // 2 :: k])
    missing = canvas < 0
    if missing.any():  # the nearest claimed target pixel's index
        _, labels = cv2.distanceTransformWithLabels(
            missing.astype(np.uint8), cv2.DIST_L2, 5, labelType=cv2.DIST_LABEL_PIXEL
        )
        claimed = canvas.ravel()[np.flatnonzero(~missing.ravel())]
        canvas[missing] = claimed[labels[missing] - 1]
    return torch.from_numpy(canvas.astype(np.int64))


@_raster_index_map.register_fake
def _(theta, layout, height, width, target_height, target_width, tol, oversample):
    return torch.empty(target_height, target_width, dtype=torch.int64)


ops.register(_raster_index_map)
