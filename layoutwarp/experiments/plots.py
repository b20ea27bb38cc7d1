"""Figures: layouts drawn over images, sensor outputs, and the speed-vs-error plot.

Figures are built with matplotlib's object-oriented API (``matplotlib.figure.Figure``), not
pyplot, so no backend is chosen or switched: nothing here touches global state.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..coords import sensor_to_pixels
from ..layouts import FAMILIES, Layout
from ..mesh import pixel_mesh

__all__ = [
    "draw_layout",
    "family_color",
    "figure",
    "layout_figure",
    "learned_runs",
    "pareto_figure",
    "save_figure",
    "theta_figure",
    "training_figures",
]


def figure(nrows: int = 1, ncols: int = 1, *, figsize: tuple[float, float] | None = None, **kwargs: Any):
    """A matplotlib ``Figure`` and its axes (``Figure.subplots`` arguments)."""
    try:
        from matplotlib.figure import Figure
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise ImportError("plots need matplotlib: pip install 'layoutwarp[plot]'") from exc
    fig = Figure(figsize=figsize)
    return fig, fig.subplots(nrows, ncols, **kwargs)


def save_figure(fig, path: str | Path, dpi: int = 110) -> Path:
    """Lay out and save a figure (creating the folder); returns the path."""
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=dpi, bbox_inches="tight")  # a legend outside the axes stays in
    return path


def family_color(family: str) -> str:
    """A colour per layout family, from matplotlib's default cycle in registration order."""
    names = list(FAMILIES)
    return f"C{names.index(family) % 10}" if family in names else "black"


def layout_color(row: str) -> str:
    """A bench row's colour: its family's, and a colour of its own for a mixed-sign θ row
    (``"curv ±"``), which is drawn beside the family's own row."""
    family = row.split()[0]
    if "±" in row:
        return "C8" if family_color(family) != "C8" else "C9"
    return family_color(family)


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
    topo = mesh.topology
    rows = [i for i in range(h + 1) if i % step_h == 0 or i == h]
    cols = [j for j in range(w + 1) if j % step_w == 0 or j == w]
    edges = [topo.horizontal(i, j) for i in rows for j in range(w)]
    edges += [topo.vertical(i, j) for i in range(h) for j in cols]
    for e in edges:
        v = sensor_to_pixels(mesh.edge_vertices(e).detach().cpu(), (sh, sw)).numpy()
        ax.plot(v[:, 0], v[:, 1], color=color, lw=lw)
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
    n = len(panels)
    fig, axes = figure(2, n, figsize=(4 * n, 7), squeeze=False)
    for k, (title, layout, out) in enumerate(panels):
        draw_layout(axes[0, k], layout, size, image=image, max_lines=max_lines)
        axes[0, k].set_title(title, fontsize=10)
        axes[1, k].imshow(np.clip(out, 0, 1), cmap="gray" if out.ndim == 2 else None, interpolation="nearest")
        axes[1, k].set_title(f"sensor output {size[1]}x{size[0]}", fontsize=9)
        axes[1, k].set_xticks([])
        axes[1, k].set_yticks([])
    return save_figure(fig, path)


def training_figures(task, data, models: dict, records: Sequence, out: str | Path) -> list[Path]:
    """The figures of a ``train`` run: ``<task>_layouts.png`` and ``<task>_theta.png``.

    ``<task>_layouts.png``: every (family, size)'s first learned layout over the task's scene,
    its sensor image and, where the task has one (CamVid), its back-warped prediction with a
    legend. ``<task>_theta.png``: [`theta_figure`][] of the runs.

    Args:
        task: the [`Task`][layoutwarp.experiments.tasks.Task].
        data: its [`TaskData`][layoutwarp.experiments.tasks.TaskData].
        models: ``{(family, size): model}`` on the CPU.
        records: the runs' [`RunRecord`][layoutwarp.experiments.runs.RunRecord].
        out: the output folder.
    """
    out = Path(out)
    scene = task.scene(data)
    keys = list(models)
    extra = [task.prediction_image(models[k], data) for k in keys]
    rows = 3 if any(e is not None for e in extra) else 2
    fig, axes = figure(rows, len(keys), figsize=(3.4 * len(keys), 3.1 * rows + 0.4), squeeze=False)
    img = torch.from_numpy(np.ascontiguousarray(scene)).float()
    img = img[None, None] if img.ndim == 2 else img.permute(2, 0, 1)[None]
    for k, (family, size) in enumerate(keys):
        model = models[family, size]
        draw_layout(axes[0, k], model.sensor.layout, size, image=scene, color=family_color(family), lw=0.8)
        axes[0, k].set_title(f"{family} {size[1]}x{size[0]}", fontsize=9)
        with torch.no_grad():
            s = model.sensor(img)[0].permute(1, 2, 0).numpy()
        axes[1, k].imshow(
            np.clip(s[..., 0] if s.shape[-1] == 1 else s, 0, 1),
            cmap="gray" if s.shape[-1] == 1 else None,
            vmin=0,
            vmax=1,
            interpolation="nearest",
        )
        axes[1, k].set_title("sensor image", fontsize=9)
        if rows == 3 and extra[k] is not None:
            axes[2, k].imshow(extra[k], interpolation="nearest")
            axes[2, k].set_title("back-warped prediction", fontsize=9)
        for ax in axes[1:, k]:
            ax.set_xticks([])
            ax.set_yticks([])
    legend = task.legend()
    if legend:
        from matplotlib.patches import Patch

        handles = [Patch(color=np.asarray(c) / 255, label=name) for name, c in legend.items()]
        fig.legend(handles=handles, loc="lower center", ncol=min(len(handles), 6), fontsize=7, frameon=False)
    fig.suptitle(
        f"{task.name}: the first seed's layouts over a {task.report_split} image, and what they record"
    )
    paths = [save_figure(fig, out / f"{task.name}_layouts.png", dpi=100)]
    if legend:  # keep room for the legend below the panels
        fig.subplots_adjust(bottom=0.12)
        fig.savefig(paths[0], dpi=100)
    runs = [asdict(r) for r in records]
    paths.append(theta_figure(runs, out / f"{task.name}_theta.png"))
    return paths


def learned_runs(runs: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """The run records (as dicts) that learned θ: a non-empty ``theta`` and more than one point of
    ``theta_history`` (what [`theta_figure`][] draws)."""
    return [r for r in runs if r.get("theta") and len(r.get("theta_history", ())) > 1]


def theta_figure(runs: Sequence[dict[str, Any]], path: str | Path) -> Path:
    """Learning over the epochs, one line per run: the ratio of the largest to the smallest pixel
    area (meaningful for every family) and, for families with at most four parameters, θ itself.

    Args:
        runs: run records as dicts (``family``, ``size_hw`` as ``[H, W]``, ``theta``,
            ``theta_history``, ``area_ratio_history``; see
            [`RunRecord`][layoutwarp.experiments.runs.RunRecord]); runs with no learned θ or a
            single point of history are left out.
        path: the PNG to write.
    """
    learned = learned_runs(runs)
    fig, axes = figure(1, 2, figsize=(11, 3.8), squeeze=False)
    seen: set[str] = set()
    for r in learned:
        label = f"{r['family']} {r['size_hw'][1]}x{r['size_hw'][0]}"
        first = label not in seen
        seen.add(label)
        color = family_color(r["family"]) if r["family"] != "density" else "tab:gray"
        axes[0, 0].plot(r["area_ratio_history"], color=color, label=label if first else None)
        if len(r["theta"]) <= 4:
            hist = np.asarray(r["theta_history"])
            for j, ls in zip(range(hist.shape[1]), ("-", "--", ":", "-."), strict=False):
                name = ("θx", "θy", "cx", "cy")[j]
                axes[0, 1].plot(hist[:, j], ls, color=color, label=f"{label} {name}" if first else None)
    from matplotlib.ticker import FuncFormatter, MaxNLocator, NullFormatter

    axes[0, 0].set_yscale("log")
    plain = FuncFormatter(lambda v, _: f"{v:g}")  # 2, 1.5, 1: not 2×10⁰
    axes[0, 0].yaxis.set_major_formatter(plain)
    axes[0, 0].yaxis.set_minor_formatter(plain if axes[0, 0].get_ylim()[1] < 10 else NullFormatter())
    axes[0, 0].set_ylabel("largest / smallest pixel area")
    axes[0, 0].set_title("pixel-size range during training (a line per run)", fontsize=10)
    axes[0, 1].set_ylabel("θ")
    axes[0, 1].set_title("θ during training (families with ≤ 4 parameters)", fontsize=10)
    for ax in axes[0]:
        ax.set_xlabel("epoch")
        ax.xaxis.set_major_locator(MaxNLocator(integer=True))  # θ is recorded after each epoch
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=7)
    return save_figure(fig, path, dpi=100)


_METHOD_MARKERS = {"separable": "s", "exact": "D", "montecarlo": "o", "point": "^"}


def pareto_figure(result: dict, path: str | Path) -> Path:
    """Speed against error from a `layoutwarp.experiments.bench.run` result, one panel per image.

    Forward time (ms) against RMSE to the float64 exact reference, log-log, one colour per
    layout and one marker per method; Monte Carlo budgets and exact tolerances are joined by
    lines, anchors are hollow. A last panel shows the θ-gradient error against the time of
    a forward and backward pass. Errors of 0 are drawn at 1e-12.
    """
    rows = result["rows"]
    images = result.get("images") or sorted({r["image"] for r in rows})
    fig, axes = figure(1, len(images) + 1, figsize=(5.2 * (len(images) + 1), 4.6), squeeze=False)
    axes = axes[0]
    floor = 1e-12
    for ax, image in zip(axes, images, strict=False):
        for layout in dict.fromkeys(r["layout"] for r in rows):
            color = layout_color(layout)
            ls = "--" if "±" in layout else "-"
            sel = [r for r in rows if r["image"] == image and r["layout"] == layout]
            for method, marker in _METHOD_MARKERS.items():
                pts = sorted((r["forward_ms"], max(r["rmse"], floor)) for r in sel if r["method"] == method)
                if pts:
                    x, y = zip(*pts, strict=True)
                    ax.plot(x, y, marker=marker, color=color, ls=ls, lw=0.8, ms=5, label=f"{layout} {method}")
            for r in sel:
                if r["method"].startswith("anchor"):
                    ax.plot(
                        r["forward_ms"], max(r["rmse"], floor), marker="*", mfc="none", color=color, ms=10
                    )
                    if layout == "curv" or "AREA" in r["method"]:  # one label per anchor kind
                        ax.annotate(r["method"][8:], (r["forward_ms"], max(r["rmse"], floor)), fontsize=6)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("forward time (ms)")
        ax.set_ylabel("RMSE vs float64 exact")
        ax.set_title(
            f"{image}: {result['src_hw'][1]}x{result['src_hw'][0]} -> "
            f"{result['sensor_hw'][1]}x{result['sensor_hw'][0]}",
            fontsize=10,
        )
        ax.grid(True, which="both", alpha=0.3)
    ax = axes[-1]
    for r in rows:
        if r["grad_rel_err"] is None or r["image"] != images[0]:
            continue
        t = r["extra"]["forward_with_grad_ms"] + r["backward_ms"]
        ax.plot(
            t,
            max(r["grad_rel_err"], floor),
            marker=_METHOD_MARKERS.get(r["method"], "x"),
            color=layout_color(r["layout"]),
            ms=5,
        )
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("forward + backward time (ms)")
    ax.set_ylabel("relative error of dL/dθ vs finite differences")
    ax.set_title(f"θ-gradient ({images[0]})", fontsize=10)
    ax.grid(True, which="both", alpha=0.3)
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(
        handles, labels, fontsize=6, loc="upper center", bbox_to_anchor=(0.5, 0.0), ncol=6, frameon=False
    )
    return save_figure(fig, path)  # the legend below the panels: it covers no point
