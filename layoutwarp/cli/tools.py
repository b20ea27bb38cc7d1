"""``layoutwarp demo``, ``doctor`` and ``bench``."""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

from .common import (
    UsageError,
    add_command,
    check_sensor_memory,
    distinct_files,
    int_range,
    out_dir,
    out_file,
    parse_theta,
    parse_wxh,
    pick_device,
    positive_float,
    quiet_decoders,
    readable_image,
)

__all__ = ["add_commands"]

#: The figure formats ``bench --plot`` writes (matplotlib's, by the file's suffix).
PLOT_SUFFIXES = (".png", ".pdf", ".svg")


def _cmd_demo(args: argparse.Namespace) -> int:
    from ..experiments.data import samples_dir
    from ..experiments.demo import demo_outputs, run_demo

    image = readable_image(args.image or samples_dir() / "photos" / "kodim20.png")
    check_sensor_memory(args.size)
    out_dir(args.out)
    for path in demo_outputs(args.out):  # the photo is none of the files the demo writes
        distinct_files({"--out": path}, {"--image": image})
    with quiet_decoders():  # the demo decodes the photo again
        numbers = run_demo(image, args.out, args.size, args.theta, args.tol)
    print(f"wrote {args.out}/layouts.png, demo.json and sensor_*.png")
    for name, d in numbers["layouts"].items():
        print(
            f"  {name:22s} method={d['method']:9s} {d['seconds'] * 1e3:7.1f} ms  "
            f"area ratio {d['pixel_area_ratio_max_over_min']:.2f}"
        )
    return 0


def _cmd_doctor(args: argparse.Namespace) -> int:
    from .. import doctor, jit

    if args.compile:
        processes = min(2, os.cpu_count() or 1)
        folder = jit.cache_folder()
        print(f"compiling every unit of kernels into {folder} (once per installation; {processes} at a time)")
        start = time.perf_counter()
        total: list[float] = []

        def said(unit: str, seconds: float, cpu: float) -> None:
            total.append(cpu)
            print(f"  {unit:<16} {seconds:6.1f} s  (CPU {cpu:5.1f} s)", flush=True)

        jit.compile_all(said, processes=processes)
        print(f"  {'in all':<16} {time.perf_counter() - start:6.1f} s  (CPU {sum(total):5.1f} s)")
    print(doctor.report())
    return 0


def _cmd_bench(args: argparse.Namespace) -> int:
    import torch

    from ..experiments.bench import main_bench

    if args.image:
        readable_image(args.image)
    for path, flag in ((args.json, "--json"), (args.text, "--text"), (args.plot, "--plot")):
        out_file(path, flag)  # all before the benchmark's minutes: nothing measured, then lost
    distinct_files({"--json": args.json, "--text": args.text, "--plot": args.plot}, {"--image": args.image})
    if args.plot and Path(args.plot).suffix.lower() not in PLOT_SUFFIXES:
        raise UsageError(f"argument --plot: must end in {', '.join(PLOT_SUFFIXES)}, got {args.plot!r}")
    only = _bench_rows(args.layouts)
    if args.threads:
        torch.set_num_threads(args.threads)
    main_bench(
        args.quick,
        args.json,
        args.plot,
        memory=not args.no_memory,
        with_scaling=not args.no_scaling,
        photo=args.image,
        device=pick_device(args.device) if args.device else "cpu",
        only=only,
        text_path=args.text,
    )
    return 0


def _bench_rows(text: str | None) -> list[str] | None:
    """``--layouts``: comma-separated rows of the benchmark, checked."""
    if text is None:
        return None
    from ..experiments.benchconfig import bench_layouts

    names = list(bench_layouts((0.0, 0.0)))
    rows = [t.strip() for t in text.split(",")]
    for r in rows:
        if r not in names:
            raise UsageError(f"argument --layouts: {r!r} is not a row; choose from {', '.join(names)}")
    return rows


def add_commands(sub: argparse._SubParsersAction) -> None:
    """The ``demo``, ``doctor`` and ``bench`` commands' parsers."""
    d = add_command(sub, "demo", "Simulate the layout families on a photo and write figures and numbers.")
    d.add_argument("--image", help="an image file (default: the bundled kodim20 photo)")
    d.add_argument("--size", type=parse_wxh, default="32x32", help="sensor WIDTHxHEIGHT")
    d.add_argument("--theta", type=parse_theta, default="0.5,0.5", help="θ as TX,TY")
    d.add_argument(
        "--tol",
        type=positive_float,
        help="bound on each pixel's error relative to the value range (default: what 8-bit data needs)",
    )
    d.add_argument("--out", default="results/demo", help="output folder")
    d.set_defaults(func=_cmd_demo)

    dr = add_command(
        sub, "doctor", "Versions, which backend each path runs here and why, and the compiled kernels."
    )
    dr.add_argument(
        "--compile",
        action="store_true",
        help="compile every group of kernels now, in the foreground (e.g. when building a container image)",
    )
    dr.set_defaults(func=_cmd_doctor)

    b = add_command(
        sub, "bench", "Time and error of every integrator against anchors measured in the same run."
    )
    b.add_argument("--quick", action="store_true", help="small sizes, few repeats")
    b.add_argument("--json", metavar="FILE", help="also write the results to this JSON file")
    b.add_argument("--text", metavar="FILE", help="also write the printed tables to this file (Markdown)")
    b.add_argument("--plot", metavar="FILE", help="also draw the speed-vs-error plot to this PNG")
    b.add_argument("--image", help="photo to measure on (default: the bundled kodim20)")
    b.add_argument("--threads", type=int_range(1, 256), help="torch threads (default: torch's choice)")
    b.add_argument(
        "--device", help="where the integrators run, e.g. cpu, cuda (default: cpu; anchors stay on the CPU)"
    )
    b.add_argument("--no-memory", action="store_true", help="skip the peak-memory children")
    b.add_argument("--no-scaling", action="store_true", help="skip the input/sensor size scaling grid")
    b.add_argument(
        "--layouts",
        metavar="ROWS",
        help="only these comma-separated layout rows (uniform, rect, curv, 'curv ±', spline, 'grid 8x8', "
        "fovea); the anchors are always measured",
    )
    b.set_defaults(func=_cmd_bench)
