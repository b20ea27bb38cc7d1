"""The demo: the layout families over a photo, with their sensor images and numbers."""

from __future__ import annotations

import json
import time
from pathlib import Path

import cv2
import numpy as np
import torch

from ..checks import warn_if_stretched
from ..density import edge_density, layout_from_density
from ..files import atomic_write
from ..layouts import CurvLayout, RectLayout, UniformLayout
from ..mesh import pixel_mesh
from ..preprocess import read_image
from ..sensor import simulate
from .plots import layout_figure

__all__ = ["demo_outputs", "photo_tensor", "run_demo"]


def photo_tensor(arr: np.ndarray) -> torch.Tensor:
    """An image as OpenCV decodes it (gray, BGR or BGRA; 8/16-bit or float) as ``(1, 3, H, W)``
    RGB: uint8 as it is, other depths as float32 in [0, 1] (float images as they are)."""
    if arr.dtype != np.uint8:  # other depths to float32 in [0, 1] first (cvtColor takes few)
        scale = np.iinfo(arr.dtype).max if np.issubdtype(arr.dtype, np.integer) else 1.0
        arr = arr.astype(np.float32) / scale
    if arr.ndim == 2:
        arr = cv2.cvtColor(arr, cv2.COLOR_GRAY2BGR)
    rgb = cv2.cvtColor(np.ascontiguousarray(arr[..., :3]), cv2.COLOR_BGR2RGB)
    return torch.from_numpy(np.ascontiguousarray(rgb)).permute(2, 0, 1)[None]


def demo_outputs(out: str | Path) -> list[Path]:
    """The files [`run_demo`][] writes into ``out``: the figure, the numbers and one sensor image a
    layout."""
    out = Path(out)
    names = ("uniform", "rect", "curv", "fovea", "spline", "grid")
    return [out / "layouts.png", out / "demo.json", *(out / f"sensor_{n}.png" for n in names)]


def run_demo(
    image: str | Path,
    out: str | Path,
    size: tuple[int, int],
    theta: tuple[float, float],
    tol: float | None = None,
) -> dict:
    """Simulate the uniform, rect and curv layouts, an off-centre fovea and the spline and grid
    layouts that follow the photo's own edge density on ``image``; write figures and ``demo.json``
    ([`demo_outputs`][]).

    Returns:
        the numbers written to ``demo.json`` (per layout: method, error bound, seconds, the
        ratio of the largest to the smallest pixel area).
    """
    img = photo_tensor(read_image(Path(image)))  # refuses a file cut short, in our words
    warn_if_stretched(size, tuple(img.shape[-2:]))
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    tx, ty = theta
    layouts = {
        "uniform": UniformLayout(),
        f"rect θ=({tx:g}, {ty:g})": RectLayout((tx, ty)),
        f"curv θ=({tx:g}, {ty:g})": CurvLayout((tx, ty)),
        "fovea at (0.3, -0.2)": CurvLayout((tx, ty), center=(0.3, -0.2)),
    }
    density = edge_density(img.float(), size)  # where this photo has detail, at sensor resolution
    layouts["spline from edges"] = layout_from_density(density, size, "spline", dtype=torch.float32)
    layouts["grid from edges"] = layout_from_density(density, size, "grid", dtype=torch.float32)
    panels, numbers = [], {"image": str(image), "size_wxh": f"{size[1]}x{size[0]}", "layouts": {}}
    for name, layout in layouts.items():
        t0 = time.perf_counter()
        sim, plan = simulate(img, layout, size, "exact", tol=tol, return_plan=True)
        elapsed = time.perf_counter() - t0
        arr = sim[0].permute(1, 2, 0).numpy()
        areas = pixel_mesh(layout, size, tol=plan.details.get("tol")).areas()
        panels.append((name, layout, arr))
        numbers["layouts"][name] = {
            "family": layout.family,
            "theta": [float(v) for v in layout.theta],
            "method": plan.method,
            "error_bound": plan.error_bound,
            "seconds": round(elapsed, 4),
            "pixel_area_ratio_max_over_min": float(areas.max() / areas.min()),
        }
        cv2.imwrite(
            str(out / f"sensor_{name.split()[0]}.png"),
            cv2.cvtColor((np.clip(arr, 0, 1) * 255).round().astype(np.uint8), cv2.COLOR_RGB2BGR),
        )
    layout_figure(
        img[0].permute(1, 2, 0).float().numpy() / (255.0 if img.dtype == torch.uint8 else 1.0),
        panels,
        size,
        out / "layouts.png",
    )
    atomic_write(out / "demo.json", json.dumps(numbers, indent=2))
    return numbers
