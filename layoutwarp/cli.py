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


def parse_um(text: str) -> tuple[float, float]:
    """``"5600x4200"`` (width x height in µm) to ``(5600.0, 4200.0)``."""
    try:
        w, h = (float(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"extent must be WIDTHxHEIGHT in µm, e.g. 5600x4200, got {text!r}"
        ) from None
    if not (w > 0 and h > 0):
        raise argparse.ArgumentTypeError(f"extent must be positive, got {text!r}")
    return w, h


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
    from layoutwarp.io import atomic_write
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
    atomic_write(out / "demo.json", json.dumps(numbers, indent=2))
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


def _sensor_options(args: argparse.Namespace, default_tol: float | None = None) -> dict:
    sensor = {"method": args.method}
    tol = args.tol if args.tol is not None else default_tol
    if args.method == "exact" and tol is not None:
        sensor["tol"] = tol
    if args.method in ("montecarlo", "point"):
        sensor["radiance"] = args.radiance
    if args.method == "montecarlo":
        sensor["samples"] = args.samples
    return sensor


def _cmd_train(args: argparse.Namespace) -> int:
    """Train a sensor layout jointly with a network (the paper's experiments)."""
    if args.task == "camvid":
        return _train_task(args, "camvid")
    if args.task == "faces":
        return _train_task(args, "faces")
    from layoutwarp.train import run_mnist_experiment

    data = Path(args.data) if args.data else (DEFAULT_DATA / "mnist" if args.quick else _shared("mnist"))
    layouts = (args.layout,) if args.layout else ("uniform", "curv", "rect")
    seeds = tuple(range(args.seeds)) if args.seeds else ((0,) if args.quick else (0, 1, 2))
    epochs = args.epochs or (3 if args.quick else 14)
    print(f"MNIST 4x4: data {data}, layouts {', '.join(layouts)}, seeds {list(seeds)}, {epochs} epochs")
    sensor = _sensor_options(args)
    result = run_mnist_experiment(
        data, args.out, layouts, seeds, epochs, progress=not args.no_progress, sensor=sensor
    )
    print(f"{'layout':8s} {'test accuracy':>18s}  θ (mean)")
    for name, s in result["summary"].items():
        th = ", ".join(f"{v:+.2f}" for v in s["theta_mean"])
        print(f"{name:8s} {s['accuracy_mean']:8.2f} ± {s['accuracy_std']:4.2f} %   ({th})  n={s['n']}")
    print(f"wrote {args.out}/results.json, layout.json, mnist_layouts.png, mnist_theta.png")
    return 0


TASK_DEFAULTS = {
    # task: (shared folder, data_samples folder, layouts, sizes (H, W), seeds, epochs, quick epochs)
    "camvid": ("camvid", "camvid", ("uniform", "curv", "rect"), ((36, 48), (72, 96)), 2, 12, 1),
    "faces": ("faces/utkface_subset", "faces/utkface", ("uniform", "rect"), ((8, 8), (16, 16)), 3, 30, 2),
}


def _train_task(args: argparse.Namespace, task: str) -> int:
    from layoutwarp import tasks

    shared, sample, layouts, sizes, n_seeds, epochs, quick_epochs = TASK_DEFAULTS[task]
    data = Path(args.data) if args.data else (DEFAULT_DATA / sample if args.quick else _shared(shared))
    if not data.exists():
        print(f"error: no data at {data}; pass --data DIR or --quick (bundled samples)", file=sys.stderr)
        return 2
    layouts = (args.layout,) if args.layout else layouts
    sizes = tuple(args.size) if args.size else (sizes[:1] if args.quick else sizes)
    seeds = tuple(range(args.seeds)) if args.seeds else ((0,) if args.quick else tuple(range(n_seeds)))
    epochs = args.epochs or (quick_epochs if args.quick else epochs)
    out = args.out if args.out != "results/mnist" else f"results/{task}"
    sizes_txt = ", ".join(f"{w}x{h}" for h, w in sizes)
    print(
        f"{task}: data {data}, layouts {', '.join(layouts)}, sensors {sizes_txt}, "
        f"seeds {list(seeds)}, {epochs} epochs"
    )
    common = {"progress": not args.no_progress, "sensor": _sensor_options(args, 1e-3), "layouts": layouts}
    common |= {"sizes": sizes, "seeds": seeds, "epochs": epochs}
    if task == "camvid":
        freeze = args.freeze_epochs if args.freeze_epochs is not None else (0 if args.quick else 3)
        result = tasks.run_camvid_experiment(
            data, out, freeze_epochs=freeze, class_weights=args.class_weights, **common
        )
        metrics = ("miou", "pixel_accuracy")
    else:
        result = tasks.run_faces_experiment(data, out, **common)
        metrics = ("gender", "age_group", "race", "mean")
    print(f"{'layout':16s} " + " ".join(f"{m:>16s}" for m in metrics) + "  θ (mean)")
    for name, s in result["summary"].items():
        cells = " ".join(f"{s[m]['mean']:8.2f} ± {s[m]['std']:5.2f}" for m in metrics)
        th = ", ".join(f"{v:+.2f}" for v in s["theta_mean"])
        print(f"{name:16s} {cells}  ({th})  n={s['n']}")
    print(f"wrote {out}/results.json, layout_*.json and {task}_layouts.png")
    return 0


def _layout_from_args(args: argparse.Namespace):
    """The layout and sensor size from ``--layout FILE`` or ``--family/--theta``, and ``--size``."""
    import torch

    import layoutwarp as lw

    if args.layout:
        layout, info = lw.load_layout(args.layout, dtype=torch.float64)
        size = args.size or (tuple(info["size_hw"]) if info.get("size_hw") else None)
    else:
        if not args.family:
            raise SystemExit("error: give --layout LAYOUT.json or --family (with --theta)")
        theta = None if args.family == "uniform" else (args.theta or (0.0, 0.0))
        layout, size = lw.make_layout(args.family, theta, dtype=torch.float64), args.size
    if size is None:
        raise SystemExit("error: --size WIDTHxHEIGHT is needed (the layout file stores no sensor size)")
    return layout, size


def _cmd_preprocess(args: argparse.Namespace) -> int:
    """Write the sensor image of every image of a folder (and move its label maps)."""
    from layoutwarp.io import atomic_write
    from layoutwarp.preprocess import _walk, benchmark_baseline, preprocess_folder

    layout, size = _layout_from_args(args)
    dst = Path(args.dst)
    if args.benchmark and dst.exists() and any(dst.iterdir()):
        print(f"error: --benchmark needs an empty DST, {dst} is not empty", file=sys.stderr)
        return 2
    base = None
    if args.benchmark:  # the baseline first, both on a warm page cache
        import tempfile

        files = _walk(Path(args.src), dst.resolve())
        for path in files:
            path.read_bytes()
        with tempfile.TemporaryDirectory() as tmp:
            base = benchmark_baseline(files, size, tmp)
    try:
        res = preprocess_folder(
            args.src,
            dst,
            layout,
            size,
            labels=args.labels,
            label_rule=args.label_rule,
            workers=args.workers,
            tol=args.tol,
            progress=False if args.no_progress else None,
        )
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(
        f"{res.processed} written, {res.skipped} already done, {len(res.failed)} failed "
        f"in {res.seconds:.2f} s ({res.images_per_second:.1f} images/s, {args.workers} worker(s)); "
        f"manifest {res.manifest}"
    )
    for f in res.failed:
        print(f"  failed: {f['file']}: {f['error']}", file=sys.stderr)
    if base is not None:
        ours = res.processed / res.seconds
        ref = len(files) / base
        print(
            f"benchmark ({len(files)} files): layoutwarp {ours:.1f} images/s, "
            f"imread + resize(INTER_AREA) + imwrite {ref:.1f} images/s, ratio {ours / ref:.2f}x"
        )
        manifest = json.loads(res.manifest.read_text())
        manifest["benchmark"] = {"images_per_s": ours, "baseline_images_per_s": ref, "ratio": ours / ref}
        atomic_write(res.manifest, json.dumps(manifest, indent=2))
    return 1 if res.failed else 0


def _cmd_export(args: argparse.Namespace) -> int:
    """Write a layout's pixel boundaries as a GDSII/DXF/SVG/PNG fabrication mask."""
    from layoutwarp.export import export_layout, report_json
    from layoutwarp.io import atomic_write

    layout, size = _layout_from_args(args)
    try:
        report = export_layout(
            layout,
            size,
            args.out,
            args.sensor_um,
            format=args.format,
            tol_um=args.tol_um,
            grid_um=args.grid_um,
            manhattan=args.manhattan,
            layer=args.gds_layer,
            datatype=args.gds_datatype,
            px_per_um=args.px_per_um,
            line_width=args.line_width,
            min_feature_um=args.min_feature_um,
        )
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(report.summary())
    if args.report:
        atomic_write(args.report, report_json(report))
    return 0


def _shared(name: str) -> Path:
    return Path(__file__).resolve().parents[1].parent / "shared" / "data" / name


def _layout_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--layout", default=None, help="layout JSON file (save_layout / train output)")
    p.add_argument("--family", choices=["uniform", "rect", "curv"], default=None, help="or a layout family")
    p.add_argument("--theta", type=parse_theta, default=None, help="θ as TX,TY with --family")
    p.add_argument("--size", type=parse_wxh, default=None, help="sensor WIDTHxHEIGHT (default: the file's)")


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
    pp = sub.add_parser(
        "preprocess", help="sensor images of a folder of images (OpenCV, precomputed weights)"
    )
    pp.add_argument("src", help="source folder (walked recursively)")
    pp.add_argument("dst", help="destination folder (same relative paths)")
    _layout_args(pp)
    pp.add_argument("--labels", default=None, help="folder of class-index label maps (same relative paths)")
    pp.add_argument(
        "--label-rule",
        choices=["nearest", "majority", "inverse"],
        default="nearest",
        help="labels to the sensor grid by the label under each pixel centre (nearest) or the "
        "largest area (majority), or keep them full size with back-warp maps (inverse)",
    )
    pp.add_argument("--workers", type=int, default=1, help="worker threads (default 1)")
    pp.add_argument(
        "--tol",
        type=float,
        default=None,
        help="curved-edge tolerance (default: 1/4 level of the image dtype)",
    )
    pp.add_argument("--no-progress", action="store_true", help="no progress bar")
    pp.add_argument(
        "--benchmark", action="store_true", help="also time a plain OpenCV loop on the same files"
    )
    pp.set_defaults(func=_cmd_preprocess)
    ex = sub.add_parser("export", help="pixel boundaries as a fabrication mask (GDSII, DXF, SVG, PNG)")
    ex.add_argument("layout", nargs="?", default=None, help="layout JSON file")
    ex.add_argument("--family", choices=["uniform", "rect", "curv"], default=None, help="or a layout family")
    ex.add_argument("--theta", type=parse_theta, default=None, help="θ as TX,TY with --family")
    ex.add_argument("--size", type=parse_wxh, default=None, help="sensor WIDTHxHEIGHT in pixels")
    ex.add_argument("--sensor-um", type=parse_um, required=True, help="sensor extent WIDTHxHEIGHT in µm")
    ex.add_argument(
        "--format", choices=["gds", "dxf", "svg", "png"], default=None, help="default: --out's suffix"
    )
    ex.add_argument("--out", required=True, help="output file")
    ex.add_argument("--tol-um", type=float, default=0.01, help="curved-edge tolerance in µm (default 0.01)")
    ex.add_argument("--grid-um", type=float, default=None, help="snap vertices to this grid (µm)")
    ex.add_argument("--manhattan", action="store_true", help="axis-aligned steps instead of slanted edges")
    ex.add_argument("--gds-layer", type=int, default=1, help="GDSII layer (DXF layer PIXELS_<n>), default 1")
    ex.add_argument("--gds-datatype", type=int, default=0, help="GDSII datatype, default 0")
    ex.add_argument(
        "--px-per-um", type=float, default=None, help="PNG resolution (default: 4096 px long side)"
    )
    ex.add_argument("--line-width", type=int, default=1, help="PNG boundary line width in raster pixels")
    ex.add_argument("--min-feature-um", type=float, default=None, help="warn below this pitch (µm)")
    ex.add_argument("--report", default=None, help="also write the report as JSON to this file")
    ex.set_defaults(func=_cmd_export)
    t = sub.add_parser("train", help="train a layout jointly with a network (mnist, camvid, faces)")
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
    t.add_argument(
        "--size",
        type=parse_wxh,
        action="append",
        default=None,
        help="sensor WIDTHxHEIGHT for camvid/faces (repeat for several; default 48x36 and 96x72 "
        "for camvid, 8x8 and 16x16 for faces)",
    )
    t.add_argument(
        "--tol",
        type=float,
        default=None,
        help="exact integrator's curved-edge tolerance (default 1e-5 for mnist, 1e-3 for camvid/faces)",
    )
    t.add_argument("--freeze-epochs", type=int, default=None, help="camvid: epochs with θ frozen (default 3)")
    t.add_argument(
        "--class-weights",
        choices=["none", "median"],
        default="median",
        help="camvid: loss class weights, none or median-frequency balancing (default median)",
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
