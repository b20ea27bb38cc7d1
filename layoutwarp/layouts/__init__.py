"""Pixel layouts: bijections φ(·, θ) of the sensor square S = [-1, 1]² onto itself, one module a
family.

Sensor pixel ``k`` of a layout is the image ``A_k = φ(U_k, θ)`` of the uniform cell ``U_k``
(Sommerhoff et al., "Differentiable Sensor Layouts for End-to-End Learning of Task-Specific
Camera Parameters", §3.2). Conventions used everywhere in this package:

* points are ``(..., 2)`` tensors ``(x, y)``: ``x`` along the image width (columns), ``y``
  along the height (rows, downwards), both in ``[-1, 1]``; ``-1`` is the outer edge of the
  first pixel and ``+1`` the outer edge of the last (``align_corners=False``);
* ``θ = (θ_x, θ_y)`` with each component in ``(-bound, bound)``; ``θ > 0`` puts more (smaller)
  pixels at the centre, ``θ < 0`` at the border. A learnable layout stores the unconstrained
  parameter ``ρ`` and derives ``θ = bound · tanh(ρ)``.

Where things are: `base` ([`Layout`][], the registry [`FAMILIES`][] with
[`register_family`][] and [`make_layout`][], [`newton_inverse`][]); `values` (θ from ρ, a
layout's dtype, a description's numbers); `centered` (the paper's two
families' movable centre); one module a family: `uniform`, `rect`, `curv`, `fovea`, `elliptic`,
`spline`, `grid`. The functional forms ([`phi_rect`][], [`phi_curv`][], their inverses,
Jacobians and θ-derivatives) take ``θ`` explicitly; the [`Layout`][] modules wrap them. Every
family registers itself when its module loads, and this package loads them all.
"""

from __future__ import annotations

from ..catalog import BUILTIN_FAMILIES
from .base import (
    FAMILIES,
    FoldoverReport,
    Layout,
    check_layout,
    layout_by_handle,
    make_layout,
    register_family,
)
from .centered import CenteredLayout
from .curv import (
    CurvLayout,
    phi_curv,
    phi_curv_dtheta,
    phi_curv_inverse,
    phi_curv_jacobian,
    phi_curv_jacobian_det,
)
from .elliptic import EllipticLayout, disk_to_square, square_to_disk
from .fovea import FoveaLayout
from .grid import GridLayout
from .inverse import newton_inverse
from .rect import RectLayout, phi_rect, phi_rect_dtheta, phi_rect_inverse, phi_rect_jacobian
from .spline import SplineLayout
from .uniform import UniformLayout
from .values import config_numbers, gradient_asked, tensor_dtype, theta_of, wants_grad

# the registry in the order the command line and the figures list the built-in families
for _name in BUILTIN_FAMILIES:
    FAMILIES[_name] = FAMILIES.pop(_name)

__all__ = [
    "FAMILIES",
    "CenteredLayout",
    "CurvLayout",
    "EllipticLayout",
    "FoldoverReport",
    "FoveaLayout",
    "GridLayout",
    "Layout",
    "RectLayout",
    "SplineLayout",
    "UniformLayout",
    "check_layout",
    "config_numbers",
    "disk_to_square",
    "gradient_asked",
    "layout_by_handle",
    "make_layout",
    "newton_inverse",
    "phi_curv",
    "phi_curv_dtheta",
    "phi_curv_inverse",
    "phi_curv_jacobian",
    "phi_curv_jacobian_det",
    "phi_rect",
    "phi_rect_dtheta",
    "phi_rect_inverse",
    "phi_rect_jacobian",
    "register_family",
    "square_to_disk",
    "tensor_dtype",
    "theta_of",
    "wants_grad",
]
