"""layoutwarp: differentiable sensor pixel layouts for PyTorch, Kornia and OpenCV.

Implements the system of Sommerhoff et al., "Differentiable Sensor Layouts for End-to-End
Learning of Task-Specific Camera Parameters": a sensor whose pixel ``k`` is the image
``φ(U_k, θ)`` of a uniform cell, simulated as the mean radiance over that pixel and
differentiable in θ and in the image.
"""

from .augment import SensorAugmentation
from .backwarp import backwarp, backwarp_cross_entropy, backwarp_numpy, sensor_index_maps
from .export import ExportReport, export_layout, pixel_polygons_um
from .integrators import (
    integrate_exact,
    integrate_montecarlo,
    integrate_point,
    integrate_separable,
)
from .io import load_layout, save_layout
from .layouts import (
    CurvLayout,
    FoldoverReport,
    Layout,
    RectLayout,
    UniformLayout,
    make_layout,
    newton_inverse,
    phi_curv,
    phi_curv_inverse,
    phi_rect,
    phi_rect_inverse,
)
from .mesh import (
    Maps,
    PixelMesh,
    forward_maps,
    inverse_maps,
    pixel_centers,
    pixel_mesh,
    sample_points,
    uniform_corners,
)
from .preprocess import AreaResampler, area_weights, preprocess_folder
from .sensor import SensorLayer, SimulationPlan, plan_simulation, simulate

__version__ = "0.1.0"

__all__ = [
    "AreaResampler",
    "CurvLayout",
    "ExportReport",
    "FoldoverReport",
    "Layout",
    "Maps",
    "PixelMesh",
    "RectLayout",
    "SensorAugmentation",
    "SensorLayer",
    "SimulationPlan",
    "UniformLayout",
    "__version__",
    "area_weights",
    "backwarp",
    "backwarp_cross_entropy",
    "backwarp_numpy",
    "export_layout",
    "forward_maps",
    "integrate_exact",
    "integrate_montecarlo",
    "integrate_point",
    "integrate_separable",
    "inverse_maps",
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
    "plan_simulation",
    "preprocess_folder",
    "sample_points",
    "save_layout",
    "sensor_index_maps",
    "simulate",
    "uniform_corners",
]
