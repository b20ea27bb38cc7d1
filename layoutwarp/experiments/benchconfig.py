"""What the benchmark measures: its configuration and its layouts."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from ..coords import uniform_corners

__all__ = ["PAPER_ROWS", "BenchConfig", "bench_layouts"]


#: Rows with every tolerance and sample count; the other families get the default, 1e-3, 16 spp.
PAPER_ROWS = ("uniform", "rect", "curv", "curv ±")


def bench_layouts(theta: tuple[float, float]) -> dict[str, dict]:
    """The benchmark's layouts by row name, as [`layout_from_spec`][] dicts: the paper's
    families at θ (``"curv ±"`` with mixed-sign θ: S-shaped pixel edges), a smooth spline and an
    8x8 control grid (fixed pseudo-random parameters) and the curvilinear fovea off the centre."""
    gen = torch.Generator().manual_seed(20261122)
    logits = (torch.randn(16, generator=gen, dtype=torch.float64) * 0.5).tolist()
    ctrl = uniform_corners((8, 8)).clone()
    ctrl[1:-1, 1:-1] += (torch.rand(7, 7, 2, generator=gen, dtype=torch.float64) - 0.5) * 0.1
    return {
        "uniform": {"family": "uniform"},
        "rect": {"family": "rect", "theta": list(theta)},
        "curv": {"family": "curv", "theta": list(theta)},
        "curv ±": {"family": "curv", "theta": [theta[0], -theta[1]]},
        "spline": {"family": "spline", "theta": logits, "knots": [8, 8], "kind": "smooth"},
        "grid 8x8": {"family": "grid", "control": ctrl.tolist()},
        "fovea": {"family": "fovea", "theta": list(theta), "center": [0.3, -0.2], "learn_center": True},
    }


@dataclass(frozen=True)
class BenchConfig:
    """What [`run`][] measures.

    Attributes:
        src: source image size ``(H, W)``.
        size: sensor size ``(h, w)``.
        theta: θ of the rect and curv layouts.
        tols: tolerances of the exact curvilinear integrator (besides the data default).
        mc_samples: Monte Carlo samples per axis (``s²`` per pixel).
        repeats: timed repeats after one warm-up (median reported).
        memory: measure peak memory in spawned children (photo image only).
        photo: photo file (default: the bundled ``kodim20``; skipped if none is found).
        device: where the integrators and the ``grid_sample`` anchor run (images and layouts
            are moved there; times wait for the GPU); the OpenCV anchors and every reference
            stay on the CPU. Peak memory is host RSS in children on ``"cpu"``, the growth of
            allocated GPU memory on ``"cuda"`` (then also ``extra["train_peak_mb"]``, forward +
            backward of the learnable layout).
        only: measure only these rows of [`bench_layouts`][] (the anchors always).
        images: the images measured, of ``"photo"`` and ``"synthetic"`` (the physics, cached
            weights and training rows on the first).
        torch_references: compute the float64 references (the exact means, the finite
            differences) on the torch path, which no kernel of float64 images serves (``--quick``:
            nothing of float64 to compile; about 10x slower at the full size).
        fd_directions: check θ's gradient along this many random directions (each two finite
            differences), not along each of its ``P`` entries (``2P``), where that is fewer
            (``--quick``: 4; a grid 8x8's 98 entries took 9 of its 37 s); ``None``: every entry.
    """

    src: tuple[int, int] = (1024, 2048)
    size: tuple[int, int] = (129, 257)
    theta: tuple[float, float] = (0.35, 0.25)
    tols: tuple[float, ...] = (1e-2, 1e-3, 1e-4)
    mc_samples: tuple[int, ...] = (1, 2, 4, 8, 16)
    repeats: int = 5
    memory: bool = True
    photo: str | Path | None = None
    device: str = "cpu"
    only: tuple[str, ...] | None = None
    images: tuple[str, ...] = ("photo", "synthetic")
    torch_references: bool = False
    fd_directions: int | None = None

    @classmethod
    def quick(cls, **changes: Any) -> BenchConfig:
        """Small sizes, few repeats, the synthetic scene alone and its references on the torch
        path (``layoutwarp bench --quick``: a check that everything runs, in about 30 s once
        compiled)."""
        small = {"src": (256, 512), "size": (33, 65), "repeats": 3, "memory": False}
        cheap = {"images": ("synthetic",), "torch_references": True, "fd_directions": 4}
        return cls(**(small | cheap | changes))
