"""``layoutwarp preprocess`` and ``export``: a folder of images to sensor images, a layout to a mask."""

from __future__ import annotations

import argparse
import json
import re
import sys
import tempfile
from collections.abc import Sequence
from pathlib import Path

from .common import (
    UsageError,
    add_command,
    add_layout_args,
    add_physics_args,
    distinct_files,
    existing_folder,
    int_range,
    layout_from_args,
    parse_um,
    physics_from_args,
    pick_device,
    positive_float,
    positive_int,
    quiet_decoders,
)

__all__ = ["add_commands"]

#: A Dask scheduler's address: ``HOST:PORT``, optionally behind a protocol (``tcp://``, ``tls://``, ...).
ADDRESS = re.compile(r"([A-Za-z][A-Za-z0-9+.-]*://)?(\[[0-9A-Fa-f:.]+\]|[^\s:/\[\]]+)(:\d{1,5})?")


def _cmd_preprocess(args: argparse.Namespace) -> int:
    from ..files import atomic_write
    from ..imagefiles import IMAGE_SUFFIXES, list_images
    from ..preprocess import check_destination, preprocess_folder

    existing_folder(args.src, "SRC")
    check_destination(Path(args.dst), Path(args.src))
    if args.labels is not None:
        existing_folder(args.labels, "--labels")
    elif args.label_rule is not None:
        raise UsageError(
            f"argument --label-rule: needs --labels DIR (the label maps), got {args.label_rule!r}"
        )
    if args.address is not None and not ADDRESS.fullmatch(args.address):
        raise UsageError(
            f"argument --address: must be a scheduler's HOST[:PORT], tcp://HOST[:PORT], got {args.address!r}"
        )
    layout, size = layout_from_args(args)
    dst = Path(args.dst)
    if not list_images(args.src, dst):
        raise UsageError(f"argument SRC: no images ({', '.join(IMAGE_SUFFIXES)}) under {args.src!r}")
    if args.benchmark and dst.exists() and any(dst.iterdir()):
        raise UsageError(f"argument --benchmark: needs an empty DST, {str(dst)!r} is not empty")
    base = None
    if args.benchmark:  # the baseline first, both on a warm page cache
        files = [path for path in list_images(args.src, dst) if path.is_file()]  # no broken link
        for path in files:
            path.read_bytes()
        with tempfile.TemporaryDirectory() as tmp:
            base = _baseline(files, size, tmp)
    physics, device = physics_from_args(args), pick_device(args.device)
    progress = not args.no_progress and sys.stderr.isatty()  # asked now: stderr is a pipe within
    with quiet_decoders() as decoder_lines:  # a broken file is reported once, as a failure
        res = preprocess_folder(
            args.src,
            dst,
            layout,
            size,
            labels=args.labels,
            label_rule=args.label_rule or "nearest",
            workers=args.workers,
            tol=args.tol,
            progress=progress,
            engine=args.engine,
            address=args.address,
            device=device,
            physics=physics,
        )
    print(
        f"{res.processed} written, {res.skipped} already done, {len(res.failed)} failed "
        f"in {res.seconds:.2f} s ({res.images_per_second:.1f} images/s, {args.workers} worker(s)); "
        f"manifest {res.manifest}"
    )
    for f in res.failed:
        print(f"  failed: {f['file']}: {f['error']}", file=sys.stderr)
    manifest = json.loads(res.manifest.read_text())
    if decoder_lines:
        print(
            f"layoutwarp: warning: the image decoders reported {len(decoder_lines)} problem(s), e.g. "
            f"{decoder_lines[0]!r}; files that still decoded were processed (the lines are in the manifest)",
            file=sys.stderr,
        )
        manifest["decoder_messages"] = decoder_lines
    if base is not None:
        ours = res.processed / res.seconds
        ref = len(files) / base
        print(
            f"benchmark ({len(files)} files): layoutwarp {ours:.1f} images/s, "
            f"imread + resize(INTER_AREA) + imwrite {ref:.1f} images/s, ratio {ours / ref:.2f}x"
        )
        total = sum(res.stages.values()) or float("nan")
        per_image = {k: v / max(res.processed, 1) * 1e3 for k, v in res.stages.items()}
        parts = [f"{k} {v / total:.0%} ({per_image[k]:.1f} ms/image)" for k, v in res.stages.items()]
        print("  where the workers' time went: " + ", ".join(parts))
        manifest["benchmark"] = {"images_per_s": ours, "baseline_images_per_s": ref, "ratio": ours / ref}
        manifest["benchmark"]["stage_seconds"] = res.stages
    if decoder_lines or base is not None:
        atomic_write(res.manifest, json.dumps(manifest, indent=2))
    return 1 if res.failed else 0


def _cmd_export(args: argparse.Namespace) -> int:
    from ..checks import ArgumentError
    from ..export import export_format, export_layout, index_mask_paths, report_json
    from ..files import atomic_write, check_file_destination

    check_file_destination(args.out, "out")  # both before any work: nothing written, then refused
    if args.report:
        check_file_destination(args.report, "report")
    outputs = {"--out": args.out}
    try:
        fmt = export_format(args.out, args.format)
    except ArgumentError as exc:  # export_layout's file is the command's --out
        raise ArgumentError("out" if exc.argument == "path" else exc.argument, str(exc)) from None
    if fmt == "png":  # its index mask beside it
        small, large = index_mask_paths(args.out)
        outputs |= {"--out (its index mask)": small, "--out (its large index mask)": large}
    outputs["--report"] = args.report
    distinct_files(outputs, {"--layout": args.layout, "--physics": args.physics})
    layout, size = layout_from_args(args)
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
        physics=physics_from_args(args, args.sensor_um),
        progress=False if args.no_progress else None,
    )
    print(report.summary())
    if args.report:
        atomic_write(args.report, report_json(report))
    return 0


def add_commands(sub: argparse._SubParsersAction, families: Sequence[str]) -> None:
    """The ``preprocess`` and ``export`` commands' parsers."""
    pp = add_command(
        sub, "preprocess", "Write the sensor image of every image in a folder (and move its label maps)."
    )
    pp.add_argument("src", metavar="SRC", help="source folder (walked recursively)")
    pp.add_argument("dst", metavar="DST", help="destination folder (same relative paths)")
    add_layout_args(pp, families)
    pp.add_argument("--labels", metavar="DIR", help="folder of class-index label maps (same relative paths)")
    pp.add_argument(
        "--label-rule",
        choices=["nearest", "majority", "inverse"],
        help="labels to the sensor grid by the label under each pixel centre (nearest) or the "
        "largest area (majority), or kept full size with back-warp maps (inverse) (default: nearest)",
    )
    pp.add_argument(
        "--workers",
        type=int_range(1, 256),
        default=1,
        help="worker threads (local) or processes (new Dask cluster)",
    )
    pp.add_argument(
        "--engine",
        choices=["local", "dask"],
        default="local",
        help="threads here, or tasks on a Dask cluster (pip install 'layoutwarp[dask]')",
    )
    pp.add_argument(
        "--address",
        metavar="HOST:PORT",
        help="with --engine dask: join this running scheduler (default: start one)",
    )
    pp.add_argument(
        "--tol", type=positive_float, help="curved-edge tolerance (default: 1/4 level of the image dtype)"
    )
    pp.add_argument(
        "--device",
        help="where the sparse products run: cpu, cuda, ... (default: cuda when available, else cpu)",
    )
    pp.add_argument("--no-progress", action="store_true", help="no progress bar")
    pp.add_argument(
        "--benchmark", action="store_true", help="also time a plain OpenCV loop on the same files"
    )
    add_physics_args(pp)
    pp.set_defaults(func=_cmd_preprocess)

    ex = add_command(
        sub, "export", "Write a layout's pixel boundaries as a fabrication mask (GDSII, DXF, SVG, PNG)."
    )
    add_layout_args(ex, families)
    ex.add_argument("--sensor-um", type=parse_um, required=True, help="sensor extent WIDTHxHEIGHT in µm")
    ex.add_argument("--out", required=True, help="output file (*.gds, *.dxf, *.svg or *.png)")
    ex.add_argument(
        "--format",
        choices=["gds", "dxf", "svg", "png"],
        help="must match --out's suffix (default: the suffix)",
    )
    ex.add_argument("--tol-um", type=positive_float, default=0.01, help="curved-edge tolerance in µm")
    ex.add_argument(
        "--grid-um",
        type=positive_float,
        help="snap vertices to this grid (µm), finer than a pixel "
        "(default: no snapping; GDSII's 1 nm for *.gds)",
    )
    ex.add_argument("--manhattan", action="store_true", help="axis-aligned steps instead of slanted edges")
    ex.add_argument(
        "--gds-layer", type=int_range(0, 32767), default=1, help="GDSII layer (DXF layer PIXELS_<n>)"
    )
    ex.add_argument("--gds-datatype", type=int_range(0, 32767), default=0, help="GDSII datatype")
    ex.add_argument(
        "--px-per-um", type=positive_float, help="PNG resolution (default: 4096 px on the long side)"
    )
    ex.add_argument(
        "--line-width", type=positive_int, default=1, help="PNG boundary line width in raster pixels"
    )
    ex.add_argument("--min-feature-um", type=positive_float, help="warn below this pitch (µm)")
    ex.add_argument("--report", metavar="FILE", help="also write the report as JSON to this file")
    ex.add_argument("--no-progress", action="store_true", help="no progress bars (drawn for large sensors)")
    add_physics_args(ex, extent="--sensor-um")
    ex.set_defaults(func=_cmd_export)


def _baseline(files: list[Path], size: tuple[int, int], out: str | Path) -> float:
    """Seconds for the plain OpenCV loop over ``files``: imread, resize INTER_AREA, imwrite."""
    import time

    import cv2

    from ..checks import check_size

    h, w = check_size(size)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    for k, path in enumerate(files):
        img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if img is None:
            continue
        cv2.imwrite(str(out / f"{k}{path.suffix}"), cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA))
    return time.perf_counter() - t0
