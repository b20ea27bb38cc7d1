"""Draw the documentation's gallery (docs/gallery.md) from the bundled CamVid street scene.

Run from anywhere:  python examples/gallery.py [--out DIR]

Writes into DIR (default examples/figures/gallery/, created if missing; nothing else is
written except a temporary folder for the mask):

* ``families.png``: every layout family's pixel grid over the scene, the 24x32 sensor image
  it records and that image back-warped to the scene's 360x480 grid;
* ``fabrication_mask.png``: the PNG fabrication mask ``lw.export_layout`` writes for one
  layout, whole and a zoomed crop;
* ``backwarp.png``: the scene's CamVid labels moved to the sensor and back-warped (nearest);
* ``landscape.png``: the committed MNIST θ-landscape (``examples/study/landscape-mnist-curv/``,
  from ``layoutwarp landscape``) drawn again.
"""

from __future__ import annotations

import argparse
import json
import re
import tempfile
import time
from pathlib import Path
from typing import Any

import cv2
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
import torch
from matplotlib.collections import PolyCollection

import layoutwarp as lw
from layoutwarp.coords import uniform_corners
from layoutwarp.labels import labels_to_sensor
from layoutwarp.layouts import FAMILIES, GridLayout, SplineLayout
from layoutwarp.mesh import pixel_mesh

ROOT = Path(__file__).resolve().parents[1]
CAMVID = ROOT / "data_samples" / "camvid"
SCENE = "0016E5_07959.png"
SIZE = (24, 32)  # sensor (h, w): the 4:3 of the 480x360 scene, so sensor pixels start square
EXTENT = (-1, 1, 1, -1)  # sensor coordinates, y down
THETA = (0.5, 0.3)  # rect, curv, elliptic, and the layout of the mask and the labels
MASK_UM, PX_PER_UM = (2400.0, 3200.0), 0.4  # the mask's sensor (height, width) and raster
DPI = 150


def layouts() -> dict[str, lw.Layout]:
    """One layout of every family, by its title: deformed visibly, far from folding."""
    ctrl = uniform_corners((4, 4)).clone()  # grid: a swirl of the 3x3 interior control points
    inner = ctrl[1:-1, 1:-1]
    angle = 0.9 * (1 - inner.norm(dim=-1))
    cos, sin = angle.cos(), angle.sin()
    x, y = inner.unbind(-1)
    ctrl[1:-1, 1:-1] = torch.stack([cos * x - sin * y, sin * x + cos * y], -1)
    out = {
        "uniform": lw.make_layout("uniform"),
        f"rect θ={THETA}": lw.make_layout("rect", THETA),
        f"curv θ={THETA}": lw.make_layout("curv", THETA),
        "fovea θ=(0.6, 0.6) at (0.2, -0.1)": lw.make_layout("fovea", (0.6, 0.6), center=(0.2, -0.1)),
        f"elliptic θ={THETA}": lw.make_layout("elliptic", THETA),
        "spline, 5 x- and 4 y-pieces": SplineLayout.from_knots(
            [-1, -0.5, -0.2, 0, 0.2, 1], [-1, -0.6, 0.2, 0.5, 1]
        ),
        "grid, 4x4 control cells": GridLayout(ctrl),
    }
    assert [v.family for v in out.values()] == list(FAMILIES), f"not every family of {list(FAMILIES)}"
    return out


def show(ax: plt.Axes, img: np.ndarray | torch.Tensor, title: str, **kw: Any) -> None:
    if isinstance(img, torch.Tensor):
        img = img[0].permute(1, 2, 0).clamp(0, 1).numpy()
    ax.imshow(img, extent=EXTENT, interpolation="nearest", **kw)
    ax.set_aspect(0.75)  # the scene's height over width, in sensor coordinates
    ax.set_title(title, fontsize=9)
    ax.set_xticks([])
    ax.set_yticks([])


def draw_grid(ax: plt.Axes, layout: lw.Layout) -> None:
    polys = pixel_mesh(layout, SIZE, tol=1e-3, dtype=torch.float64).polygons()
    ax.add_collection(PolyCollection(polys, facecolors="none", edgecolors="red", linewidths=0.35))


def families(rgb: np.ndarray, image: torch.Tensor, out: Path) -> None:
    all_layouts = layouts()
    fig, axes = plt.subplots(len(all_layouts), 3, figsize=(9, 2.45 * len(all_layouts)))
    for row, (title, layout) in zip(axes, all_layouts.items(), strict=True):
        with torch.no_grad():
            sensor = lw.simulate(image, layout, SIZE)
            back = lw.backwarp(sensor, layout, rgb.shape[:2])
        show(row[0], rgb, f"{title}: pixels", alpha=0.7)
        draw_grid(row[0], layout)
        show(row[1], sensor, f"sensor image {SIZE[0]}x{SIZE[1]}")
        show(row[2], back, f"back-warped to {rgb.shape[0]}x{rgb.shape[1]}")
    fig.suptitle("The layout families on a CamVid scene", fontsize=12)
    fig.tight_layout(rect=(0, 0, 1, 0.99))
    fig.savefig(out / "families.png", dpi=100)  # 21 photo panels: 150 dpi would weigh 2 MB
    plt.close(fig)


def fabrication_mask(out: Path) -> None:
    layout = lw.make_layout("curv", THETA)
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "mask.png"
        report = lw.export_layout(
            layout, SIZE, path, MASK_UM, px_per_um=PX_PER_UM, line_width=2, progress=False
        )
        mask = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    fig, (whole, crop) = plt.subplots(1, 2, figsize=(10, 4.2))
    h, w = mask.shape
    whole.imshow(mask, cmap="gray", interpolation="antialiased")
    whole.add_patch(plt.Rectangle((w // 2 - 120, h // 2 - 90), 240, 180, fill=False, ec="red", lw=1.5))
    whole.set_title(f"whole mask, {w}x{h} raster px ({PX_PER_UM:g} px/µm)", fontsize=9)
    crop.imshow(
        mask[h // 2 - 90 : h // 2 + 90, w // 2 - 120 : w // 2 + 120], cmap="gray", interpolation="nearest"
    )
    crop.set_title("the red box, enlarged", fontsize=9)
    for ax in (whole, crop):
        ax.set_xticks([])
        ax.set_yticks([])
    fig.suptitle(
        f"Fabrication mask (PNG) of curv θ={THETA}, {SIZE[0]}x{SIZE[1]} pixels on "
        f"{MASK_UM[1]:g}x{MASK_UM[0]:g} µm: pitch {report.min_pitch_um:.0f}–{report.max_pitch_um:.0f} µm",
        fontsize=11,
    )
    fig.tight_layout()
    fig.savefig(out / "fabrication_mask.png", dpi=DPI)
    plt.close(fig)


def backwarp(rgb: np.ndarray, out: Path) -> None:
    labels = cv2.imread(str(CAMVID / "valannot" / SCENE), cv2.IMREAD_GRAYSCALE)
    rows = re.findall(r"^(\d+) (\w+) +\[(\d+),(\d+),(\d+)\]", (CAMVID / "CLASSES.txt").read_text(), re.M)
    names = [r[1] for r in rows]
    palette = np.array([r[2:] for r in rows], dtype=np.uint8)  # class index -> RGB
    layout = lw.make_layout("curv", THETA)
    sensor = labels_to_sensor(torch.from_numpy(labels).long(), layout, SIZE, rule="majority")
    back = lw.backwarp(sensor[None], layout, labels.shape, mode="nearest")[0].numpy()
    known = labels != names.index("Unlabelled")
    agree = float((back == labels)[known].mean())
    fig, axes = plt.subplots(2, 2, figsize=(9, 7.2))
    show(axes[0, 0], rgb, f"CamVid scene, curv θ={THETA} pixels", alpha=0.7)
    draw_grid(axes[0, 0], layout)
    show(axes[0, 1], palette[labels], "label map, 360x480 (ground truth)")
    show(axes[1, 0], palette[sensor.numpy()], f"labels on the {SIZE[0]}x{SIZE[1]} sensor (majority)")
    show(axes[1, 1], palette[back], f"back-warped (nearest): {agree:.1%} of labelled pixels agree")
    handles = [plt.Rectangle((0, 0), 1, 1, fc=palette[k] / 255) for k in np.unique(labels)]
    fig.legend(handles, [names[k] for k in np.unique(labels)], loc="lower center", ncol=6, fontsize=8)
    fig.suptitle("Dense prediction: labels to the sensor and back", fontsize=12)
    fig.tight_layout(rect=(0, 0.07, 1, 1))
    fig.savefig(out / "backwarp.png", dpi=DPI)
    plt.close(fig)


def landscape(out: Path) -> None:
    """The committed MNIST 4x4 curv θ-landscape, drawn as ``layoutwarp landscape`` draws it."""
    from layoutwarp.experiments.landscape import landscape_figure

    summary = json.loads(
        (ROOT / "examples" / "study" / "landscape-mnist-curv" / "landscape.json").read_text()
    )
    landscape_figure(summary, out / "landscape.png")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=ROOT / "examples" / "figures" / "gallery")
    out = parser.parse_args().out
    out.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    rgb = cv2.cvtColor(cv2.imread(str(CAMVID / "val" / SCENE)), cv2.COLOR_BGR2RGB)
    image = torch.from_numpy(rgb).permute(2, 0, 1)[None].float() / 255  # (1, 3, 360, 480) in [0, 1]
    families(rgb, image, out)
    fabrication_mask(out)
    backwarp(rgb, out)
    landscape(out)
    print(
        f"wrote families.png, fabrication_mask.png, backwarp.png, landscape.png to {out} "
        f"in {time.perf_counter() - start:.1f} s"
    )


if __name__ == "__main__":
    main()
