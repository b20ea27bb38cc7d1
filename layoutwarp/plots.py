"""Figures: layouts drawn over images, sensor outputs, and training curves (matplotlib)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch

from .layouts import Layout
from .mesh import pixel_mesh

__all__ = ["draw_layout", "layout_figure"]


def _plt():
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise ImportError("plots need matplotlib: pip install 'layoutwarp[plot]'") from exc
    return plt


def draw_layout(
    ax,
    layout: Layout,
    size: tuple[int, int],
    *,
    image: np.ndarray | None = None,
    max_lines: int = 64,
    color: str = "tab:red",
    lw: float = 0.6,
) -> None:
    """Draw the pixel boundaries of ``layout`` (sensor ``size``) on a matplotlib axis.

    The axis spans the image in pixel units when ``image`` (HW or HWC) is given, else the
    sensor square. Only about ``max_lines`` grid lines per axis are drawn for large sensors.
    """
    h, w = size
    sh, sw = (image.shape[0], image.shape[1]) if image is not None else (2, 2)
    if image is not None:
        ax.imshow(image, cmap="gray" if image.ndim == 2 else None, extent=(0, sw, sh, 0))
    step_h, step_w = max(1, -(-h // max_lines)), max(1, -(-w // max_lines))
    with torch.no_grad():
        mesh = pixel_mesh(layout, (h, w), tol=1e-4, dtype=torch.float64)
        nh = (h + 1) * w
        for e in range(mesh.num_edges):
            if e < nh:
                i, j = divmod(e, w)
                if i % step_h and i != h:
                    continue
            else:
                i, j = divmod(e - nh, w + 1)
                if j % step_w and j != w:
                    continue
            v = mesh.edge_vertices(e).numpy()
            x, y = (v[:, 0] + 1) * sw / 2, (v[:, 1] + 1) * sh / 2
            ax.plot(x, y, color=color, lw=lw)
    ax.set_xlim(0, sw)
    ax.set_ylim(sh, 0)
    ax.set_aspect("equal")
    ax.set_xticks([])
    ax.set_yticks([])


def layout_figure(
    image: np.ndarray,
    panels: Sequence[tuple[str, Layout, np.ndarray]],
    size: tuple[int, int],
    path: str | Path,
    *,
    max_lines: int = 48,
) -> Path:
    """Save a figure: each layout over ``image`` (top row) and its sensor output (bottom row).

    Args:
        image: the source image, HW or HWC in ``[0, 1]``.
        panels: ``(title, layout, sensor_image)`` triples; sensor images HW or HWC.
        size: sensor size ``(h, w)``.
        path: output PNG path.
    """
    plt = _plt()
    n = len(panels)
    fig, axes = plt.subplots(2, n, figsize=(4 * n, 7), squeeze=False)
    for k, (title, layout, out) in enumerate(panels):
        draw_layout(axes[0, k], layout, size, image=image, max_lines=max_lines)
        axes[0, k].set_title(title, fontsize=10)
        axes[1, k].imshow(np.clip(out, 0, 1), cmap="gray" if out.ndim == 2 else None, interpolation="nearest")
        axes[1, k].set_title(f"sensor output {size[1]}x{size[0]}", fontsize=9)
        axes[1, k].set_xticks([])
        axes[1, k].set_yticks([])
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
