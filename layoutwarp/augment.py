"""The sensor as a step of a Kornia augmentation pipeline.

:class:`SensorAugmentation` fits inside ``kornia.augmentation.AugmentationSequential`` next
to Kornia's own augmentations. Per data key:

* ``input`` images go through :func:`~layoutwarp.simulate` (differentiable in θ, which is a
  parameter of the augmentation and therefore of the container);
* ``mask`` label maps go to the sensor grid by ``mask_rule``: ``"nearest"`` (the label at
  the deformed pixel centre) or ``"majority"`` (the label covering most of the pixel's
  area, computed exactly as the area integral of the one-hot mask);
* ``keypoints`` go through ``φ⁻¹`` to sensor pixel coordinates (Kornia's convention: pixel
  centres at integers), and back through ``φ`` on ``inverse``;
* ``bbox`` boxes: exact for separable (rectangular) layouts, where an axis-aligned box maps
  to an axis-aligned box through its corners; for curvilinear layouts a box is not a box on
  the sensor, so they raise ``NotImplementedError`` rather than pass through silently wrong.

``AugmentationSequential.inverse`` back-warps images and masks to the input size with
nearest neighbour (:func:`~layoutwarp.backwarp`).
"""

from __future__ import annotations

from typing import Any

import torch
from kornia.augmentation import GeometricAugmentationBase2D
from torch import Tensor

from .backwarp import backwarp
from .checks import check_choice, check_int, check_size
from .coords import pixels_to_sensor, sensor_to_pixels
from .layouts import Layout, make_layout
from .sensor import METHODS, simulate

__all__ = ["SensorAugmentation"]


class SensorAugmentation(GeometricAugmentationBase2D):
    """Simulate a sensor with a (learnable) pixel layout as a Kornia augmentation.

    Args:
        size: sensor size ``(h, w)``.
        layout: a registered family name (``"rect"``, ``"curv"``, ``"uniform"``, ...) or a
            :class:`~layoutwarp.Layout`.
        method: integrator (see :func:`~layoutwarp.simulate`).
        mask_rule: ``"nearest"`` or ``"majority"`` (see the module docstring).
        num_classes: number of mask classes for ``"majority"`` (labels ``>= num_classes``,
            e.g. an ignore label, are kept as a class of their own).
        learn: train θ (for a family name).
        theta: initial θ (for a family name).
        **options: further :func:`~layoutwarp.simulate` options.

    Example:
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
        num_classes: int | None = None,
        learn: bool = True,
        theta=None,
        **options: Any,
    ) -> None:
        super().__init__(p=1.0, same_on_batch=True, keepdim=False)
        self.size = check_size(size)
        self.layout = layout if isinstance(layout, Layout) else make_layout(layout, theta, learn=learn)
        check_choice(method, METHODS, "method")
        check_choice(mask_rule, ("nearest", "majority"), "mask_rule")
        if mask_rule == "majority":
            check_int(num_classes, "num_classes", 1)
        self.method, self.mask_rule, self.num_classes, self.options = method, mask_rule, num_classes, options
        self.flags = {"size": self.size}

    # Kornia plumbing: the sensor is not a matrix; an identity keeps the container's
    # matrix bookkeeping consistent, and every data path below ignores it.
    def compute_transformation(self, input: Tensor, params: dict[str, Tensor], flags: dict) -> Tensor:
        return torch.eye(3, device=input.device, dtype=input.dtype).expand(input.shape[0], 3, 3)

    def apply_transform(self, input: Tensor, params, flags, transform=None) -> Tensor:
        return simulate(input, self.layout, self.size, self.method, **self.options)

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
        if self.mask_rule == "nearest":
            out = simulate(masks.to(torch.float64), self.layout, self.size, "point", radiance="box")
            return out.to(masks.dtype)
        labels = masks.long()
        k = max(self.num_classes, int(labels.max()) + 1 if labels.numel() else 1)
        onehot = torch.nn.functional.one_hot(labels[:, 0], k).permute(0, 3, 1, 2).to(torch.float32)
        with torch.no_grad():
            frac = simulate(onehot, self.layout, self.size, "exact")
        return frac.argmax(1, keepdim=True).to(masks.dtype)

    # keypoints and boxes -------------------------------------------------------------
    def _to_sensor_points(self, pts: Tensor, src_hw: tuple[int, int], inverse: bool) -> Tensor:
        """Pixel coordinates (centres at integers) between the source and the sensor."""
        src, dst = (src_hw, self.size) if not inverse else (self.size, src_hw)
        theta = self.layout.theta.detach().double()
        q = pixels_to_sensor(pts.to(theta), src, centered=True)
        p = self.layout.phi(q, theta) if inverse else self.layout.phi_inverse(q, theta)
        return sensor_to_pixels(p, dst, centered=True).to(pts)

    def keypoints_to_sensor(self, pts: Tensor, src_hw: tuple[int, int]) -> Tensor:
        """``(..., 2)`` source pixel ``(x, y)`` to sensor pixel coordinates via ``φ⁻¹``."""
        return self._to_sensor_points(pts, src_hw, inverse=False)

    def keypoints_from_sensor(self, pts: Tensor, src_hw: tuple[int, int]) -> Tensor:
        """Sensor pixel coordinates back to source pixel ``(x, y)`` via ``φ``."""
        return self._to_sensor_points(pts, src_hw, inverse=True)

    def _check_boxes(self) -> None:
        if not self.layout.separable:
            raise NotImplementedError(
                f"boxes cannot follow a {self.layout.family!r} layout: its pixels are curvilinear, so a "
                "box is not a box on the sensor. Use keypoints (mapped exactly through φ⁻¹) or a "
                "rectangular layout"
            )

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
        self._check_boxes()
        return self._with_data(input, self.keypoints_to_sensor(input.data, self._src_hw(params)))

    def inverse_boxes(self, input, params, flags, transform=None, **kwargs):
        self._check_boxes()
        return self._with_data(input, self.keypoints_from_sensor(input.data, self._src_hw(params)))

    def generate_parameters(self, shape: tuple[int, ...]) -> dict[str, Tensor]:
        return {"src_hw": torch.tensor([[shape[-2], shape[-1]]] * shape[0])}
