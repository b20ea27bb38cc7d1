"""layoutwarp: differentiable sensor pixel layouts for PyTorch, Kornia and OpenCV.

Implements the system of Sommerhoff et al., "Differentiable Sensor Layouts for End-to-End
Learning of Task-Specific Camera Parameters": a sensor whose pixel ``k`` is the image
``φ(U_k, θ)`` of a uniform cell, simulated as the mean radiance over that pixel and
differentiable in θ and in the image.

The top level is the front door: the sensor ([`simulate`][], [`SensorLayer`][]), the
layout families, maps and back-warping, layout files (imported together at the first use of
any of them), and, each on its own first use, the Kornia augmentation, dataset preprocessing and
fabrication export; ``import layoutwarp`` alone imports nothing heavy. The building blocks
stay in their modules:
[`layoutwarp.integrators`][integrators] (the integrators one by one), [`layoutwarp.layouts`][layouts] (the
paper's φ in functional form), [`layoutwarp.coords`][coords] (the coordinate convention),
[`layoutwarp.mesh`][mesh], [`layoutwarp.maps`][maps], [`layoutwarp.labels`][labels],
[`layoutwarp.resampler`][resampler], `layoutwarp.export`. The paper's experiments and the
benchmark live beside the library in `layoutwarp.experiments`.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from .version import __version__

if TYPE_CHECKING:
    from .augment import SensorAugmentation
    from .backwarp import backwarp, backwarp_cross_entropy, backwarp_numpy
    from .density import edge_density, layout_from_density
    from .export import export_layout
    from .grids import GridLayout
    from .integrators import data_tolerance
    from .layoutfile import load_layout, save_layout
    from .layouts import (
        FAMILIES,
        CurvLayout,
        EllipticLayout,
        FoveaLayout,
        Layout,
        RectLayout,
        UniformLayout,
        make_layout,
        register_family,
    )
    from .maps import Maps, forward_maps, inverse_maps
    from .mesh import PixelMesh, pixel_mesh
    from .physics import SensorPhysics
    from .preprocess import preprocess_folder
    from .resampler import AreaResampler
    from .sensor import SensorLayer, SimulationPlan, plan_simulation, simulate
    from .splines import SplineLayout

#: The front door's core: loaded together at the first use of any of its names (torch, the
#: families, which register themselves, and the compiled kernels' warm-ups), so that
#: ``import layoutwarp`` and the command line's help cost no torch import.
_CORE = {
    "backwarp": ("backwarp", "backwarp_cross_entropy", "backwarp_numpy"),
    "density": ("edge_density", "layout_from_density"),
    "grids": ("GridLayout",),
    "integrators": ("data_tolerance",),
    "layoutfile": ("load_layout", "save_layout"),
    "layouts": (
        "FAMILIES",
        "CurvLayout",
        "EllipticLayout",
        "FoveaLayout",
        "Layout",
        "RectLayout",
        "UniformLayout",
        "make_layout",
        "register_family",
    ),
    "maps": ("Maps", "forward_maps", "inverse_maps"),
    "mesh": ("PixelMesh", "pixel_mesh"),
    "physics": ("SensorPhysics",),
    "sensor": ("SensorLayer", "SimulationPlan", "plan_simulation", "simulate"),
    "splines": ("SplineLayout",),
    "warmups": (),  # registers the compiled kernels' warm-ups with layoutwarp.jit
}
#: Front-door names whose modules load on their own first use (Kornia, OpenCV file I/O, CAD writers).
_LAZY = {
    "SensorAugmentation": "augment",
    "export_layout": "export",
    "AreaResampler": "resampler",
    "preprocess_folder": "preprocess",
}
#: Submodules that ``layoutwarp.<name>`` loads on first use.
_LAZY_MODULES = ("augment", "doctor", "export", "jit", "labels", "preprocess", "resampler")


def _load_core() -> None:
    """Import the front door's core ([`_CORE`][]); what the first use of one of its names does."""
    for module, names in _CORE.items():
        mod = importlib.import_module(f".{module}", __name__)
        globals().update({name: getattr(mod, name) for name in names})


def __getattr__(name: str) -> Any:
    if any(name in names for names in _CORE.values()):
        _load_core()
        return globals()[name]
    if name in _LAZY:
        value = getattr(importlib.import_module(f".{_LAZY[name]}", __name__), name)
    elif name in _LAZY_MODULES:
        value = importlib.import_module(f".{name}", __name__)
    else:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(__all__)


__all__ = [
    "FAMILIES",
    "AreaResampler",
    "CurvLayout",
    "EllipticLayout",
    "FoveaLayout",
    "GridLayout",
    "Layout",
    "Maps",
    "PixelMesh",
    "RectLayout",
    "SensorAugmentation",
    "SensorLayer",
    "SensorPhysics",
    "SimulationPlan",
    "SplineLayout",
    "UniformLayout",
    "__version__",
    "backwarp",
    "backwarp_cross_entropy",
    "backwarp_numpy",
    "data_tolerance",
    "edge_density",
    "export_layout",
    "forward_maps",
    "inverse_maps",
    "layout_from_density",
    "load_layout",
    "make_layout",
    "pixel_mesh",
    "plan_simulation",
    "preprocess_folder",
    "register_family",
    "save_layout",
    "simulate",
]
