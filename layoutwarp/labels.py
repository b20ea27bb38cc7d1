"""Label maps onto the sensor grid: the one rule set that Kornia masks and preprocessing share.

A class-index map of the source resolution goes to the sensor grid by one of two rules:

* ``"nearest"``: the label of the source pixel under each deformed pixel centre ``φ(c_k)``
  (the pixel whose cell ``[c, c + 1) × [r, r + 1)`` contains it; a centre exactly on a cell
  boundary takes the cell to its right/below, as back-warping does);
* ``"majority"``: the label covering the largest share of the pixel's area, from the exact area
  integral of each class's indicator; shares within ``1e-6`` of the largest count as ties, and
  a tie goes to the smaller label.

The way back, sensor grid to full resolution, is `backwarp`.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch
from torch import Tensor

from .checks import check_choice, check_size
from .coords import pixel_centers, pixel_containing
from .integrators import integrate_exact
from .layouts import Layout
from .maps import map_points

__all__ = ["LABEL_RULES", "TIE", "labels_to_sensor", "source_pixels"]

#: The rules [`labels_to_sensor`][] knows.
LABEL_RULES = ("nearest", "majority")
#: Area shares closer than this to the largest one tie (and go to the smaller label).
TIE = 1e-6

#: A linear area operator: class indicators ``(K, H, W)`` float to their pixel means ``(K, h, w)``.
AreaOperator = Callable[[Tensor], Tensor]


def source_pixels(layout: Layout, size: tuple[int, int], src_size: tuple[int, int]) -> tuple[Tensor, Tensor]:
    """Row and column of the source pixel under every deformed pixel centre.

    Args:
        layout: the pixel layout (θ fixed).
        size: sensor size ``(h, w)``.
        src_size: source size ``(H, W)``.

    Returns:
        two ``(h, w)`` int64 tensors on the CPU, clamped to the source.

    Examples:
        >>> from layoutwarp import UniformLayout
        >>> source_pixels(UniformLayout(), (1, 2), (2, 4))[1]
        tensor([[1, 3]])
    """
    (h, w), (hs, ws) = check_size(size), check_size(src_size, "src_size")
    q = map_points(layout, pixel_centers((h, w)))
    idx = pixel_containing(q, (hs, ws)).cpu()
    return idx[..., 1], idx[..., 0]


def labels_to_sensor(
    labels: Tensor | np.ndarray,
    layout: Layout,
    size: tuple[int, int],
    rule: str = "nearest",
    *,
    area: AreaOperator | None = None,
) -> Tensor | np.ndarray:
    """Move integer label maps ``(..., H, W)`` to the sensor grid ``(..., h, w)``.

    Args:
        labels: class indices, a tensor or numpy array of any dtype holding integers.
        layout: the pixel layout (θ fixed; no gradient flows).
        size: sensor size ``(h, w)``.
        rule: ``"nearest"`` or ``"majority"`` (see the module docstring).
        area: for ``"majority"``, the area operator that integrates class indicators
            ``(K, H, W)`` to pixel means ``(K, h, w)`` (e.g. an
            [`AreaResampler`][layoutwarp.resampler.AreaResampler]'s weights); default: the exact integrator.

    Returns:
        the labels on the sensor grid, of ``labels``' type, dtype and (tensor) device.
    """
    check_choice(rule, LABEL_RULES, "rule")
    size = check_size(size)
    is_numpy = isinstance(labels, np.ndarray)
    lab = torch.from_numpy(np.ascontiguousarray(labels)) if is_numpy else labels
    if lab.ndim < 2:
        raise ValueError(f"labels must have shape (..., H, W), got {tuple(lab.shape)}")
    lead, src = lab.shape[:-2], tuple(lab.shape[-2:])
    if rule == "nearest":
        row, col = source_pixels(layout, size, src)
        out = lab[..., row.to(lab.device), col.to(lab.device)]
    else:
        out = _majority(lab.reshape(-1, *src), layout, size, area).reshape(*lead, *size)
    return out.numpy() if is_numpy else out


def _majority(lab: Tensor, layout: Layout, size: tuple[int, int], area: AreaOperator | None) -> Tensor:
    """The majority rule for ``(N, H, W)`` labels: one indicator integral per present class."""
    if area is None:

        def area(x: Tensor) -> Tensor:
            return integrate_exact(x, layout, size).to(torch.float32)

    best = torch.full((lab.shape[0], *size), -1.0, device=lab.device)
    out = torch.zeros(best.shape, dtype=lab.dtype, device=lab.device)
    for k in torch.unique(lab).tolist():  # ascending: a tie keeps the smaller label
        share = area((lab == k).to(torch.float32)).to(best)
        better = share > best + TIE
        best = torch.where(better, share, best)
        out = torch.where(better, torch.as_tensor(k, dtype=lab.dtype, device=lab.device), out)
    return out
