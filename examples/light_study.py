"""What a learned layout is worth under light: a pixel-budget study at several light levels.

Every layout gets the same sensor extent (1 µm a source pixel: MNIST 28 x 28 µm, faces
200 x 200 µm) and exposure, so the total light is the same and only its division between pixels
differs. For each light level the task's study (its uniform curve, and the two best families of
its noise-free study, grid and curv, at the study's learned sizes) trains for 3 seeds with shot
and read noise (1 e⁻); the noise-free level is the shipped study (``examples/study/TASK``, the
same plan and tolerance). Then the saving factor of every learned layout is read through the
uniform curve of its own light level.

Run from the repository root (resumable: a finished run is never repeated)::

    LAYOUTWARP_DATA=/path/to/data python examples/light_study.py --out results/light-mnist \\
        --ship examples/study/light-mnist
    LAYOUTWARP_DATA=/path/to/data python examples/light_study.py --task faces --levels 0.035 \\
        --out results/light-faces --ship examples/study/light-faces

``--levels`` are photons per µm² at full scale. MNIST: its mean image value is 0.1307 and a
uniform 4x4 pixel covers 49 µm², so 3.12 is about 20 photons per uniform 4x4 pixel at the mean
value (shot-noise-limited) and 31.2 about 200 (the default levels). Faces: mean value 0.514, a
uniform 6x6 pixel covers 1111 µm², so 0.035 is about 20 photons per uniform 6x6 pixel.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

import layoutwarp as lw
from layoutwarp.cli import main as layoutwarp
from layoutwarp.experiments.plots import family_color, figure, save_figure
from layoutwarp.files import atomic_write

ROOT = Path(__file__).resolve().parents[1]
FAMILIES = ("grid", "curv")


@dataclass(frozen=True)
class Light:
    """A task's light scale: its mean image value, the uniform pixel that names a level, that
    pixel's area at 1 µm a source pixel, the learned sizes to plot and the default levels."""

    mean_value: float
    pixel: str
    pixel_um2: float
    sizes: tuple[tuple[int, int], ...]
    levels: str


TASKS = {
    "mnist": Light(0.1307, "4x4", 49.0, ((3, 3), (4, 4)), "3.12,31.2"),
    "faces": Light(0.514, "6x6", (200 / 6) ** 2, ((6, 6), (8, 8)), "0.035"),
}


def photons_per_pixel(level: float, light: Light) -> float:
    """Mean photons per uniform reference pixel at the task's mean image value."""
    return level * light.mean_value * light.pixel_um2


def area_ratio(run: dict) -> float | None:
    """Largest over smallest pixel area at the end of a run (from its record)."""
    history = run.get("area_ratio_history")
    return history[-1] if history else None


def layout_area_ratio(path: Path) -> float:
    """Largest over smallest pixel area of a layout file's layout at its sensor size."""
    layout, info = lw.load_layout(path, dtype=torch.float64)
    areas = lw.pixel_mesh(layout, tuple(info["size_hw"]), tol=1e-5).areas()
    return float(areas.max() / areas.min())


def collect(out: Path, levels: list[float], task: str) -> dict:
    """The savings of every level's study (and the shipped noise-free one), and how the learned
    layouts' pixel-size range changes."""
    light = TASKS[task]
    studies = {f"{photons_per_pixel(p, light):.0f}": out / f"p{p:g}" for p in levels}
    studies["noise-free"] = ROOT / "examples" / "study" / task
    result: dict = {
        "task": task,
        "pixel": light.pixel,
        "levels": {},
        "photons_per_um2": {f"{photons_per_pixel(p, light):.0f}": p for p in levels},
    }
    for label, folder in studies.items():
        if not (folder / "study.json").exists():
            continue
        summary = json.loads((folder / "study.json").read_text())
        rows = [r for r in summary["rows"] if r["family"] in FAMILIES and "saving" in r]
        entry = {"runs": summary["runs"], "planned": summary.get("planned"), "rows": []}
        for r in rows:
            size = r["size_hw"]
            name = f"{r['family']}_{size[1]}x{size[0]}_seed*.json"
            ratios = [area_ratio(json.loads(p.read_text())) for p in sorted((folder / "runs").glob(name))]
            if not ratios:  # a shipped study keeps the learned layouts, not the run records
                ratios = [layout_area_ratio(p) for p in sorted((folder / "layouts").glob(name))]
            ratios = [v for v in ratios if v is not None]
            entry["rows"].append(
                {
                    "family": r["family"],
                    "size_hw": size,
                    "accuracy": [r["mean"], r["std"]],
                    "saving": r["saving"],
                    "saving_interval": r["saving_interval"],
                    "bound": r["bound"],
                    "area_ratio": float(np.mean(ratios)) if ratios else None,
                }
            )
        uniform = {
            f"{r['size_hw'][1]}x{r['size_hw'][0]}": [r["mean"], r["std"]]
            for r in summary["rows"]
            if r["family"] == "uniform"
        }
        entry["uniform"] = uniform
        result["levels"][label] = entry
    return result


def table(result: dict) -> str:
    lines = [
        f"| photons per uniform {result['pixel']} pixel | family | sensor | test accuracy (%) | pixel saving "
        "| largest/smallest pixel |",
        "|---|---|---|---|---|---|",
    ]
    for label, entry in result["levels"].items():
        for r in entry["rows"]:
            lo, hi = r["saving_interval"]
            mark = {"=": "", "<": "< ", ">": "> "}[r["bound"]]
            ratio = "—" if r["area_ratio"] is None else f"{r['area_ratio']:.2f}"
            h, w = r["size_hw"]
            acc = f"{r['accuracy'][0]:.2f} ± {r['accuracy'][1]:.2f}"
            saving = f"{mark}{r['saving']:.2f}x [{lo:.2f}, {hi:.2f}]"
            lines.append(f"| {label} | {r['family']} | {w}x{h} | {acc} | {saving} | {ratio} |")
    return "\n".join(lines) + "\n"


def plot(result: dict, path: Path) -> Path:
    light = TASKS[result["task"]]
    fig, ax = figure(figsize=(6.4, 4.2))
    labels = list(result["levels"])
    xs = {label: k for k, label in enumerate(labels)}
    for fam in FAMILIES:
        for size, ls in zip(light.sizes, ("--", "-"), strict=True):
            pts = [
                (xs[label], r["saving"], *r["saving_interval"])
                for label, e in result["levels"].items()
                for r in e["rows"]
                if r["family"] == fam and tuple(r["size_hw"]) == size
            ]
            if not pts:
                continue
            x, y, lo, hi = (np.array(v) for v in zip(*pts, strict=True))
            ax.errorbar(
                x,
                y,
                [y - lo, hi - y],
                color=family_color(fam),
                ls=ls,
                marker="o",
                capsize=3,
                label=f"{fam} {size[1]}x{size[0]}",
            )
    ax.axhline(1, color="black", lw=0.8)
    ax.set_xticks(range(len(labels)), labels)
    name = {"mnist": "MNIST", "faces": "faces"}[result["task"]]
    ax.set_xlabel(f"mean photons per uniform {light.pixel} pixel (at the images' mean value)")
    ax.set_ylabel("pixel saving against uniform")
    ax.set_title(f"{name}: what learned layouts save as light falls (3 seeds)")
    ax.legend(fontsize=8)
    return save_figure(fig, path)


def run(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--task", choices=sorted(TASKS), default="mnist", help="the study's task (default mnist)")
    p.add_argument("--levels", help="photons per µm² at full scale, comma-separated (default: the task's)")
    p.add_argument("--out", help="study folders, one per level (default: results/light-TASK)")
    p.add_argument("--ship", help="copy the summary, the figure and each level's study to this folder")
    p.add_argument("--summarise-only", action="store_true", help="train nothing: summarise what is there")
    args = p.parse_args(argv)
    light = TASKS[args.task]
    levels = [float(v) for v in (args.levels or light.levels).split(",")]
    out = Path(args.out or f"results/light-{args.task}")
    for level in levels if not args.summarise_only else ():
        study = ["study", args.task, "--family", "grid", "--family", "curv", "--no-progress"]
        study += ["--device", "cpu"]
        study += ["--photons-per-um2", f"{level:g}", "--read-noise-e", "1", "--out", str(out / f"p{level:g}")]
        if layoutwarp(study) != 0:
            return 1
    result = collect(out, levels, args.task)
    figure_name = f"light_{args.task}.png"
    atomic_write(out / "light.json", json.dumps(result, indent=2))
    atomic_write(out / "light.md", table(result))
    plot(result, out / figure_name)
    print(table(result), end="")
    if args.ship:
        dest = Path(args.ship)
        for name in ("light.json", "light.md", figure_name):
            atomic_write(dest / name, (out / name).read_bytes())
        for level in levels:  # each level's summary and its run records
            folder = out / f"p{level:g}"
            files = [folder / n for n in ("study.json", "study.md", f"study_{args.task}.png")]
            for src in [*files, *sorted((folder / "runs").glob("*.json"))]:
                if src.exists():
                    atomic_write(dest / src.relative_to(out), src.read_bytes())
        print(f"shipped to {dest}")
    return 0


if __name__ == "__main__":
    sys.exit(run())
