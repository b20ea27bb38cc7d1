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
import importlib.abc
import importlib.util
import sys
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

__all__ = ["__version__", *FRONT_DOOR]


#: The modules that register layoutwarp's torch operators (``torch.ops.layoutwarp.*``).
OPERATOR_MODULES = ("operators", "maps", "measurement", "resampler")


def _register_operators() -> None:
    """Import every module that registers an operator of the ``layoutwarp`` namespace."""
    for module in OPERATOR_MODULES:
        importlib.import_module(f".{module}", __name__)


def _importing() -> bool:
    """Whether a module of layoutwarp is being imported now (its operators are on their way: a
    lookup then, e.g. torch.library's own while it defines one, must not import the others)."""
    modules = [m for n, m in list(sys.modules.items()) if n.startswith(f"{__name__}.")]
    return any(getattr(getattr(m, "__spec__", None), "_initializing", False) for m in modules)


def _look_up_operators(torch: Any) -> None:
    """Make the first lookup of ``torch.ops.layoutwarp.<op>`` register layoutwarp's operators:
    a program that ``torch.export`` saved (or AOTInductor packaged) loads in a process that did
    no more than ``import layoutwarp``, while that import stays free of torch (a fast
    ``--help``)."""

    class Namespace(torch._ops._OpNamespace):
        def __getattr__(self, op_name: str) -> Any:
            try:
                return super().__getattr__(op_name)
            except AttributeError:
                if op_name.startswith("__") or _importing():
                    raise  # a dunder, or a lookup made while layoutwarp's own modules load
            _register_operators()
            return super().__getattr__(op_name)

    Namespace.__module__ = torch._ops._OpNamespace.__module__  # what its operators' names begin with

    if not isinstance(torch.ops.__dict__.get("layoutwarp"), Namespace):
        torch.ops.__dict__.pop("layoutwarp", None)
        setattr(torch.ops, "layoutwarp", Namespace("layoutwarp"))  # noqa: B010
        if "layoutwarp" not in torch.ops._dir:
            torch.ops._dir.append("layoutwarp")


class _AfterTorch(importlib.abc.MetaPathFinder):
    """Runs [`_look_up_operators`][] once torch is imported (when ``import layoutwarp`` came first)."""

    def find_spec(self, name: str, path: Any = None, target: Any = None) -> Any:
        if name != "torch":
            return None
        sys.meta_path.remove(self)
        spec = importlib.util.find_spec(name)
        if spec is None or spec.loader is None or not hasattr(spec.loader, "exec_module"):
            return spec
        run = spec.loader.exec_module

        def exec_module(module: Any) -> None:
            run(module)
            _look_up_operators(module)

        spec.loader.exec_module = exec_module  # type: ignore[method-assign]  # this load only
        return spec


if "torch" in sys.modules:
    _look_up_operators(sys.modules["torch"])
elif not any(isinstance(f, _AfterTorch) for f in sys.meta_path):
    sys.meta_path.insert(0, _AfterTorch())


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
    elif not name.startswith("_") and importlib.util.find_spec(f"{__name__}.{name}"):
        value = importlib.import_module(f".{name}", __name__)  # any submodule, on first use
    else:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(__all__)
