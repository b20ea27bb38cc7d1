"""Command line: ``layoutwarp <command>`` (also ``python -m layoutwarp``).

Sizes on the command line are ``WIDTHxHEIGHT`` like OpenCV's ``dsize`` ("257x129" is 257
wide); the Python API uses ``(H, W)``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Sequence
from pathlib import Path

__all__ = ["main", "parse_wxh"]

DEFAULT_DATA = Path("data_samples")


def parse_wxh(text: str) -> tuple[int, int]:
    """``"257x129"`` (width x height) to ``(H, W) = (129, 257)``."""
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"size must be WIDTHxHEIGHT, e.g. 257x129, got {text!r}") from None
    if w <= 0 or h <= 0:
        raise argparse.ArgumentTypeError(f"size must be positive, got {text!r}")
    return h, w


def parse_theta(text: str) -> tuple[float, float]:
    try:
        tx, ty = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"theta must be TX,TY, e.g. 0.3,0.1, got {text!r}") from None
    return tx, ty


def _cmd_demo(args: argparse.Namespace) -> int:
    """Simulate the paper's layouts on a bundled photo; write figures and numbers."""
    import cv2
    import numpy as np
    import torch

    import layoutwarp as lw
    from layoutwarp.plots import layout_figure

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    path = Path(args.image) if args.image else Path(args.data) / "photos" / "kodim20.png"
    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if bgr is None:
        print(f"error: cannot read image {path}", file=sys.stderr)
        return 2
    rgb = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
    img = torch.from_numpy(rgb).permute(2, 0, 1)[None]
    size = args.size
    tx, ty = args.theta
    layouts = {
        "uniform": lw.UniformLayout(),
        f"rect θ=({tx:g}, {ty:g})": lw.RectLayout((tx, ty)),
        f"curv θ=({tx:g}, {ty:g})": lw.CurvLayout((tx, ty)),
    }
    panels, numbers = [], {"image": str(path), "size_wxh": f"{size[1]}x{size[0]}", "layouts": {}}
    for name, layout in layouts.items():
        t0 = time.perf_counter()
        with torch.no_grad():
            sim, plan = lw.simulate(img, layout, size, "exact", tol=args.tol, return_plan=True)
        elapsed = time.perf_counter() - t0
        arr = sim[0].permute(1, 2, 0).numpy()
        areas = lw.pixel_mesh(layout, size, tol=args.tol).areas().detach()
        panels.append((name, layout, arr))
        numbers["layouts"][name] = {
            "family": layout.family,
            "theta": [float(v) for v in layout.theta.detach()],
            "method": plan.method,
            "error_bound": plan.error_bound,
            "seconds": round(elapsed, 4),
            "pixel_area_ratio_max_over_min": float(areas.max() / areas.min()),
        }
        cv2.imwrite(
            str(out / f"sensor_{layout.family}.png"),
            cv2.cvtColor((np.clip(arr, 0, 1) * 255).round().astype(np.uint8), cv2.COLOR_RGB2BGR),
        )
    fig = layout_figure(rgb / 255.0, panels, size, out / "layouts.png")
    (out / "demo.json").write_text(json.dumps(numbers, indent=2))
    print(f"wrote {fig}, {out / 'demo.json'} and sensor_*.png")
    for name, d in numbers["layouts"].items():
        print(
            f"  {name:22s} method={d['method']:9s} {d['seconds'] * 1e3:7.1f} ms  "
            f"area ratio {d['pixel_area_ratio_max_over_min']:.2f}"
        )
    return 0


def _cmd_bench(args: argparse.Namespace) -> int:
    """Speed against error of every integrator, with anchors measured in the same run."""
    from layoutwarp.bench import main_bench

    main_bench(
        args.quick,
        args.json,
        args.plot,
        memory=not args.no_memory,
        with_scaling=not args.no_scaling,
        photo=args.image,
    )
    return 0


def _cmd_train(args: argparse.Namespace) -> int:
    """Train a sensor layout jointly with a network (the paper's experiments)."""
    if args.task != "mnist":
        print(f"error: task {args.task!r} is not available yet (mnist is)", file=sys.stderr)
        return 2
    from layoutwarp.train import run_mnist_experiment

    data = Path(args.data) if args.data else (DEFAULT_DATA / "mnist" if args.quick else _shared("mnist"))
    layouts = (args.layout,) if args.layout else ("uniform", "curv", "rect")
    seeds = tuple(range(args.seeds)) if args.seeds else ((0,) if args.quick else (0, 1, 2))
    epochs = args.epochs or (3 if args.quick else 14)
    print(f"MNIST 4x4: data {data}, layouts {', '.join(layouts)}, seeds {list(seeds)}, {epochs} epochs")
    sensor = {"method": args.method}
    if args.method in ("montecarlo", "point"):
        sensor["radiance"] = args.radiance
    if args.method == "montecarlo":
        sensor["samples"] = args.samples
    result = run_mnist_experiment(
        data, args.out, layouts, seeds, epochs, progress=not args.no_progress, sensor=sensor
    )
    print(f"{'layout':8s} {'test accuracy':>18s}  θ (mean)")
    for name, s in result["summary"].items():
        th = ", ".join(f"{v:+.2f}" for v in s["theta_mean"])
        print(f"{name:8s} {s['accuracy_mean']:8.2f} ± {s['accuracy_std']:4.2f} %   ({th})  n={s['n']}")
    print(f"wrote {args.out}/results.json, layout.json, mnist_layouts.png, mnist_theta.png")
    return 0


def _shared(name: str) -> Path:
    return Path(__file__).resolve().parents[1].parent / "shared" / "data" / name


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="layoutwarp", description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="command", required=True)
    d = sub.add_parser("demo", help="simulate the paper's layouts on a bundled photo and write figures")
    d.add_argument("--data", default=str(DEFAULT_DATA), help="data folder (default: data_samples)")
    d.add_argument("--image", default=None, help="an image file instead of the bundled photo")
    d.add_argument("--size", type=parse_wxh, default=(24, 32), help="sensor WIDTHxHEIGHT (default 32x24)")
    d.add_argument("--theta", type=parse_theta, default=(0.5, 0.5), help="θ as TX,TY (default 0.5,0.5)")
    d.add_argument("--tol", type=float, default=1e-5, help="relative pixel-value tolerance")
    d.add_argument("--out", default="results/demo", help="output folder")
    d.set_defaults(func=_cmd_demo)
    b = sub.add_parser("bench", help="time and error of every integrator against anchors (one process)")
    b.add_argument("--quick", action="store_true", help="small sizes, few repeats")
    b.add_argument("--json", default=None, help="also write the results to this JSON file")
    b.add_argument("--plot", default=None, help="also draw the speed-vs-error plot to this PNG")
    b.add_argument("--image", default=None, help="photo to use (default: the bundled kodim20)")
    b.add_argument("--no-memory", action="store_true", help="skip the peak-memory children")
    b.add_argument("--no-scaling", action="store_true", help="skip the input/sensor size scaling grid")
    b.set_defaults(func=_cmd_bench)
    t = sub.add_parser("train", help="train a layout jointly with a network (mnist)")
    t.add_argument("task", choices=["mnist", "camvid", "faces"], help="the experiment")
    t.add_argument(
        "--layout", choices=["uniform", "curv", "rect"], default=None, help="one layout (default: all)"
    )
    t.add_argument("--quick", action="store_true", help="data_samples/, 1 seed, 3 epochs (about a minute)")
    t.add_argument("--data", default=None, help="folder with the dataset (default: ../shared/data/<task>)")
    t.add_argument("--seeds", type=int, default=None, help="number of seeds (default 3; 1 with --quick)")
    t.add_argument("--epochs", type=int, default=None, help="epochs (default 14; 3 with --quick)")
    t.add_argument(
        "--method", default="exact", choices=["exact", "montecarlo", "point"], help="sensor integrator"
    )
    t.add_argument("--samples", type=int, default=4, help="Monte Carlo samples per axis (s² per pixel)")
    t.add_argument(
        "--radiance", default="bilinear", choices=["bilinear", "box"], help="radiance for sampling"
    )
    t.add_argument("--no-progress", action="store_true", help="no progress bars")
    t.add_argument("--out", default="results/mnist", help="output folder")
    t.set_defaults(func=_cmd_train)
    return p


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    return int(args.func(args) or 0)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
