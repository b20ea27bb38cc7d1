"""Layouts from an importance map: pixels where a scene needs them, without learning.

[`layout_from_density`][] makes the pixel density (pixels per unit sensor area) follow a
non-negative importance map ``d``, e.g. a dataset's mean edge strength ([`edge_density`][])
or label-boundary density. The map is first mixed with the uniform density,
``d' = (1 − floor) d / mean(d) + floor``, which bounds how far pixels can grow: a spline
layout's pixel rows and columns, and a grid layout's control rows, are at most ``1 / floor``
times their uniform width. Then, with ``F`` a cumulative distribution of ``d'`` (piecewise linear between
the map's cells):

* ``kind="spline"`` (separable, rectangular pixels): each axis is the inverse of the CDF of
  ``d'``'s marginal, sampled at ``k`` equal quantiles: a piecewise-linear
  [`SplineLayout`][] whose ``k`` pieces each hold an equal share of the mass;
* ``kind="grid"``: the Knothe–Rosenblatt map on a control grid: control rows at equal
  quantiles of the vertical marginal, and along each control row the columns at equal
  quantiles of the density averaged over the two control bands around that row. Control cells
  are trapezoids with horizontal top and bottom, so the [`GridLayout`][] never
  folds, and the pixel density follows ``d'`` in both directions.
"""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np
import torch
from torch import Tensor

from .checks import check_choice, check_number, check_size
from .coords import grid_lines
from .layouts import GridLayout, Layout, SplineLayout

__all__ = ["edge_density", "layout_from_density"]


def _inverse_cdf(mass: np.ndarray, n: int) -> np.ndarray:
    """The ``n + 1`` points of ``[-1, 1]`` at equal quantiles of the piecewise-constant density
    whose cells (equal width) hold ``mass``; exactly ``±1`` at the ends."""
    cdf = np.concatenate([[0.0], np.cumsum(mass)])
    cdf /= cdf[-1]
    x = np.interp(np.arange(n + 1) / n, cdf, grid_lines(len(mass)).numpy())
    x[0], x[-1] = -1.0, 1.0
    return x


def _band_rows(y: np.ndarray, i: int, n_rows: int) -> np.ndarray:
    """Overlap weights of the density map's ``n_rows`` rows with the band ``[y_{i−1}, y_{i+1}]``."""
    lo, hi = y[max(i - 1, 0)], y[min(i + 1, len(y) - 1)]
    edges = grid_lines(n_rows).numpy()
    return np.clip(np.minimum(edges[1:], hi) - np.maximum(edges[:-1], lo), 0, None)


def layout_from_density(
    density: Tensor | np.ndarray,
    size: Sequence[int],
    kind: str = "spline",
    *,
    knots: Sequence[int] | None = None,
    grid: Sequence[int] | None = None,
    floor: float = 0.25,
    learn: bool = False,
    dtype: torch.dtype | None = torch.float64,
) -> Layout:
    """A layout whose pixel density follows ``density`` (see `layoutwarp.density`).

    Args:
        density: ``(h_d, w_d)`` non-negative importance map over the sensor (row 0 at the top),
            any resolution.
        size: sensor size ``(H, W)``; sets the default resolution of the layout.
        kind: ``"spline"`` (separable) or ``"grid"`` (Knothe–Rosenblatt control grid).
        knots: ``(k_x, k_y)`` spline pieces (default ``(min(W, 64), min(H, 64))``; with one piece
            per pixel every pixel row and column holds an equal share of the mass).
        grid: ``(g_h, g_w)`` control cells for ``kind="grid"`` (default ``(min(H, 32), min(W, 32))``).
        floor: share of the uniform density mixed in, in ``(0, 1]`` (1 gives the uniform layout;
            smaller lets pixels grow more where the map is empty).
        learn: passed to the layout (it can start a learned layout).
        dtype: passed to the layout.

    Examples:
        >>> d = torch.ones(8, 8)
        >>> d[:, :4] = 3.0  # three times the detail on the left half
        >>> layout = layout_from_density(d, (4, 4), floor=1e-9)
        >>> [round(v, 3) for v in layout.knot_outputs()[0].tolist()]
        [-1.0, -0.667, -0.333, 0.0, 1.0]
    """
    check_choice(kind, ("spline", "grid"), "kind")
    h, w = check_size(size)
    floor = check_number(floor, "floor", 0, 1, lo_open=True)
    d = torch.as_tensor(np.asarray(density) if not isinstance(density, Tensor) else density)
    d = d.detach().double().cpu().numpy()
    if d.ndim != 2 or 0 in d.shape:
        raise ValueError(f"density must be a non-empty 2-D map (h_d, w_d), got shape {d.shape}")
    if not np.isfinite(d).all() or (d < 0).any() or d.sum() <= 0:
        raise ValueError("density must be finite and non-negative with a positive sum")
    d = (1 - floor) * d / d.mean() + floor
    if kind == "spline":
        kx, ky = knots if knots is not None else (min(w, 64), min(h, 64))
        return SplineLayout.from_knots(
            _inverse_cdf(d.mean(0), int(kx)), _inverse_cdf(d.mean(1), int(ky)), learn=learn, dtype=dtype
        )
    gh, gw = check_size(grid if grid is not None else (min(h, 32), min(w, 32)), "grid")
    ys = _inverse_cdf(d.mean(1), gh)
    ctrl = np.empty((gh + 1, gw + 1, 2))
    for i in range(gh + 1):
        band = _band_rows(ys, i, d.shape[0]) @ d  # the density along x near control row i
        ctrl[i, :, 0] = _inverse_cdf(band, gw)
        ctrl[i, :, 1] = ys[i]
    return GridLayout(torch.from_numpy(ctrl), learn=learn, dtype=dtype)


def edge_density(images: Tensor | np.ndarray, size: Sequence[int] | None = None) -> Tensor:
    """Mean gradient magnitude (Sobel) of a stack of images: an importance map for
    [`layout_from_density`][].

    Args:
        images: ``(N, H, W)`` or ``(N, C, H, W)`` (channels are averaged), any real dtype.
        size: resize the map to ``(h, w)`` with ``INTER_AREA`` (default: keep ``(H, W)``).

    Returns:
        ``(H, W)`` (or ``size``) float64 map.
    """
    x = torch.as_tensor(np.asarray(images) if not isinstance(images, Tensor) else images)
    if x.ndim == 4:
        x = x.double().mean(1)
    if x.ndim != 3:
        raise ValueError(f"images must have shape (N, H, W) or (N, C, H, W), got {tuple(x.shape)}")
    acc = np.zeros(x.shape[-2:])
    for img in x.double().cpu().numpy():
        gx = cv2.Sobel(img, cv2.CV_64F, 1, 0, ksize=3)
        gy = cv2.Sobel(img, cv2.CV_64F, 0, 1, ksize=3)
        acc += np.hypot(gx, gy)
    acc /= max(len(x), 1)
    if size is not None:
        hh, ww = check_size(size)
        acc = cv2.resize(acc, (ww, hh), interpolation=cv2.INTER_AREA)
    return torch.from_numpy(acc)
