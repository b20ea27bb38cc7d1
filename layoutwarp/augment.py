"""The sensor as a step of a Kornia augmentation pipeline.

[`SensorAugmentation`][] fits inside ``kornia.augmentation.AugmentationSequential`` next
to Kornia's own augmentations. Per data key:

* ``input`` images go through a [`SensorLayer`][] (differentiable in θ, which is
  a parameter of the augmentation and therefore of the container; a learnable layout is
  guarded as the layer guards it, e.g. a [`GridLayout`][layoutwarp.layouts.grid.GridLayout] against folding);
* ``mask`` label maps go to the sensor grid by ``mask_rule``
  ([`labels_to_sensor`][]): ``"nearest"`` (the label at the deformed
  pixel centre) or ``"majority"`` (the label covering most of the pixel's area);
* ``keypoints`` go through ``φ⁻¹`` to sensor pixel coordinates (Kornia's convention: pixel
  centres at integers), and back through ``φ`` on ``inverse``;
* ``bbox`` boxes: the tight axis-aligned box of the box's outline mapped through ``φ⁻¹`` (and
  through ``φ`` on ``inverse``), as learned-zoom detectors map boxes through a warp. Exact for
  separable (rectangular) layouts, where a box maps to a box; for the others the outline is
  sampled at [`BOX_SAMPLES`][] points a side, which keeps the box within 0.01 sensor pixels
  of the outline's true extent (tested against 4097 points a side).

``AugmentationSequential.inverse`` back-warps images and masks to the input size with
nearest neighbour (`backwarp`).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import torch
from kornia.augmentation import GeometricAugmentationBase2D
from torch import Tensor

from .backwarp import backwarp
from .checks import check_choice
from .coords import pixels_to_sensor, sensor_to_pixels
from .labels import LABEL_RULES, labels_to_sensor
from .layouts import Layout
from .maps import map_points
from .sensor import SensorLayer

__all__ = ["BOX_SAMPLES", "SensorAugmentation"]

#: Points a side at which a box's outline is mapped (see the module docstring).
BOX_SAMPLES = 257


class SensorAugmentation(GeometricAugmentationBase2D):
    """Simulate a sensor with a (learnable) pixel layout as a Kornia augmentation.

    Args:
        size: sensor size ``(h, w)``.
        layout: a registered family name (``"rect"``, ``"curv"``, ``"uniform"``, ...) or a
            [`Layout`][].
        method: integrator (see [`simulate`][layoutwarp.sensor.simulate]).
        mask_rule: ``"nearest"`` or ``"majority"`` (see the module docstring).
        learn: train θ (for a family name), as [`SensorLayer`][].
        theta: initial θ (for a family name).
        **options: as [`SensorLayer`][] (unknown options are
            refused here, not at the first batch).

    Examples:
        >>> import kornia.augmentation as K
        >>> aug = K.AugmentationSequential(K.RandomHorizontalFlip(), SensorAugmentation((16, 16), "rect"),
        ...                                data_keys=["input", "mask"])
        >>> img, mask = aug(torch.rand(2, 3, 64, 64), torch.randint(0, 5, (2, 1, 64, 64)).float())
        >>> img.shape, mask.shape
        (torch.Size([2, 3, 16, 16]), torch.Size([2, 1, 16, 16]))
    """

    def __init__(
        self,
        size: tuple[int, int],
        layout: str | Layout = "rect",
        method: str = "exact",
        *,
        mask_rule: str = "nearest",
        learn: bool | None = None,
        theta: Sequence[float] | Tensor | None = None,
        **options: Any,
    ) -> None:
        super().__init__(p=1.0, same_on_batch=True, keepdim=False)
        self.sensor = SensorLayer(size, layout, method, learn=learn, theta=theta, **options)
        check_choice(mask_rule, LABEL_RULES, "mask_rule")
        self.mask_rule = mask_rule
        self.flags = {"size": self.size}

    @property
    def size(self) -> tuple[int, int]:
        """The sensor size ``(h, w)``."""
        return self.sensor.size

    @property
    def layout(self) -> Layout:
        """The sensor's layout (θ is a parameter of this module)."""
        return self.sensor.layout

    # Kornia plumbing: the sensor is not a matrix; an identity keeps the container's
    # matrix bookkeeping consistent, and every data path below ignores it.
    def compute_transformation(self, input: Tensor, params: dict[str, Tensor], flags: dict) -> Tensor:
        return torch.eye(3, device=input.device, dtype=input.dtype).expand(input.shape[0], 3, 3)

    def apply_transform(self, input: Tensor, params, flags, transform=None) -> Tensor:
        return self.sensor(input)

    def apply_non_transform(self, input: Tensor, params, flags, transform=None) -> Tensor:
        return self.apply_transform(input, params, flags, transform)  # p = 1: never reached

    def apply_transform_mask(self, input: Tensor, params, flags, transform=None) -> Tensor:
        return self.masks_to_sensor(input)

    def inverse_transform(self, input: Tensor, flags, transform=None, size=None) -> Tensor:
        if size is None:
            raise ValueError("SensorAugmentation.inverse needs the original size")
        return backwarp(input, self.layout, tuple(int(v) for v in size[-2:]))

    def masks_to_sensor(self, masks: Tensor) -> Tensor:
        """Label maps ``(B, 1, H, W)`` (any dtype holding integers) to the sensor grid."""
        return labels_to_sensor(masks, self.layout, self.size, self.mask_rule)

    # keypoints and boxes -------------------------------------------------------------
    def _to_sensor_points(self, pts: Tensor, src_hw: tuple[int, int], inverse: bool) -> Tensor:
        """Pixel coordinates (centres at integers) between the source and the sensor."""
        src, dst = (src_hw, self.size) if not inverse else (self.size, src_hw)
        q = pixels_to_sensor(pts.double(), src, centered=True)
        p = map_points(self.layout, q, inverse=not inverse)
        return sensor_to_pixels(p, dst, centered=True).to(pts)

    def keypoints_to_sensor(self, pts: Tensor, src_hw: tuple[int, int]) -> Tensor:
        """``(..., 2)`` source pixel ``(x, y)`` to sensor pixel coordinates via ``φ⁻¹``."""
        return self._to_sensor_points(pts, src_hw, inverse=False)

    def keypoints_from_sensor(self, pts: Tensor, src_hw: tuple[int, int]) -> Tensor:
        """Sensor pixel coordinates back to source pixel ``(x, y)`` via ``φ``."""
        return self._to_sensor_points(pts, src_hw, inverse=True)

    def boxes_to_sensor(self, corners: Tensor, src_hw: tuple[int, int], inverse: bool = False) -> Tensor:
        """Boxes as their 4 corners ``(..., 4, 2)`` (pixel ``(x, y)``) to the tight axis-aligned
        boxes of their mapped outlines, in the same corner order (``inverse``: sensor to source)."""
        lo, hi = corners.amin(-2), corners.amax(-2)  # (..., 2)
        t = torch.linspace(0, 1, BOX_SAMPLES, dtype=torch.float64, device=corners.device)
        x0, y0, x1, y1 = (v.double()[..., None] for v in (lo[..., 0], lo[..., 1], hi[..., 0], hi[..., 1]))
        xs, ys = x0 + t * (x1 - x0), y0 + t * (y1 - y0)
        outline = torch.cat(
            [
                torch.stack([xs, y0.expand_as(xs)], -1),
                torch.stack([x1.expand_as(ys), ys], -1),
                torch.stack([xs, y1.expand_as(xs)], -1),
                torch.stack([x0.expand_as(ys), ys], -1),
            ],
            -2,
        )
        mapped = self._to_sensor_points(outline, src_hw, inverse)
        new_lo, new_hi = mapped.amin(-2), mapped.amax(-2)
        is_lo = corners == lo[..., None, :]
        return torch.where(is_lo, new_lo[..., None, :], new_hi[..., None, :]).to(corners)

    @staticmethod
    def _with_data(obj, data: Tensor):
        out = obj.clone()
        out._data = data  # how Kornia's own containers update Keypoints/Boxes
        return out

    @staticmethod
    def _src_hw(params: dict[str, Tensor]) -> tuple[int, int]:
        return int(params["src_hw"][0, 0]), int(params["src_hw"][0, 1])

    def apply_transform_keypoint(self, input, params, flags, transform=None):
        return self._with_data(input, self.keypoints_to_sensor(input.data, self._src_hw(params)))

    def inverse_keypoints(self, input, params, flags, transform=None, **kwargs):
        return self._with_data(input, self.keypoints_from_sensor(input.data, self._src_hw(params)))

    def apply_transform_box(self, input, params, flags, transform=None):
        return self._with_data(input, self.boxes_to_sensor(input.data, self._src_hw(params)))

    def inverse_boxes(self, input, params, flags, transform=None, **kwargs):
        return self._with_data(input, self.boxes_to_sensor(input.data, self._src_hw(params), inverse=True))

    def generate_parameters(self, shape: tuple[int, ...]) -> dict[str, Tensor]:
        return {"src_hw": torch.tensor([[shape[-2], shape[-1]]] * shape[0])}
