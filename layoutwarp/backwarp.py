"""Back-warping: sensor-grid outputs to the uniform ground-truth grid (paper §4).

A network fed by a non-uniform sensor predicts on the deformed grid. For the loss and for
display, every target pixel centre ``q`` reads the sensor pixel that contains it: the
uniform cell of ``φ⁻¹(q)``. Nearest back-warping is a gather, so label maps keep their
dtype and gradients reach the logits (not θ, whose gradient through a piecewise-constant map is
zero: θ learns through the sensor, as in the paper). Bilinear back-warping samples at ``φ⁻¹(q)``,
which moves with θ: its gradient reaches θ too (the implicit derivative of the inverse).
"""

from __future__ import annotations

import cv2
import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from .checks import check_choice, check_shape, check_size
from .coords import pixel_centers, pixel_containing
from .layouts import Layout, check_layout, wants_grad
from .maps import inverse_coords, raster_index_map

__all__ = ["backwarp", "backwarp_cross_entropy", "backwarp_numpy", "sensor_index_maps"]


#: How nearest back-warping finds the sensor pixel of a target pixel.
INDEX_METHODS = ("inverse", "raster")


def sensor_index_maps(
    layout: Layout, size: tuple[int, int], target_size: tuple[int, int], method: str = "inverse"
) -> tuple[Tensor, Tensor]:
    """Integer sensor pixel ``(col, row)`` containing each target pixel centre.

    Args:
        layout: the pixel layout.
        size: sensor size ``(h, w)``.
        target_size: target size ``(H, W)``.
        method: ``"inverse"`` (the exact point inverse φ⁻¹ of every target centre) or
            ``"raster"`` (the pixel polygons filled into the target grid by OpenCV, see
            [`raster_index_map`][]: no inverse needed; differs from
            ``"inverse"`` only in target pixels that a pixel boundary passes through).

    Returns:
        two ``(H, W)`` int64 tensors ``col = floor((φ⁻¹(q)_x + 1) w / 2)`` and likewise
        ``row``, clamped to the sensor. Computed in float64; a centre on a pixel boundary goes to
        the pixel on its right/below ([`pixel_containing`][layoutwarp.coords.pixel_containing]).
    """
    check_layout(layout)
    (h, w), target_size = check_size(size), check_size(target_size, "target_size")
    check_choice(method, INDEX_METHODS, "method")
    if method == "raster":
        idx = raster_index_map(layout, (h, w), target_size).to(layout.rho.device)
        return idx % w, idx // w
    idx = pixel_containing(inverse_coords(layout, target_size), (h, w))
    return idx[..., 0], idx[..., 1]


def backwarp(
    pred: Tensor,
    layout: Layout,
    target_size: tuple[int, int],
    mode: str = "nearest",
    index_method: str = "inverse",
) -> Tensor:
    """Resample a sensor-grid tensor to the uniform grid of ``target_size``.

    Args:
        pred: ``(B, C, h, w)`` (or ``(B, h, w)`` label maps) on the sensor grid.
        layout: the layout the sensor image was taken with.
        target_size: target size ``(H, W)``.
        mode: ``"nearest"`` (each target pixel takes the value of the sensor pixel that
            contains its centre; any dtype) or ``"bilinear"`` (smooth display of continuous
            outputs, sampled at ``φ⁻¹(q)`` with border padding; floating dtypes).
        index_method: how ``"nearest"`` finds each target's sensor pixel (see
            `sensor_index_maps`).

    Returns:
        ``(B, C, H, W)`` (or ``(B, H, W)``) with ``pred``'s dtype, on ``pred``'s device.

    Examples:
        >>> from layoutwarp import RectLayout
        >>> # θ_x = 0.5: the middle one of three sensor pixels is small, the outer ones wide
        >>> backwarp(torch.arange(3.0).view(1, 1, 1, 3), RectLayout((0.5, 0.0)), (1, 8))[0, 0]
        tensor([[0., 0., 0., 1., 1., 2., 2., 2.]])
    """
    check_layout(layout)
    check_shape(pred, "B C h w|B h w", "pred")
    size = check_size(target_size, "target_size")
    check_choice(mode, ("nearest", "bilinear"), "mode")
    h, w = pred.shape[-2:]
    if mode == "nearest":
        col, row = sensor_index_maps(layout, (h, w), size, index_method)
        idx = (row * w + col).to(pred.device).flatten()
        return pred.flatten(-2).index_select(-1, idx).unflatten(-1, size)
    if mode == "bilinear":
        if not pred.is_floating_point():
            raise TypeError(
                f"mode='bilinear' needs a floating-point pred, got {pred.dtype}; use mode='nearest'"
            )
        p = _theta_attached(layout, inverse_coords(layout, size), size).to(pred)
        x = pred if pred.ndim == 4 else pred[:, None]
        out = F.grid_sample(
            x,
            p[None].expand(x.shape[0], -1, -1, -1),
            mode="bilinear",
            padding_mode="border",
            align_corners=False,
        )
        return out if pred.ndim == 4 else out[:, 0]


def _theta_attached(layout: Layout, p: Tensor, size: tuple[int, int]) -> Tensor:
    """``p = φ⁻¹(q, θ)`` of the target centres ``q`` (float64, no gradient), with θ's gradient
    re-attached where θ needs one (a learnable layout, or θ batched under ``torch.vmap``): one
    Newton step ``p − J⁻¹ (φ(p, θ) − q)``, equal to ``p`` in value (the residual is the
    inverse's, ~1e-13) and with the implicit derivative ``∂p/∂θ = −J⁻¹ ∂φ/∂θ``."""
    theta = layout.theta
    if not (torch.is_grad_enabled() and wants_grad(theta)):
        return p
    q = pixel_centers(size, dtype=torch.float64, device=p.device)
    th = theta.to(torch.float64)
    j = layout.phi_jacobian(p, th.detach())  # (H, W, 2, 2)
    residual = layout.phi(p, th) - q
    return p - torch.linalg.solve(j, residual.unsqueeze(-1)).squeeze(-1)


def backwarp_numpy(
    arr: np.ndarray, layout: Layout, target_size: tuple[int, int], index_method: str = "inverse"
) -> np.ndarray:
    """OpenCV back-warping of an HW or HWC numpy array (nearest; ``cv2.remap``).

    Bit-identical to `backwarp` with ``mode="nearest"`` and the same ``index_method``:
    the remap maps hold the integer sensor indices, so ``INTER_NEAREST`` reads exactly the
    same pixel.
    Supports the dtypes ``cv2.remap`` does (uint8, uint16, int16, float32, float64).
    """
    check_layout(layout)
    if not isinstance(arr, np.ndarray) or arr.ndim not in (2, 3):
        raise ValueError(f"arr must be an HW or HWC numpy array, got {getattr(arr, 'shape', arr)!r}")
    col, row = sensor_index_maps(layout, arr.shape[:2], target_size, index_method)
    return cv2.remap(
        arr,
        col.cpu().numpy().astype(np.float32),
        row.cpu().numpy().astype(np.float32),
        cv2.INTER_NEAREST,
        borderMode=cv2.BORDER_REPLICATE,
    )


def backwarp_cross_entropy(
    logits: Tensor, labels: Tensor, layout: Layout, *, ignore_index: int = -100, weight: Tensor | None = None
) -> Tensor:
    """Cross-entropy between back-warped sensor-grid logits and full-resolution labels.

    Args:
        logits: ``(B, K, h, w)`` class scores on the sensor grid.
        labels: ``(B, H, W)`` int64 class indices on the uniform ground-truth grid.
        layout: the layout of the sensor.
        ignore_index: label value excluded from the loss (e.g. CamVid's "Unlabelled").
        weight: optional per-class weights.

    Returns:
        the mean loss over non-ignored pixels, differentiable in ``logits``.
    """
    check_layout(layout)
    check_shape(labels, ["B", "H", "W"], "labels")
    check_shape(logits, ["B", "K", "h", "w"], "logits")
    if logits.shape[0] != labels.shape[0]:
        raise ValueError(
            f"logits and labels must have the same batch size, got {logits.shape[0]} and {labels.shape[0]}"
        )
    # Nearest back-warping copies each sensor pixel to the targets it contains, so the loss is
    # a count-weighted cross-entropy on the sensor grid: count[b, c, k] = number of (non-ignored)
    # targets of class c that read sensor pixel k. Same value and gradient, without building
    # the (B, K, H, W) back-warped logits.
    b, k, h, w = logits.shape
    col, row = sensor_index_maps(layout, (h, w), tuple(labels.shape[-2:]))
    pix = (row * w + col).to(labels.device).flatten()
    lab = labels.long().flatten(1)
    valid = lab != ignore_index
    if bool(((lab < 0) | (lab >= k))[valid].any()):
        raise ValueError(f"labels must be in [0, {k}) or ignore_index={ignore_index}")
    idx = (torch.arange(b, device=lab.device)[:, None] * k + lab.clamp(0, k - 1)) * (h * w) + pix
    counts = torch.bincount(idx[valid], minlength=b * k * h * w).view(b, k, h * w).to(logits.dtype)
    if weight is not None:
        counts = counts * weight.to(logits.dtype)[None, :, None]
    nll = -F.log_softmax(logits.flatten(2), dim=1)
    return (counts * nll).sum() / counts.sum()
