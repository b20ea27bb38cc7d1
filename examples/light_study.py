"""What a learned layout is worth under light: the MNIST pixel-budget study at several light levels.

Every layout gets the same sensor extent (28 x 28 µm: 1 µm a source pixel) and exposure, so the
total light is the same and only its division between pixels differs. For each light level the
uniform curve (2x2 to 7x7) and the two best families of the noise-free study (grid and curv, at
3x3 and 4x4) train for 3 seeds with shot and read noise (1 e⁻); the noise-free level is the
shipped study (``examples/study/mnist``, the same plan and tolerance). Then the saving factor of
every learned layout is read through the uniform curve of its own light level.

Run from the repository root (resumable: a finished run is never repeated)::

    LAYOUTWARP_DATA=/path/to/data python examples/light_study.py --out results/light-mnist \\
        --ship examples/study/light-mnist

``--levels`` are photons per µm² at full scale; MNIST's mean image value is 0.1307 and a
uniform 4x4 pixel covers 49 µm², so 3.12 is about 20 photons per uniform 4x4 pixel at the mean
value (shot-noise-limited) and 31.2 about 200.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch

import layoutwarp as lw
from layoutwarp.cli import main as layoutwarp
from layoutwarp.experiments.plots import family_color, figure, save_figure
from layoutwarp.files import atomic_write

ROOT = Path(__file__).resolve().parents[1]
MEAN_VALUE, PIXEL_4X4_UM2 = 0.1307, 49.0
FAMILIES = ("grid", "curv")


def photons_per_pixel(level: float) -> float:
    """Mean photons per uniform 4x4 pixel at MNIST's mean image value."""
    return level * MEAN_VALUE * PIXEL_4X4_UM2


def area_ratio(run: dict) -> float | None:
    """Largest over smallest pixel area at the end of a run (from its record)."""
    history = run.get("area_ratio_history")
    return history[-1] if history else None


def layout_area_ratio(path: Path) -> float:
    """Largest over smallest pixel area of a layout file's layout at its sensor size."""
    layout, info = lw.load_layout(path, dtype=torch.float64)
    areas = lw.pixel_mesh(layout, tuple(info["size_hw"]), tol=1e-5).areas()
    return float(areas.max() / areas.min())


def collect(out: Path, levels: list[float]) -> dict:
    """The savings of every level's study (and the shipped noise-free one), and how the learned
    layouts' pixel-size range changes."""
    studies = {f"{photons_per_pixel(p):.0f}": out / f"p{p:g}" for p in levels}
    studies["noise-free"] = ROOT / "examples" / "study" / "mnist"
    result: dict = {"levels": {}, "photons_per_um2": {f"{photons_per_pixel(p):.0f}": p for p in levels}}
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
        "| photons per uniform 4x4 pixel | family | sensor | test accuracy (%) | pixel saving "
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
    fig, ax = figure(figsize=(6.4, 4.2))
    labels = list(result["levels"])
    xs = {label: k for k, label in enumerate(labels)}
    for fam in FAMILIES:
        for size, ls in (([3, 3], "--"), ([4, 4], "-")):
            pts = [
                (xs[label], r["saving"], *r["saving_interval"])
                for label, e in result["levels"].items()
                for r in e["rows"]
                if r["family"] == fam and r["size_hw"] == size
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
    ax.set_xlabel("mean photons per uniform 4x4 pixel (MNIST's mean value)")
    ax.set_ylabel("pixel saving against uniform")
    ax.set_title("MNIST: what learned layouts save as light falls (3 seeds)")
    ax.legend(fontsize=8)
    return save_figure(fig, path)


def run(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--levels", default="3.12,31.2", help="photons per µm² at full scale, comma-separated")
    p.add_argument("--out", default="results/light-mnist", help="study folders (one per level)")
    p.add_argument("--ship", help="copy the summary, the figure and each level's study to this folder")
    p.add_argument("--summarise-only", action="store_true", help="train nothing: summarise what is there")
    args = p.parse_args(argv)
    levels = [float(v) for v in args.levels.split(",")]
    out = Path(args.out)
    for level in levels if not args.summarise_only else ():
        study = ["study", "mnist", "--family", "grid", "--family", "curv", "--no-progress", "--device", "cpu"]
        study += ["--photons-per-um2", f"{level:g}", "--read-noise-e", "1", "--out", str(out / f"p{level:g}")]
        if layoutwarp(study) != 0:
            return 1
    result = collect(out, levels)
    atomic_write(out / "light.json", json.dumps(result, indent=2))
    atomic_write(out / "light.md", table(result))
    plot(result, out / "light_mnist.png")
    print(table(result), end="")
    if args.ship:
        dest = Path(args.ship)
        for name in ("light.json", "light.md", "light_mnist.png"):
            atomic_write(dest / name, (out / name).read_bytes())
        for level in levels:  # each level's summary and its run records
            folder = out / f"p{level:g}"
            files = [folder / n for n in ("study.json", "study.md", "study_mnist.png")]
            for src in [*files, *sorted((folder / "runs").glob("*.json"))]:
                if src.exists():
                    atomic_write(dest / src.relative_to(out), src.read_bytes())
        print(f"shipped to {dest}")
    return 0


if __name__ == "__main__":
    sys.exit(run())
