"""The coordinate convention, written once.

* Sensor coordinates: points ``(x, y)`` in ``[-1, 1]²``; ``x`` runs along the image width
  (columns), ``y`` along the height (rows, downwards). ``-1`` is the outer edge of the first
  pixel and ``+1`` the outer edge of the last (``grid_sample``'s ``align_corners=False``).
* Pixel coordinates of an ``(H, W)`` image: ``X = (x + 1) · W / 2``, ``Y = (y + 1) · H / 2``,
  so pixel ``c`` covers ``[c, c + 1)``. With ``centered=True`` pixel centres sit at
  integers instead (``X − 0.5``): the convention of ``cv2.remap`` maps and of Kornia
  keypoints.
* Physical units: the same map with ``size = (H_um, W_um)`` gives micrometres.

Sizes are ``(H, W)`` here as in torch and Kornia; the command line writes ``WIDTHxHEIGHT``.
"""

from __future__ import annotations

import torch
from torch import Tensor

from .checks import check_size

__all__ = [
    "ON_BOUNDARY",
    "cell_index",
    "grid_lines",
    "pixel_centers",
    "pixel_containing",
    "pixels_to_sensor",
    "sensor_to_pixels",
    "uniform_corners",
]


def grid_lines(
    n: int, dtype: torch.dtype = torch.float64, device: torch.device | str | None = None
) -> Tensor:
    """The ``n + 1`` uniform cell boundaries ``(2k − n)/n`` of ``[-1, 1]`` (exactly ±1 at the ends).

    Examples:
        >>> grid_lines(4)
        tensor([-1.0000, -0.5000,  0.0000,  0.5000,  1.0000], dtype=torch.float64)
    """
    k = torch.arange(n + 1, dtype=dtype, device=device)
    return (2 * k - n) / n


def cell_index(x: Tensor, n: int) -> tuple[Tensor, Tensor]:
    """The uniform cell of ``[-1, 1]`` (``n`` cells) holding each of ``x``, and the position in it.

    Points are clamped to ``[-1, 1]``; ``+1`` belongs to the last cell (position 1). The
    position ``∈ [0, 1]`` is differentiable in ``x``; the index is not.

    Examples:
        >>> cell_index(torch.tensor([-1.0, 0.25, 1.0]), 4)
        (tensor([0, 2, 3]), tensor([0.0000, 0.5000, 1.0000]))
    """
    u = (x.clamp(-1, 1) + 1) * (n / 2)
    i = u.detach().floor().clamp(0, n - 1)
    return i.long(), u - i


#: How far (in pixels) before a pixel boundary a point still lies on it for [`pixel_containing`][]:
#: the float64 rounding of the maps that compute the point (about 1e-12 pixels at thousands of
#: pixels), with room to spare.
ON_BOUNDARY = 1e-9


def pixel_containing(p: Tensor, size: tuple[int, int]) -> Tensor:
    """The pixel ``(column, row)`` (int64, ``(..., 2)``) of an ``(H, W)`` image containing each
    sensor point ``p`` ``(..., 2)`` (float64: the rounding it allows for is float64's), clamped to
    the image. A point on a pixel boundary goes to the pixel after it (right, below), also where
    rounding put it a hair before (``ON_BOUNDARY``): the centres of a uniform sensor of ``w``
    pixels over ``10 w`` source columns fall on source columns ``5, 15, 25, …``, every one.

    Examples:
        >>> pixel_containing(torch.tensor([[0.0, -1.0], [1 - 2**-52, 1.0]], dtype=torch.float64), (2, 4))
        tensor([[2, 0],
                [3, 1]])
    """
    h, w = check_size(size)
    idx = torch.floor(sensor_to_pixels(p, (h, w)) + ON_BOUNDARY).long()
    return torch.stack([idx[..., 0].clamp(0, w - 1), idx[..., 1].clamp(0, h - 1)], -1)


def uniform_corners(
    size: tuple[int, int], dtype: torch.dtype = torch.float64, device: torch.device | str | None = None
) -> Tensor:
    """Uniform pixel corners, shape ``(H + 1, W + 1, 2)`` holding ``(x, y)``."""
    h, w = check_size(size)
    ys, xs = grid_lines(h, dtype, device), grid_lines(w, dtype, device)
    return torch.stack(torch.meshgrid(xs, ys, indexing="xy"), -1)


def pixel_centers(
    size: tuple[int, int], dtype: torch.dtype = torch.float64, device: torch.device | str | None = None
) -> Tensor:
    """Uniform pixel centres, shape ``(H, W, 2)`` holding ``(x, y)``."""
    h, w = check_size(size)
    xs = (2 * torch.arange(w, dtype=dtype, device=device) + 1 - w) / w
    ys = (2 * torch.arange(h, dtype=dtype, device=device) + 1 - h) / h
    return torch.stack(torch.meshgrid(xs, ys, indexing="xy"), -1)


def _half_extent(p: Tensor, size: tuple[float, float]) -> Tensor:
    h, w = size
    return torch.tensor([w / 2, h / 2], dtype=p.dtype, device=p.device)


def sensor_to_pixels(p: Tensor, size: tuple[float, float], *, centered: bool = False) -> Tensor:
    """Sensor coordinates ``(..., 2)`` to pixel coordinates of an ``(H, W)`` image.

    ``X = (x + 1) · W / 2`` (pixel ``c`` covers ``[c, c + 1)``), minus ``0.5`` with
    ``centered=True`` (pixel centres at integers, OpenCV ``remap`` / Kornia keypoints).

    Examples:
        >>> sensor_to_pixels(torch.tensor([[-1.0, 1.0]]), (4, 8))
        tensor([[0., 4.]])
    """
    out = (p + 1) * _half_extent(p, size)
    return out - 0.5 if centered else out


def pixels_to_sensor(p: Tensor, size: tuple[float, float], *, centered: bool = False) -> Tensor:
    """Inverse of [`sensor_to_pixels`][]."""
    return (p + 0.5 if centered else p) / _half_extent(p, size) - 1
