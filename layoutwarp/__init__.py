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
from typing import Any

from .version import __version__

#: The front door: every name and the module it comes from, listed once (``__all__`` and the
#: lazy loading below read this). The modules of the core (`CORE`) load together at the first use
#: of any of their names (torch, the families, which register themselves, and the compiled
#: kernels' warm-ups); the others each on their own first use (Kornia, OpenCV file I/O, CAD
#: writers). ``import layoutwarp`` and the command line's help so cost no torch import.
FRONT_DOOR = {
    "simulate": "sensor",
    "SensorLayer": "sensor",
    "SimulationPlan": "sensor",
    "plan_simulation": "sensor",
    "SensorPhysics": "physics",
    "data_tolerance": "tolerance",
    "Layout": "layouts",
    "UniformLayout": "layouts",
    "RectLayout": "layouts",
    "CurvLayout": "layouts",
    "FoveaLayout": "layouts",
    "EllipticLayout": "layouts",
    "SplineLayout": "layouts",
    "GridLayout": "layouts",
    "FAMILIES": "layouts",
    "make_layout": "layouts",
    "register_family": "layouts",
    "layout_from_density": "density",
    "edge_density": "density",
    "pixel_mesh": "mesh",
    "PixelMesh": "mesh",
    "forward_maps": "maps",
    "inverse_maps": "maps",
    "Maps": "maps",
    "backwarp": "backwarp",
    "backwarp_cross_entropy": "backwarp",
    "backwarp_numpy": "backwarp",
    "save_layout": "layoutfile",
    "load_layout": "layoutfile",
    "SensorAugmentation": "augment",
    "AreaResampler": "resampler",
    "preprocess_folder": "preprocess",
    "export_layout": "export",
    "device_status": "kernels.mesh",
}
#: The modules loaded together at the first use of any front-door name of theirs (``warmups``
#: registers the compiled kernels' warm-ups with `layoutwarp.jit`).
CORE = (
    "backwarp",
    "density",
    "integrators",
    "layoutfile",
    "layouts",
    "maps",
    "mesh",
    "physics",
    "sensor",
    "warmups",
)
#: Submodules that ``layoutwarp.<name>`` loads on first use.
LAZY_MODULES = ("augment", "doctor", "export", "jit", "labels", "preprocess", "resampler")

__all__ = ["__version__", *FRONT_DOOR]


def __getattr__(name: str) -> Any:
    module = FRONT_DOOR.get(name)
    if module in CORE:  # the core at once: its names share their first use
        for core in CORE:
            importlib.import_module(f".{core}", __name__)
        globals().update(
            {
                n: getattr(importlib.import_module(f".{m}", __name__), n)
                for n, m in FRONT_DOOR.items()
                if m in CORE
            }
        )
        return globals()[name]
    if module is not None:
        value = getattr(importlib.import_module(f".{module}", __name__), name)
    elif name in LAZY_MODULES:
        value = importlib.import_module(f".{name}", __name__)
    else:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(__all__)
