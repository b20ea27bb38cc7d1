"""Command line: ``layoutwarp <command>`` (also ``python -m layoutwarp``).

Sizes on the command line are ``WIDTHxHEIGHT`` like OpenCV's ``dsize`` ("257x129" is 257
wide); the Python API uses ``(H, W)``. Every error ends in one line on stderr that names the
flag, the value and what is allowed, with exit status 2.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import re
import sys
import tempfile
import warnings
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, NoReturn

if TYPE_CHECKING:  # the experiments load on demand
    from .experiments.protocols import StudyPlan, TaskDefaults, TaskSpec
    from .experiments.runs import RunOptions
    from .experiments.tasks import Task

__all__ = ["build_parser", "main", "parse_theta", "parse_wxh"]

#: Library argument names and the command-line flags that set them, for error lines.
FLAGS = {
    "out": "--out",
    "report": "--report",
    "dst": "DST",
    "src": "SRC",
    "format": "--format",
    "grid_um": "--grid-um",
    "tol_um": "--tol-um",
    "tol": "--tol",
    "workers": "--workers",
    "label_rule": "--label-rule",
    "engine": "--engine",
    "address": "--address",
}


class UsageError(Exception):
    """A bad command-line value: printed as one line, exit status 2."""


class _Parser(argparse.ArgumentParser):
    """An ``ArgumentParser`` whose errors are one line (no usage block) with exit status 2."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message}\n")


class _Formatter(argparse.ArgumentDefaultsHelpFormatter):
    """Shows every default as ``(default: X)``, except for flags and options without one."""

    def _get_help_string(self, action: argparse.Action) -> str | None:
        if action.default is None or action.default is False or isinstance(action, argparse._VersionAction):
            return action.help
        return super()._get_help_string(action)


# ----------------------------------------------------------------------------------------
# Value types
# ----------------------------------------------------------------------------------------
def parse_wxh(text: str) -> tuple[int, int]:
    """``"257x129"`` (width x height) to ``(H, W) = (129, 257)``."""
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be WIDTHxHEIGHT, e.g. 257x129, got {text!r}") from None
    if w <= 0 or h <= 0:
        raise argparse.ArgumentTypeError(f"width and height must be >= 1, got {text!r}")
    return h, w


def parse_um(text: str) -> tuple[float, float]:
    """``"5600x4200"`` (width x height in µm) to ``(H_um, W_um) = (4200.0, 5600.0)``."""
    try:
        w, h = (float(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"must be WIDTHxHEIGHT in µm, e.g. 5600x4200, got {text!r}"
        ) from None
    if not (0 < w < math.inf and 0 < h < math.inf):
        raise argparse.ArgumentTypeError(f"width and height must be finite and > 0, got {text!r}")
    return h, w


def parse_theta(text: str) -> tuple[float, float]:
    """``"0.3,-0.1"`` to ``(0.3, -0.1)``; each value finite with ``|θ| < 1``."""
    try:
        tx, ty = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be TX,TY, e.g. 0.3,0.1, got {text!r}") from None
    if not all(math.isfinite(v) and abs(v) < 1 for v in (tx, ty)):
        raise argparse.ArgumentTypeError(f"each θ must be finite with |θ| < 1, got {text!r}")
    return tx, ty


def _number(lo: float, *, integer: bool = False, open_lo: bool = False) -> Callable[[str], Any]:
    """An argparse type: a finite number ``>= lo`` (``> lo`` with ``open_lo``)."""
    kind = "an integer" if integer else "a number"
    bound = f"{'>' if open_lo else '>='} {lo:g}"

    def parse(text: str) -> int | float:
        try:
            v = int(text) if integer else float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"must be {kind} {bound}, got {text!r}") from None
        if not math.isfinite(v) or (v <= lo if open_lo else v < lo):
            raise argparse.ArgumentTypeError(f"must be {kind} {bound}, got {text!r}")
        return v

    return parse


positive_int = _number(1, integer=True)
non_negative_int = _number(0, integer=True)
positive_float = _number(0, open_lo=True)
non_negative_float = _number(0)


def _check_memory(size: tuple[int, int], flag: str = "--size") -> None:
    """Refuse a sensor whose pixels alone need more memory than is available, before allocating
    ([`check_memory`][layoutwarp.checks.check_memory], with the flag named)."""
    from .checks import ArgumentError, check_memory

    h, w = size
    try:
        check_memory(size, shown=f"{w}x{h}")
    except ArgumentError as exc:
        raise UsageError(f"argument {flag}: {str(exc).removeprefix('size ')}") from None


# ----------------------------------------------------------------------------------------
# Commands
# ----------------------------------------------------------------------------------------
def _existing_folder(path: str | Path, flag: str) -> Path:
    """A folder that must exist: refused in one line if it is missing or is a file."""
    path = Path(path)
    if path.is_file():
        raise UsageError(f"argument {flag}: must be a folder; {str(path)!r} is a file")
    if not path.is_dir():
        raise UsageError(f"argument {flag}: no such folder {str(path)!r}")
    return path


#: Output folders the running command will create (a failed command removes them if empty).
_NEW_FOLDERS: list[Path] = []


def _out_dir(path: str | Path, flag: str = "--out") -> Path:
    """An output folder that can be created: refused in one line if it is, or lies under, a file."""
    from .files import file_in_the_way

    path = Path(path)
    blocker = file_in_the_way(path)
    if blocker is not None:
        what = "is a file" if blocker == path else f"lies under {str(blocker)!r}, which is a file"
        raise UsageError(f"argument {flag}: must be a folder; {str(path)!r} {what}")
    if not path.exists():
        _NEW_FOLDERS.append(path)
    return path


def _cmd_demo(args: argparse.Namespace) -> int:
    from .experiments.data import samples_dir
    from .experiments.demo import run_demo

    image = Path(args.image) if args.image else samples_dir() / "photos" / "kodim20.png"
    if not image.is_file():
        raise UsageError(f"argument --image: no such file {str(image)!r}")
    _check_memory(args.size)
    _out_dir(args.out)
    numbers = run_demo(image, args.out, args.size, args.theta, args.tol)
    print(f"wrote {args.out}/layouts.png, demo.json and sensor_*.png")
    for name, d in numbers["layouts"].items():
        print(
            f"  {name:22s} method={d['method']:9s} {d['seconds'] * 1e3:7.1f} ms  "
            f"area ratio {d['pixel_area_ratio_max_over_min']:.2f}"
        )
    return 0


def _cmd_doctor(args: argparse.Namespace) -> int:
    from . import doctor, jit

    if args.compile:
        print(f"compiling every group of kernels into {jit.cache_folder()} (once per installation)")
        jit.compile_all(lambda unit, seconds: print(f"  {unit:<16} {seconds:6.1f} s", flush=True))
    print(doctor.report())
    return 0


def _cmd_bench(args: argparse.Namespace) -> int:
    import torch

    from .experiments.bench import main_bench

    if args.image and not Path(args.image).is_file():
        raise UsageError(f"argument --image: no such file {args.image!r}")
    if args.threads:
        torch.set_num_threads(args.threads)
    main_bench(
        args.quick,
        args.json,
        args.plot,
        memory=not args.no_memory,
        with_scaling=not args.no_scaling,
        photo=args.image,
        device=_device(args.device) if args.device else "cpu",
        only=_bench_rows(args.layouts),
        text_path=args.text,
    )
    return 0


def _bench_rows(text: str | None) -> list[str] | None:
    """``--layouts``: comma-separated rows of the benchmark, checked."""
    if text is None:
        return None
    from .experiments.bench import bench_layouts

    names = list(bench_layouts((0.0, 0.0)))
    rows = [t.strip() for t in text.split(",")]
    for r in rows:
        if r not in names:
            raise UsageError(f"argument --layouts: {r!r} is not a row; choose from {', '.join(names)}")
    return rows


def _sensor_options(args: argparse.Namespace, default_tol: float) -> dict:
    sensor: dict[str, Any] = {"method": args.method}
    if args.method == "exact":
        sensor["tol"] = args.tol if args.tol is not None else default_tol
    if args.method in ("montecarlo", "point"):
        sensor["radiance"] = args.radiance
    if args.method == "montecarlo":
        sensor["samples"] = args.samples
    return sensor


def _task_folder(task: Task, args: argparse.Namespace) -> Path:
    """The task's data folder: ``--data``, the bundled samples with ``--quick``, else the task's
    folder under the data root of ``LAYOUTWARP_DATA``."""
    from .experiments.data import DATA_ENV, data_root

    if args.data:
        return _existing_folder(args.data, "--data")
    root = data_root(quick=args.quick)
    if root is None:
        raise UsageError(
            f"no {task.name} data: pass --data DIR (the task's folder), set {DATA_ENV} to a data root "
            f"holding {task.folder}/, or --quick (the bundled samples)"
        )
    folder = root / task.folder
    if not folder.is_dir():
        src = "the bundled samples" if args.quick else f"{DATA_ENV}={root}"
        raise UsageError(f"no {task.name} data at {str(folder)!r} ({src}); pass --data DIR")
    return folder


def _training_flags(task: Task, args: argparse.Namespace) -> dict[str, Any]:
    """The run options every training command (train, study, landscape) reads from its flags."""
    weights = getattr(args, "backbone_weights", None)
    if weights is not None and not Path(weights).is_file():
        raise UsageError(f"argument --backbone-weights: no such file {weights!r}")
    return {
        "freeze_epochs": args.freeze_epochs,
        "theta_lr": args.theta_lr,
        "device": _device(args.device),
        "amp": args.amp,
        "progress": not args.no_progress,
        "task_options": {k: getattr(args, k) for k in task.extra_dests},
        "backbone_weights": getattr(args, "backbone_weights", None),
    }


def _run_options(task: Task, args: argparse.Namespace, defaults: TaskDefaults) -> RunOptions:
    """The training options of ``train`` from the task's defaults and the flags."""
    from .experiments.runs import RunOptions

    sensor = _sensor_options(args, defaults.tol) | _physics_option(task, args)
    return RunOptions.of(defaults, epochs=args.epochs, sensor=sensor, **_training_flags(task, args))


def _physics_option(task: Task, args: argparse.Namespace) -> dict:
    """The ``physics`` sensor option of a training command (the task's images at 1 µm a pixel)."""
    physics = _physics_from_args(args, tuple(float(v) for v in task.image_size))
    return {} if physics is None else {"physics": physics.to_dict()}


def _cmd_train(args: argparse.Namespace) -> int:
    from .experiments.runs import format_summary, run_experiment
    from .experiments.tasks import get_task
    from .experiments.training import init_distributed

    task = get_task(args.task).with_net(getattr(args, "net", None))
    d = task.quick_defaults() if args.quick else task.defaults
    folder = _task_folder(task, args)
    families = tuple(dict.fromkeys(args.family)) if args.family else d.families
    seeds = tuple(range(args.seeds or d.seeds))
    sizes = tuple(dict.fromkeys(args.size)) if args.size else d.sizes
    for size in sizes:
        _check_memory(size)
    out = _out_dir(args.out or f"results/{task.name}")
    if init_distributed()[0] != 0:  # under torchrun rank 0 alone reports and writes; the others train alike
        out = Path(tempfile.mkdtemp(prefix="layoutwarp-rank-"))
        sys.stdout = open(os.devnull, "w")  # for the rest of this process
    options = _run_options(task, args, d)
    sizes_txt = ", ".join(f"{w}x{h}" for h, w in sizes)
    print(
        f"{task.name}: data {folder}, families {', '.join(families)}, sensors {sizes_txt}, "
        f"seeds {list(seeds)}, {options.epochs} epochs"
    )
    if args.quick:
        print(
            f"  --quick: a smoke test on the few bundled {task.name} samples; its scores say that "
            "the pipeline runs, not what a layout is worth (train on the full data for that)"
        )
    result = run_experiment(task, folder, out, families=families, sizes=sizes, seeds=seeds, options=options)
    print(format_summary(task, result["summary"]))
    print(
        f"wrote {out}/results.json (scores in percent), layout.json, layout_*.json, model_*.pt, "
        f"{task.name}_layouts.png, {task.name}_theta.png"
    )
    return 0


def _device(name: str | None) -> str:
    """``--device``: the given torch device, checked, or CUDA when available, else the CPU."""
    import torch

    from .experiments.training import default_device

    if name is None:  # under torchrun each rank takes the GPU of its local rank
        local = os.environ.get("LOCAL_RANK")
        return f"cuda:{local}" if local is not None and torch.cuda.is_available() else default_device()
    from .checks import check_device

    try:
        return str(check_device(name, "argument --device"))
    except ValueError as exc:
        raise UsageError(str(exc)) from None


def _add_run_args(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--device", help="torch device, e.g. cpu, cuda, cuda:1 (default: cuda when available, else cpu)"
    )
    p.add_argument(
        "--amp",
        action="store_true",
        help="mixed precision for the network (float16 on CUDA, bfloat16 on CPU); the sensor stays float32",
    )


def _cmd_study(args: argparse.Namespace) -> int:
    from dataclasses import replace

    from .experiments.data import samples_dir
    from .experiments.study import run_study, ship_study, study_runs, study_table
    from .experiments.tasks import get_task
    from .experiments.training import init_distributed

    task = get_task(args.task).with_net(getattr(args, "net", None))
    folder = _task_folder(task, args)
    out = _out_dir(args.out or f"results/study-{task.name}")
    plan = task.study
    if args.quick:  # the smallest study that exercises every step
        plan = replace(
            plan, uniform_sizes=plan.uniform_sizes[:2], learned_sizes=plan.learned_sizes[:1], seeds=1
        )
        plan = replace(plan, families=tuple(args.family or ("rect", "density")))
    elif args.family:
        plan = replace(plan, families=tuple(dict.fromkeys(args.family)))
    if args.ship:
        if not (out / "runs").is_dir():
            raise UsageError(
                f"no study in {str(out)!r} to ship; run `layoutwarp study {task.name} --out DIR` first"
            )
        samples = samples_dir() / task.folder
        summary = ship_study(
            task,
            out,
            _out_dir(args.ship, "--ship"),
            scene=task.scene(task.load(folder)),
            models=args.weights != "none",
            weights=args.weights,
            samples=samples if samples.is_dir() and args.weights != "none" else None,
            planned=len(study_runs(plan, args.seeds or plan.seeds)),
        )
        print(study_table(summary), end="")
        print(f"shipped {out} to {args.ship}")
        return 0
    for size in plan.uniform_sizes + plan.learned_sizes:
        _check_memory(size)
    init_distributed()
    options = _study_run_options(task, plan, args)
    summary = run_study(task, folder, out, plan=plan, seeds=args.seeds, options=options)
    print(study_table(summary), end="")
    theta = f", theta_{task.name}.png" if (out / f"theta_{task.name}.png").exists() else ""
    print(f"wrote {out}/study.json, study.md, study_{task.name}.png{theta} (scores in percent)")
    return 0


def _study_run_options(task: Task, plan: StudyPlan, args: argparse.Namespace) -> RunOptions:
    """How every run of a study or landscape trains: the plan's tolerance, the task's defaults,
    the flags (``--quick``: one epoch) and the physics flags."""
    from dataclasses import replace

    from .experiments.study import study_options

    epochs = args.epochs or (1 if args.quick else None)
    options = study_options(task, plan, epochs=epochs, **_training_flags(task, args))
    return replace(options, sensor=options.sensor | _physics_option(task, args))


def _cmd_landscape(args: argparse.Namespace) -> int:
    from .experiments.landscape import run_landscape
    from .experiments.tasks import get_task
    from .experiments.training import init_distributed

    task = get_task(args.task).with_net(getattr(args, "net", None))
    folder = _task_folder(task, args)
    size = args.size or task.study.learned_sizes[0]
    _check_memory(size)
    out = _out_dir(args.out or f"results/landscape-{task.name}-{args.family}")
    lo, hi = args.range
    if args.study and not any((Path(args.study) / d).is_dir() for d in ("runs", "layouts")):
        raise UsageError(f"argument --study: no study runs (or shipped layouts) in {args.study!r}")
    init_distributed()
    options = _study_run_options(task, task.study, args)
    n = args.grid or (3 if args.quick else 7)
    summary = run_landscape(
        task, folder, out, family=args.family, size=size, n=n, lo=lo, hi=hi, options=options, study=args.study
    )
    from .experiments.landscape import landscape_table

    print(landscape_table(summary), end="")
    print(f"wrote {out}/landscape.json, landscape.md and landscape_{task.name}_{args.family}.png (percent)")
    return 0


def parse_range(text: str) -> tuple[float, float]:
    """``"-0.8,0.8"`` to ``(-0.8, 0.8)``: finite, ``|θ| < 1``, low below high."""
    try:
        lo, hi = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be LO,HI, e.g. -0.8,0.8, got {text!r}") from None
    if not (all(math.isfinite(v) and abs(v) < 1 for v in (lo, hi)) and lo < hi):
        raise argparse.ArgumentTypeError(f"must have -1 < LO < HI < 1, got {text!r}")
    return lo, hi


def _cmd_evaluate(args: argparse.Namespace) -> int:
    from .experiments.models import evaluate_model, load_model

    _existing_folder(args.data, "--data")
    try:
        model, info = load_model(args.model, args.task, _device(args.device))
    except ValueError as exc:
        raise UsageError(f"argument --model: {exc}") from None
    try:
        scores = evaluate_model(args.task, model, args.data, args.split)
    except (FileNotFoundError, ValueError) as exc:
        raise UsageError(f"argument --data: {exc}") from None
    layout = {k: v for k, v in info["layout"].items() if k in ("family", "theta", "center", "knots", "grid")}
    from .experiments.tasks import get_task

    split = args.split or get_task(args.task).report_split
    if args.task == "faces":
        split = "all"  # a faces folder is scored whole
    out = {"task": args.task, "model": str(args.model), "data": str(args.data), "split": split}
    out |= {"layout": layout, "size_hw": info["size_hw"], "units": "percent", **scores}
    print(json.dumps(out, indent=2))
    return 0


def _layout_from_args(args: argparse.Namespace):
    """The fixed layout and sensor size from ``--layout FILE`` or ``--family/--theta``, and ``--size``."""
    import torch

    from .layoutfile import load_layout
    from .layouts import FAMILIES

    if args.layout and (args.family or args.theta):
        raise UsageError("argument --layout: give a layout file or --family/--theta, not both")
    if args.layout:
        try:
            layout, info = load_layout(args.layout, dtype=torch.float64)
        except ValueError as exc:
            raise UsageError(f"argument --layout: {exc}") from None
        size = args.size or (tuple(info["size_hw"]) if info.get("size_hw") else None)
    elif args.family:
        cls = FAMILIES[args.family]
        if cls.num_params is None:
            raise UsageError(
                f"argument --family: a {args.family!r} layout has more parameters than --theta holds; "
                "give it as --layout FILE (e.g. written by train or save_layout)"
            )
        if cls.num_params and args.theta is None:
            raise UsageError(
                f"argument --family: {args.family!r} needs --theta TX,TY (θ = 0,0 is the uniform layout)"
            )
        if not cls.num_params and args.theta is not None:
            raise UsageError(
                f"argument --theta: the {args.family!r} layout has no parameters, got {args.theta!r}"
            )
        layout, size = cls(args.theta, dtype=torch.float64), args.size
    else:
        raise UsageError("give --layout LAYOUT.json or --family (with --theta)")
    if size is None:
        raise UsageError("argument --size: needed (the layout file stores no sensor size)")
    _check_memory(size)
    return layout, size


def _cmd_preprocess(args: argparse.Namespace) -> int:
    from .experiments.bench import preprocess_baseline
    from .files import atomic_write
    from .preprocess import check_destination, list_images, preprocess_folder

    _existing_folder(args.src, "SRC")
    check_destination(Path(args.dst))
    layout, size = _layout_from_args(args)
    dst = Path(args.dst)
    if args.benchmark and dst.exists() and any(dst.iterdir()):
        raise UsageError(f"argument --benchmark: needs an empty DST, {str(dst)!r} is not empty")
    base = None
    if args.benchmark:  # the baseline first, both on a warm page cache
        files = list_images(args.src, dst)
        for path in files:
            path.read_bytes()
        with tempfile.TemporaryDirectory() as tmp:
            base = preprocess_baseline(files, size, tmp)
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
        engine=args.engine,
        address=args.address,
        device=_device(args.device),
        physics=_physics_from_args(args),
    )
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
    from .export import export_layout, report_json
    from .files import atomic_write, check_file_destination

    check_file_destination(args.out, "out")  # both before any work: nothing written, then refused
    if args.report:
        check_file_destination(args.report, "report")
    layout, size = _layout_from_args(args)
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
        physics=_physics_from_args(args, args.sensor_um),
        progress=False if args.no_progress else None,
    )
    print(report.summary())
    if args.report:
        atomic_write(args.report, report_json(report))
    return 0


# ----------------------------------------------------------------------------------------
# Parser
# ----------------------------------------------------------------------------------------
def _add_physics_args(p: argparse.ArgumentParser, extent: str | None = None) -> None:
    """``--physics FILE`` and the common fields as flags (a flag overrides the file's value)."""
    g = p.add_argument_group(
        "sensor physics", "record as a real sensor would: photons, noise, full well, ADC, optics"
    )
    g.add_argument(
        "--physics",
        metavar="FILE",
        help="a SensorPhysics JSON file (SensorPhysics.to_json); the flags below override its values",
    )
    g.add_argument(
        "--photons-per-um2",
        type=positive_float,
        help="the light: mean photons per µm² where the image is at full scale",
    )
    if extent is None:
        g.add_argument("--sensor-um", type=parse_um, help="the sensor's extent WIDTHxHEIGHT in µm")
    g.add_argument("--read-noise-e", type=non_negative_float, help="read noise in electrons (rms)")
    g.add_argument("--full-well-per-um2", type=positive_float, help="electrons a pixel holds per µm²")
    g.add_argument("--adc-bits", type=positive_int, help="ADC resolution in bits")
    g.add_argument("--psf", choices=["gaussian", "airy"], help="the optics' point spread function")
    g.add_argument("--f-number", type=positive_float, help="the optics' f-number (with --psf)")
    g.add_argument("--noise-seed", type=non_negative_int, help="seed of the temporal noise")


#: Physics flags and the SensorPhysics fields they set.
PHYSICS_FLAGS = {
    "photons_per_um2": "photons_per_um2",
    "sensor_um": "sensor_um",
    "read_noise_e": "read_noise_e",
    "full_well_per_um2": "full_well_per_um2",
    "adc_bits": "adc_bits",
    "psf": "psf",
    "f_number": "f_number",
    "noise_seed": "seed",
}


def _physics_from_args(args: argparse.Namespace, extent: tuple[float, float] | None = None):
    """The [`SensorPhysics`][layoutwarp.physics.SensorPhysics] of ``--physics FILE`` and the physics flags, or
    ``None`` when none is given. ``extent``: the sensor extent when no flag or file sets one.
    A flag overrides the file's value, and the values are checked once merged, so a file may
    leave out what the flags give; an error names the flag, or the file, that set the value."""
    from .physics import SensorPhysics

    values: dict[str, Any] = {}
    source = f"--physics: {args.physics}"
    if args.physics:
        try:
            values = json.loads(Path(args.physics).read_text())
        except (OSError, json.JSONDecodeError) as exc:
            raise UsageError(f"argument {source}: {exc}") from None
        if not isinstance(values, dict):
            raise UsageError(f"argument {source}: must hold a JSON object, got {type(values).__name__}")
    flags = {
        field: ("--" + dest.replace("_", "-"), getattr(args, dest))
        for dest, field in PHYSICS_FLAGS.items()
        if getattr(args, dest, None) is not None
    }
    if not values and not set(flags) - {"sensor_um"}:  # an extent alone (export's own) asks for no physics
        return None
    values |= {field: value for field, (_, value) in flags.items()}
    if "sensor_um" not in values and extent is not None:
        values["sensor_um"] = extent
    for field, flag in (("photons_per_um2", "--photons-per-um2"), ("sensor_um", "--sensor-um")):
        if field not in values:
            raise UsageError(f"argument {flag}: needed for sensor physics (or give it in --physics FILE)")
    try:
        return SensorPhysics.from_dict(values)
    except ValueError as exc:
        field = getattr(exc, "argument", None)
        where = flags[field][0] if field in flags else source if args.physics else None
        raise UsageError(f"argument {where}: {exc}" if where else f"sensor physics: {exc}") from None


def _add_layout_args(p: argparse.ArgumentParser, families: Sequence[str]) -> None:
    p.add_argument("--layout", metavar="FILE", help="layout file (written by save_layout or train)")
    p.add_argument("--family", choices=families, help="or a layout family (with --theta)")
    p.add_argument("--theta", type=parse_theta, help="θ as TX,TY with --family, each |θ| < 1")
    p.add_argument("--size", type=parse_wxh, help="sensor WIDTHxHEIGHT (default: the layout file's)")


def _extent_text(task: TaskSpec) -> str:
    h, w = task.image_size
    return f"{w}x{h} µm"


def _sizes_text(sizes) -> str:
    return " and ".join(f"{w}x{h}" for h, w in sizes)


def _add_training_args(p: argparse.ArgumentParser, task: TaskSpec, quick_help: str) -> None:
    """The options every training command of every task takes, and the task's own."""
    d, q = task.defaults, task.quick_defaults()
    p.add_argument("--quick", action="store_true", help=quick_help)
    p.add_argument(
        "--data",
        metavar="DIR",
        help=f"the task's data folder (default: $LAYOUTWARP_DATA/{task.folder}; "
        "the bundled samples with --quick)",
    )
    p.add_argument("--seeds", type=positive_int, help=f"number of seeds (default: {d.seeds}; 1 with --quick)")
    p.add_argument(
        "--epochs", type=positive_int, help=f"epochs (default: {d.epochs}; {q.epochs} with --quick)"
    )
    p.add_argument(
        "--freeze-epochs",
        type=non_negative_int,
        help=f"epochs with θ frozen at the start (default: {d.freeze_epochs}; 0 with --quick)",
    )
    p.add_argument("--theta-lr", type=positive_float, help=f"θ's own learning rate (default: {d.theta_lr:g})")
    if task.nets:
        p.add_argument(
            "--net",
            choices=list(task.nets),
            help=f"the network, with its training protocol's defaults (default: {task.net})",
        )
        p.add_argument(
            "--backbone-weights",
            metavar="FILE",
            help="a torchvision-format ResNet state dict (e.g. ImageNet weights you downloaded) the "
            "network's backbone starts from (networks with a ResNet backbone; nothing is downloaded)",
        )
    task.add_arguments(p)
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    _add_run_args(p)
    _add_physics_args(p, extent=f"the task's images at 1 µm a source pixel ({_extent_text(task)})")


def _add_train_parser(sub: argparse._SubParsersAction, task: TaskSpec, families: Sequence[str]) -> None:
    d = task.defaults
    t = sub.add_parser(
        task.name,
        help=task.description,
        description=f"{task.description}: train layouts jointly with the network and compare them "
        "with the uniform baseline.",
        formatter_class=_Formatter,
    )
    _add_training_args(t, task, "smoke test on the bundled samples: 1 seed, the first size, few epochs")
    t.add_argument(
        "--family",
        action="append",
        choices=families,
        help=f"a family to train, repeatable (default: {', '.join(d.families)})",
    )
    t.add_argument(
        "--size",
        type=parse_wxh,
        action="append",
        help=f"sensor WIDTHxHEIGHT, repeatable (default: {_sizes_text(d.sizes)}; the first with --quick)",
    )
    t.add_argument(
        "--method", default="exact", choices=["exact", "montecarlo", "point"], help="sensor integrator"
    )
    t.add_argument(
        "--tol",
        type=positive_float,
        help=f"the exact integrator's curved-edge tolerance (default: {d.tol:g})",
    )
    t.add_argument(
        "--samples", type=positive_int, default=4, help="Monte Carlo samples per axis (s² per pixel)"
    )
    t.add_argument(
        "--radiance",
        default="bilinear",
        choices=["bilinear", "box"],
        help="radiance of the sampling integrators",
    )
    t.add_argument("--out", help=f"output folder (default: results/{task.name})")
    t.set_defaults(func=_cmd_train, task=task.name)


def _add_study_parser(sub: argparse._SubParsersAction, task: TaskSpec, families: Sequence[str]) -> None:
    plan = task.study
    st = sub.add_parser(
        task.name,
        help=task.description,
        description=f"The {task.name} pixel-budget study: uniform layouts at "
        f"{_sizes_text(plan.uniform_sizes)}, every family at {_sizes_text(plan.learned_sizes)}; resumable.",
        formatter_class=_Formatter,
    )
    _add_training_args(st, task, "bundled samples, 1 seed, 1 epoch, 2 uniform sizes and 1 learned size")
    st.add_argument(
        "--family",
        action="append",
        choices=[*families, "density"],
        help=f"families besides uniform, repeatable (default: {', '.join(plan.families)})",
    )
    st.add_argument("--out", help=f"output folder (default: results/study-{task.name}); rerun to resume")
    st.add_argument(
        "--ship",
        metavar="DIR",
        help="train nothing: summarise the runs in --out so far and copy the results, learned layouts, "
        "the best models and a figure of the layouts to DIR",
    )
    st.add_argument(
        "--weights",
        choices=["float32", "float16", "int8", "none"],
        default="float16",
        help="with --ship: the precision of the shipped models' weights (int8: conv and linear "
        "weights at 255 levels per output channel; none: no models, e.g. PSPNet's 49 M parameters)",
    )
    st.set_defaults(func=_cmd_study, task=task.name)


def _catalogues() -> tuple[dict[str, TaskSpec], list[str], list[str]]:
    """The tasks' protocols, the families and the two-parameter families the parser lists: the
    built-in ones from torch-free modules, and, in a process that has loaded the registries, any a
    user registered there (without loading them)."""
    from .catalog import BUILTIN_FAMILIES, TWO_PARAMETER_FAMILIES
    from .experiments.protocols import SPECS

    specs, families, two = dict(SPECS), list(BUILTIN_FAMILIES), list(TWO_PARAMETER_FAMILIES)
    layouts = sys.modules.get(f"{__package__}.layouts")
    if layouts is not None:
        for name, cls in layouts.FAMILIES.items():
            if name not in families:
                families.append(name)
                if cls.num_params == 2:
                    two.append(name)
    tasks = sys.modules.get(f"{__package__}.experiments.tasks")
    if tasks is not None:
        specs |= {name: task.spec for name, task in tasks.TASKS.items() if name not in specs}
    return specs, families, two


def build_parser() -> argparse.ArgumentParser:
    """The ``layoutwarp`` argument parser. It imports nothing heavy (the tasks and families it
    lists come from torch-free modules), so help and argument errors answer at once."""
    from .version import __version__

    specs, families, two = _catalogues()
    p = _Parser(
        prog="layoutwarp",
        description="Differentiable sensor pixel layouts: simulate, learn and export task-specific sensors.",
        formatter_class=_Formatter,
    )
    p.add_argument("--version", action="version", version=f"layoutwarp {__version__}")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND", parser_class=_Parser)

    def command(name: str, summary: str) -> argparse.ArgumentParser:
        return sub.add_parser(name, help=summary, description=summary, formatter_class=_Formatter)

    d = command("demo", "Simulate the layout families on a photo and write figures and numbers.")
    d.add_argument("--image", help="an image file (default: the bundled kodim20 photo)")
    d.add_argument("--size", type=parse_wxh, default="32x24", help="sensor WIDTHxHEIGHT")
    d.add_argument("--theta", type=parse_theta, default="0.5,0.5", help="θ as TX,TY")
    d.add_argument(
        "--tol",
        type=positive_float,
        help="bound on each pixel's error relative to the value range (default: what 8-bit data needs)",
    )
    d.add_argument("--out", default="results/demo", help="output folder")
    d.set_defaults(func=_cmd_demo)

    dr = command("doctor", "Versions, which backend each path runs here and why, and the compiled kernels.")
    dr.add_argument(
        "--compile",
        action="store_true",
        help="compile every group of kernels now, in the foreground (e.g. when building a container image)",
    )
    dr.set_defaults(func=_cmd_doctor)

    b = command("bench", "Time and error of every integrator against anchors measured in the same run.")
    b.add_argument("--quick", action="store_true", help="small sizes, few repeats")
    b.add_argument("--json", metavar="FILE", help="also write the results to this JSON file")
    b.add_argument("--text", metavar="FILE", help="also write the printed tables to this file (Markdown)")
    b.add_argument("--plot", metavar="FILE", help="also draw the speed-vs-error plot to this PNG")
    b.add_argument("--image", help="photo to measure on (default: the bundled kodim20)")
    b.add_argument("--threads", type=positive_int, help="torch threads (default: torch's choice)")
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

    st = command(
        "study", "The pixel-budget study: uniform layouts at several sizes, every family at some; resumable."
    )
    st_tasks = st.add_subparsers(dest="task", required=True, metavar="TASK", parser_class=_Parser)
    for task in specs.values():
        _add_study_parser(st_tasks, task, families)

    la = command(
        "landscape",
        "Train the task's network with θ frozen at every point of a grid: does learning find the best θ?",
    )
    la_tasks = la.add_subparsers(dest="task", required=True, metavar="TASK", parser_class=_Parser)
    for task in specs.values():
        lt = la_tasks.add_parser(
            task.name,
            help=task.description,
            description=f"A θ-landscape of {task.name}: θ frozen on an N x N grid (one seed a point, "
            "three at uniform and at the best point), the study's training; resumable.",
            formatter_class=_Formatter,
        )
        _add_training_args(lt, task, "bundled samples, 1 epoch, a 3x3 grid")
        lt.add_argument("--family", choices=two, required=True, help="a two-parameter family")
        lt.add_argument("--grid", type=positive_int, help="N: the grid is N x N (default: 7; 3 with --quick)")
        lt.add_argument(
            "--range",
            type=parse_range,
            default="-0.8,0.8",
            help="θ range LO,HI on both axes",
        )
        sizes = _sizes_text(task.study.learned_sizes[:1])
        lt.add_argument("--size", type=parse_wxh, help=f"sensor WIDTHxHEIGHT (default: {sizes})")
        lt.add_argument(
            "--study", metavar="DIR", help="a study folder whose learned θ are rerun frozen and marked"
        )
        lt.add_argument(
            "--out", help=f"output folder (default: results/landscape-{task.name}-FAMILY); rerun to resume"
        )
        lt.set_defaults(func=_cmd_landscape, task=task.name)

    ev = command("evaluate", "Score a saved model (a train run's model_*.pt) on a data folder; print JSON.")
    ev.add_argument("task", choices=list(specs), metavar="TASK", help=", ".join(specs))
    ev.add_argument("--model", required=True, metavar="FILE", help="a model file written by train")
    ev.add_argument(
        "--data",
        required=True,
        metavar="DIR",
        help="a folder laid out like the training data (MNIST: IDX files; CamVid: NAME/ and NAMEannot/; "
        "faces: images and labels.csv; Cityscapes: leftImg8bit/ and gtFine/; CelebA: img_align_celeba/ "
        "and its two lists)",
    )
    ev.add_argument(
        "--split",
        help="MNIST: test or train (default: test); CamVid: NAME (default: val); Cityscapes: train or val "
        "(default: val); CelebA: train, val or test (default: test)",
    )
    _add_run_args(ev)
    ev.set_defaults(func=_cmd_evaluate)

    pp = command("preprocess", "Write the sensor image of every image in a folder (and move its label maps).")
    pp.add_argument("src", metavar="SRC", help="source folder (walked recursively)")
    pp.add_argument("dst", metavar="DST", help="destination folder (same relative paths)")
    _add_layout_args(pp, families)
    pp.add_argument("--labels", metavar="DIR", help="folder of class-index label maps (same relative paths)")
    pp.add_argument(
        "--label-rule",
        choices=["nearest", "majority", "inverse"],
        default="nearest",
        help="labels to the sensor grid by the label under each pixel centre (nearest) or the "
        "largest area (majority), or kept full size with back-warp maps (inverse)",
    )
    pp.add_argument(
        "--workers",
        type=positive_int,
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
    _add_physics_args(pp)
    pp.set_defaults(func=_cmd_preprocess)

    ex = command("export", "Write a layout's pixel boundaries as a fabrication mask (GDSII, DXF, SVG, PNG).")
    _add_layout_args(ex, families)
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
        "--gds-layer", type=non_negative_int, default=1, help="GDSII layer (DXF layer PIXELS_<n>)"
    )
    ex.add_argument("--gds-datatype", type=non_negative_int, default=0, help="GDSII datatype")
    ex.add_argument(
        "--px-per-um", type=positive_float, help="PNG resolution (default: 4096 px on the long side)"
    )
    ex.add_argument(
        "--line-width", type=positive_int, default=1, help="PNG boundary line width in raster pixels"
    )
    ex.add_argument("--min-feature-um", type=positive_float, help="warn below this pitch (µm)")
    ex.add_argument("--report", metavar="FILE", help="also write the report as JSON to this file")
    ex.add_argument("--no-progress", action="store_true", help="no progress bars (drawn for large sensors)")
    _add_physics_args(ex, extent="--sensor-um")
    ex.set_defaults(func=_cmd_export)

    t = command("train", "Train a layout jointly with a network: the paper's experiments.")
    tasks = t.add_subparsers(dest="task", required=True, metavar="TASK", parser_class=_Parser)
    for task in specs.values():
        _add_train_parser(tasks, task, families)
    return p


def join_negative_values(argv: Sequence[str]) -> list[str]:
    """``--flag -0.5,0.5`` as ``--flag=-0.5,0.5``: a value that starts with a minus and a digit is
    the flag's value, not a flag (argparse takes only plain negative numbers so, and read
    ``--theta -0.5,0.5`` or ``--size -4x4`` as a missing value)."""
    out: list[str] = []
    i = 0
    while i < len(argv):
        arg = argv[i]
        if arg.startswith("--") and "=" not in arg and i + 1 < len(argv) and _NEGATIVE.match(argv[i + 1]):
            out.append(f"{arg}={argv[i + 1]}")
            i += 2
        else:
            out.append(arg)
            i += 1
    return out


_NEGATIVE = re.compile(r"^-\.?\d")


def main(argv: Sequence[str] | None = None, *, own_process: bool = False) -> int:
    """Run the command line; returns the exit status. ``own_process``: the process is the
    command's alone, and its allocator keeps freed memory for the next training step
    ([`retain_freed_memory`][layoutwarp.kernels.retain_freed_memory])."""
    argv = join_negative_values(sys.argv[1:] if argv is None else argv)
    args = build_parser().parse_args(argv)
    if own_process:
        from .kernels import retain_freed_memory

        retain_freed_memory()
        warnings.formatwarning = _one_line_warning
    prog = f"layoutwarp {args.command}" + (
        f" {args.task}" if args.command in ("train", "study", "landscape") else ""
    )
    _NEW_FOLDERS.clear()
    status = 1  # what an unexpected exception leaves
    try:
        status = int(args.func(args) or 0)
    except (UsageError, ValueError, FileNotFoundError) as exc:
        print(f"{prog}: error: {_name_the_flag(exc)}", file=sys.stderr)
        status = 2
    finally:
        if status != 0:  # a failed command leaves no empty output folder of its own behind
            for folder in reversed(_NEW_FOLDERS):
                with contextlib.suppress(OSError):  # kept if anything was written there
                    folder.rmdir()
    return status


def _one_line_warning(message: Warning | str, category: type[Warning], *args: Any, **kwargs: Any) -> str:
    """A warning on the command line: one line, no source location."""
    return f"layoutwarp: warning: {message}\n"


def run() -> None:
    """The ``layoutwarp`` command (and ``python -m layoutwarp``): [`main`][] in a process of
    its own. Output cut short by its reader (``| head``) ends the command quietly."""
    try:
        status = main(own_process=True)
        sys.stdout.flush()
    except BrokenPipeError:
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # no second error at exit
        status = 141  # as a shell reports a command ended by SIGPIPE
    sys.exit(status)


def _name_the_flag(exc: Exception) -> str:
    """A library error about an argument ([`ArgumentError`][layoutwarp.checks.ArgumentError]) prefixed
    with the flag that sets it; any other error's message as it is."""
    from .checks import ArgumentError

    flag = FLAGS.get(exc.argument) if isinstance(exc, ArgumentError) else None
    return f"argument {flag}: {exc}" if flag else str(exc)


if __name__ == "__main__":  # pragma: no cover
    run()
