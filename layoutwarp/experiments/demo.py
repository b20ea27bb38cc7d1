"""The demo: the layout families over a photo, with their sensor images and numbers."""

from __future__ import annotations

import json
import time
from pathlib import Path

import cv2
import numpy as np
import torch

from ..density import edge_density, layout_from_density
from ..files import atomic_write
from ..layouts import CurvLayout, RectLayout, UniformLayout
from ..mesh import pixel_mesh
from ..sensor import simulate
from .plots import layout_figure

__all__ = ["run_demo"]


def run_demo(
    image: str | Path,
    out: str | Path,
    size: tuple[int, int],
    theta: tuple[float, float],
    tol: float | None = None,
) -> dict:
    """Simulate the uniform, rect and curv layouts, an off-centre fovea and the spline and grid
    layouts that follow the photo's own edge density on ``image``; write figures and ``demo.json``.

    Returns:
        the numbers written to ``demo.json`` (per layout: method, error bound, seconds, the
        ratio of the largest to the smallest pixel area).
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    bgr = cv2.imread(str(image), cv2.IMREAD_COLOR)
    if bgr is None:
        raise ValueError(f"cannot read image {image}")
    rgb = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
    img = torch.from_numpy(rgb).permute(2, 0, 1)[None]
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
    layout_figure(rgb / 255.0, panels, size, out / "layouts.png")
    atomic_write(out / "demo.json", json.dumps(numbers, indent=2))
    return numbers
