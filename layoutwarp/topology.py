"""A sensor grid's topology: its ``(H + 1) × (W + 1)`` pixel corners, its edges numbered once
(horizontal then vertical) and each pixel's four, so a boundary integral is computed once per
edge and combined into pixels ([`MeshTopology`][]), for [`layoutwarp.mesh`][]'s meshes and the
compiled ones."""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import TypeVar

import numpy as np
import torch
from torch import Tensor

from .coords import uniform_corners

__all__ = ["MeshTopology"]

_A = TypeVar("_A", Tensor, np.ndarray)


@dataclass(frozen=True)
class MeshTopology:
    """The numbering of an ``(H, W)`` sensor's pixel edges, used by every mesh consumer.

    Horizontal edge ``(i, j)`` (corner row ``0 <= i <= H``, column ``j < W``) runs in ``+x``
    from corner ``(i, j)`` to ``(i, j + 1)`` and has index ``i · W + j``; vertical edge
    ``(i, j)`` (``i < H``, ``0 <= j <= W``) runs in ``+y`` from corner ``(i, j)`` to
    ``(i + 1, j)`` and has index ``(H + 1) W + i (W + 1) + j``. Pixel ``(i, j)`` is bounded by
    horizontal edges ``(i, j)`` (top, ``+``) and ``(i + 1, j)`` (bottom, ``−``) and vertical
    edges ``(i, j + 1)`` (right, ``+``) and ``(i, j)`` (left, ``−``).

    Examples:
        >>> top = MeshTopology((2, 3))
        >>> top.num_edges, top.pixel_edges()[1, 2].tolist()  # top, right, bottom, left
        (17, [5, 16, 8, 15])
    """

    size: tuple[int, int]

    @property
    def num_horizontal(self) -> int:
        """Number of horizontal edges, ``(H + 1) W``; they come first."""
        return (self.size[0] + 1) * self.size[1]

    @property
    def num_edges(self) -> int:
        h, w = self.size
        return (h + 1) * w + h * (w + 1)

    def horizontal(self, i: _A | int, j: _A | int) -> _A | int:
        """Index of horizontal edge ``(i, j)``."""
        return i * self.size[1] + j

    def vertical(self, i: _A | int, j: _A | int) -> _A | int:
        """Index of vertical edge ``(i, j)``."""
        return self.num_horizontal + i * (self.size[1] + 1) + j

    def edge_corners(self, device: torch.device | str | None = None) -> tuple[Tensor, Tensor]:
        """Start and end corner of every edge, ``(E,)`` each, as row-major corner indices.

        Cached per size and device, as is [`edge_ends`][]: do not modify the tensors."""
        return _edge_corners(self.size, torch.device(device or "cpu"))

    def edge_ends(
        self, dtype: torch.dtype = torch.float64, device: torch.device | str | None = None
    ) -> tuple[Tensor, Tensor]:
        """Uniform end points ``(a, b)``, each ``(E, 2)`` in sensor coordinates, of every edge."""
        return _edge_ends(self.size, dtype, torch.device(device or "cpu"))

    def corners(self, dtype: torch.dtype = torch.float64, device: torch.device | str | None = None) -> Tensor:
        """`uniform_corners` flattened to ``(V, 2)``, row-major (cached)."""
        return _corners(self.size, dtype, torch.device(device or "cpu"))

    def pixel_edges(self) -> np.ndarray:
        """``(H, W, 4)`` int64 edge indices of every pixel: top, right, bottom, left."""
        h, w = self.size
        i, j = np.meshgrid(np.arange(h), np.arange(w), indexing="ij")
        return np.stack(
            [self.horizontal(i, j), self.vertical(i, j + 1), self.horizontal(i + 1, j), self.vertical(i, j)],
            -1,
        )

    def edge_pixels(self) -> np.ndarray:
        """``(E, 2)`` int64: the pixel that adds each edge's integral (``+``) and the one that
        subtracts it (``−``), ``-1`` on the sensor border."""
        h, w = self.size
        out = np.full((self.num_edges, 2), -1, dtype=np.int64)
        pix = np.arange(h * w).reshape(h, w)
        edges = self.pixel_edges()
        for k, col in ((0, 0), (1, 0), (2, 1), (3, 1)):  # top and right add, bottom and left subtract
            out[edges[..., k].ravel(), col] = pix.ravel()
        return out

    def combine(self, edge_values: _A) -> _A:
        """Pixel boundary integrals ``(..., H, W)`` from oriented edge integrals ``(..., E)``
        (a tensor or an array)."""
        h, w = self.size
        nh, lead = self.num_horizontal, tuple(edge_values.shape[:-1])
        eh = edge_values[..., :nh].reshape(*lead, h + 1, w)
        ev = edge_values[..., nh:].reshape(*lead, h, w + 1)
        return (eh[..., :-1, :] - eh[..., 1:, :]) + (ev[..., :, 1:] - ev[..., :, :-1])

    def combine_adjoint(self, pixel_values: _A) -> _A:
        """The transpose of [`combine`][]: the gradient ``(..., E)`` of the edge integrals from
        that of the pixels' ``(..., H, W)`` (a tensor or an array)."""
        h, w = self.size
        lead = tuple(pixel_values.shape[:-2])
        if isinstance(pixel_values, np.ndarray):
            eh, ev = np.zeros((*lead, h + 1, w)), np.zeros((*lead, h, w + 1))
        else:
            eh, ev = pixel_values.new_zeros(*lead, h + 1, w), pixel_values.new_zeros(*lead, h, w + 1)
        eh[..., :-1, :] += pixel_values
        eh[..., 1:, :] -= pixel_values
        ev[..., :, 1:] += pixel_values
        ev[..., :, :-1] -= pixel_values
        parts = (eh.reshape(*lead, (h + 1) * w), ev.reshape(*lead, h * (w + 1)))  # an empty lead too
        return np.concatenate(parts, -1) if isinstance(pixel_values, np.ndarray) else torch.cat(parts, -1)


@functools.lru_cache(maxsize=64)
def _edge_corners(size: tuple[int, int], device: torch.device) -> tuple[Tensor, Tensor]:
    h, w = size
    cid = torch.arange((h + 1) * (w + 1), device=device).view(h + 1, w + 1)
    start = torch.cat([cid[:, :-1].flatten(), cid[:-1, :].flatten()])
    end = torch.cat([cid[:, 1:].flatten(), cid[1:, :].flatten()])
    return start, end


@functools.lru_cache(maxsize=64)
def _corners(size: tuple[int, int], dtype: torch.dtype, device: torch.device) -> Tensor:
    return uniform_corners(size, dtype, device).reshape(-1, 2)


@functools.lru_cache(maxsize=64)
def _edge_ends(size: tuple[int, int], dtype: torch.dtype, device: torch.device) -> tuple[Tensor, Tensor]:
    corners = _corners(size, dtype, device)
    start, end = _edge_corners(size, device)
    return corners[start], corners[end]
