"""layoutwarp: differentiable sensor pixel layouts for PyTorch, Kornia and OpenCV.

Implements the system of Sommerhoff et al., "Differentiable Sensor Layouts for End-to-End
Learning of Task-Specific Camera Parameters": a sensor whose pixel ``k`` is the image
``φ(U_k, θ)`` of a uniform cell, simulated as the mean radiance over that pixel and
differentiable in θ and in the image.

The Kornia augmentation, dataset preprocessing and fabrication export are imported on first
use, so ``import layoutwarp`` costs little more than ``import torch``. The paper's
experiments and the benchmark live beside the library in :mod:`layoutwarp.experiments`.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from .backwarp import backwarp, backwarp_cross_entropy, backwarp_numpy, sensor_index_maps
from .coords import grid_lines, pixel_centers, pixels_to_sensor, sensor_to_pixels, uniform_corners
from .density import edge_density, layout_from_density
from .grids import GridLayout
from .integrators import (
    green_pieces,
    integrate_exact,
    integrate_montecarlo,
    integrate_point,
    integrate_separable,
)
from .layoutfile import load_layout, save_layout
from .layouts import (
    FAMILIES,
    CurvLayout,
    FoldoverReport,
    FoveaLayout,
    Layout,
    RectLayout,
    UniformLayout,
    make_layout,
    newton_inverse,
    phi_curv,
    phi_curv_inverse,
    phi_rect,
    phi_rect_inverse,
    register_family,
)
from .maps import Maps, forward_maps, inverse_maps, raster_index_map, sample_points
from .mesh import MeshTopology, PixelMesh, pixel_mesh
from .sensor import SensorLayer, SimulationPlan, plan_simulation, simulate
from .splines import SplineLayout

if TYPE_CHECKING:
    from .augment import SensorAugmentation
    from .export import ExportReport, export_layout, pixel_polygons_um
    from .preprocess import AreaResampler, area_weights, preprocess_folder

__version__ = "0.2.0"

_LAZY = {
    "SensorAugmentation": "augment",
    "ExportReport": "export",
    "export_layout": "export",
    "pixel_polygons_um": "export",
    "AreaResampler": "preprocess",
    "area_weights": "preprocess",
    "preprocess_folder": "preprocess",
}


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        value = getattr(importlib.import_module(f".{_LAZY[name]}", __name__), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(__all__)


__all__ = [
    "FAMILIES",
    "AreaResampler",
    "CurvLayout",
    "ExportReport",
    "FoldoverReport",
    "FoveaLayout",
    "GridLayout",
    "Layout",
    "Maps",
    "MeshTopology",
    "PixelMesh",
    "RectLayout",
    "SensorAugmentation",
    "SensorLayer",
    "SimulationPlan",
    "SplineLayout",
    "UniformLayout",
    "__version__",
    "area_weights",
    "backwarp",
    "backwarp_cross_entropy",
    "backwarp_numpy",
    "edge_density",
    "export_layout",
    "forward_maps",
    "green_pieces",
    "grid_lines",
    "integrate_exact",
    "integrate_montecarlo",
    "integrate_point",
    "integrate_separable",
    "inverse_maps",
    "layout_from_density",
    "load_layout",
    "make_layout",
    "newton_inverse",
    "phi_curv",
    "phi_curv_inverse",
    "phi_rect",
    "phi_rect_inverse",
    "pixel_centers",
    "pixel_mesh",
    "pixel_polygons_um",
    "pixels_to_sensor",
    "plan_simulation",
    "preprocess_folder",
    "raster_index_map",
    "register_family",
    "sample_points",
    "save_layout",
    "sensor_index_maps",
    "sensor_to_pixels",
    "simulate",
    "uniform_corners",
]
