"""The training commands: ``layoutwarp train``, ``study``, ``landscape`` and ``evaluate``."""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import tempfile
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from .common import (
    Formatter,
    Parser,
    UsageError,
    add_command,
    add_physics_args,
    add_run_args,
    check_sensor_memory,
    existing_folder,
    int_range,
    non_negative_int,
    not_within,
    out_dir,
    parse_range,
    parse_wxh,
    physics_from_args,
    pick_device,
    positive_float,
    positive_int,
)

if TYPE_CHECKING:  # the experiments load on demand
    from ..experiments.protocols import StudyPlan, TaskDefaults, TaskSpec
    from ..experiments.runs import RunOptions
    from ..experiments.tasks import Task

__all__ = ["add_commands"]

#: The epochs of every run of a ``study`` or ``landscape`` with ``--quick``.
QUICK_STUDY_EPOCHS = 1


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
    from ..experiments.data import DATA_ENV, data_root

    if args.data:
        return existing_folder(args.data, "--data")
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
        "device": pick_device(args.device),
        "amp": args.amp,
        "progress": not args.no_progress,
        "task_options": {k: getattr(args, k) for k in task.extra_dests},
        "backbone_weights": getattr(args, "backbone_weights", None),
    }


def _run_options(task: Task, args: argparse.Namespace, defaults: TaskDefaults) -> RunOptions:
    """The training options of ``train`` from the task's defaults and the flags."""
    from ..experiments.runs import RunOptions

    sensor = _sensor_options(args, defaults.tol) | _physics_option(task, args)
    return _checked(
        RunOptions.of(defaults, epochs=args.epochs, sensor=sensor, **_training_flags(task, args)), args
    )


def _checked(options: RunOptions, args: argparse.Namespace) -> RunOptions:
    """Refuse flags that would quietly train something else than asked (a task's own defaults
    are its protocol's: a short run freezes θ for what it has)."""
    if args.freeze_epochs is not None and 0 < options.epochs <= options.freeze_epochs:
        raise UsageError(
            f"argument --freeze-epochs: {options.freeze_epochs} would freeze θ for all {options.epochs} "
            "epochs; give fewer than --epochs"
        )
    return options


@contextlib.contextmanager
def _data_errors() -> Iterator[None]:
    """Within: a data file the task cannot find is the ``--data`` folder's error, and a learned θ
    that a step made no layout (`Layout.check_theta_now`) ``--theta-lr``'s, each in one line."""
    from ..checks import ArgumentError

    try:
        yield
    except FileNotFoundError as exc:
        raise UsageError(f"argument --data: {exc}") from None
    except ArgumentError as exc:
        if exc.argument != "theta":
            raise
        raise UsageError(
            f"argument --theta-lr: training diverged: {exc}; lower --theta-lr (or --lr)"
        ) from None


def _physics_option(task: Task, args: argparse.Namespace) -> dict:
    """The ``physics`` sensor option of a training command (the task's images at 1 µm a pixel)."""
    physics = physics_from_args(args, tuple(float(v) for v in task.image_size))
    return {} if physics is None else {"physics": physics.to_dict()}


def _cmd_train(args: argparse.Namespace) -> int:
    from ..experiments.tasks import get_task
    from ..experiments.training import init_distributed

    task = get_task(args.task).with_net(getattr(args, "net", None))
    d = task.quick_defaults() if args.quick else task.defaults
    folder = _task_folder(task, args)
    families = tuple(dict.fromkeys(args.family)) if args.family else d.families
    seeds = tuple(range(args.seeds or d.seeds))
    sizes = tuple(dict.fromkeys(args.size)) if args.size else d.sizes
    for size in sizes:
        check_sensor_memory(size)
    out = out_dir(args.out or f"results/{task.name}")
    with _rank_zero_writes(out, init_distributed()[0]) as out:
        options = _run_options(task, args, d)
        return _train(task, folder, out, families, sizes, seeds, options, args.quick)


@contextlib.contextmanager
def _rank_zero_writes(out: Path, rank: int) -> Iterator[Path]:
    """``out`` on rank 0 (a single process is rank 0). Under ``torchrun`` rank 0 alone reports and
    writes; every other rank trains alike into a temporary folder, removed when its command ends
    (also on an error), with its printing silenced."""
    if rank == 0:
        yield out
        return
    with tempfile.TemporaryDirectory(prefix="layoutwarp-rank-") as scratch, _rank_zero_prints(rank):
        yield Path(scratch)


@contextlib.contextmanager
def _rank_zero_prints(rank: int) -> Iterator[None]:
    """Within: this process prints its report only on rank 0 (a single process is rank 0); the
    other ranks of a ``torchrun`` print nothing to stdout (their errors still go to stderr)."""
    if rank == 0:
        yield
        return
    with open(os.devnull, "w") as null, contextlib.redirect_stdout(null):
        yield


def _train(
    task: Task,
    folder: Path,
    out: Path,
    families: tuple[str, ...],
    sizes: tuple[tuple[int, int], ...],
    seeds: tuple[int, ...],
    options: RunOptions,
    quick: bool,
) -> int:
    """``layoutwarp train``'s runs into ``out``, with its report."""
    from ..experiments.runs import format_summary, run_experiment

    sizes_txt = ", ".join(f"{w}x{h}" for h, w in sizes)
    print(
        f"{task.name}: data {folder}, families {', '.join(families)}, sensors {sizes_txt}, "
        f"seeds {list(seeds)}, {options.epochs} epochs"
    )
    if quick:
        print(
            f"  --quick: a smoke test on the few bundled {task.name} samples; its scores say that "
            "the pipeline runs, not what a layout is worth (train on the full data for that)"
        )
    with _data_errors():
        result = run_experiment(
            task, folder, out, families=families, sizes=sizes, seeds=seeds, options=options
        )
    print(format_summary(task, result["summary"]))
    learned = any(f not in ("uniform", "density") for f in families)  # the best of them: layout.json
    print(
        f"wrote {out}/results.json (scores in percent), {'layout.json, ' if learned else ''}layout_*.json, "
        f"model_*.pt, {task.name}_layouts.png, {task.name}_theta.png"
    )
    return 0


def _cmd_study(args: argparse.Namespace) -> int:
    from dataclasses import replace

    from ..experiments.data import samples_dir
    from ..experiments.study import run_study, ship_study, study_runs, study_table
    from ..experiments.tasks import get_task
    from ..experiments.training import init_distributed

    task = get_task(args.task).with_net(getattr(args, "net", None))
    folder = _task_folder(task, args)
    out = out_dir(args.out or f"results/study-{task.name}")
    plan = task.study
    if args.quick:  # the smallest study that exercises every step
        plan = replace(
            plan, uniform_sizes=plan.uniform_sizes[:2], learned_sizes=plan.learned_sizes[:1], seeds=1
        )
        plan = replace(plan, families=tuple(args.family or ("rect", "density")))
    elif args.family:
        plan = replace(plan, families=tuple(dict.fromkeys(args.family)))
    if args.size:  # the learned sizes, each also on the uniform curve (which keeps its own)
        sizes = tuple(dict.fromkeys(args.size))
        uniform = sorted(set(plan.uniform_sizes) | set(sizes), key=lambda hw: (hw[0] * hw[1], hw))
        plan = replace(plan, learned_sizes=sizes, uniform_sizes=tuple(uniform))
    if args.weights is not None and not args.ship:
        raise UsageError(
            f"argument --weights: the shipped models' precision needs --ship DIR, got {args.weights!r}"
        )
    if args.ship:
        if not (out / "runs").is_dir():
            raise UsageError(
                f"argument --ship: no study in {str(out)!r} to ship; "
                f"run `layoutwarp study {task.name} --out DIR` first"
            )
        not_within(args.ship, "--ship", out, "--out (the study's own folder)")
        weights = args.weights or "float16"
        samples = samples_dir() / task.folder
        summary = ship_study(
            task,
            out,
            out_dir(args.ship, "--ship"),
            scene=task.scene(task.load(folder)),
            models=weights != "none",
            weights=weights,
            samples=samples if samples.is_dir() and weights != "none" else None,
            planned=len(study_runs(plan, args.seeds or plan.seeds)),
        )
        print(study_table(summary), end="")
        print(f"shipped {out} to {args.ship}")
        return 0
    for size in plan.uniform_sizes + plan.learned_sizes:
        check_sensor_memory(size)
    # under torchrun every rank trains and writes the same records (atomically, the same bytes
    # but for a run's time): a resumed run's checkpoint is where each rank looks for it
    with _rank_zero_prints(init_distributed()[0]):
        options = _study_run_options(task, plan, args)
        with _data_errors():
            summary = run_study(task, folder, out, plan=plan, seeds=args.seeds, options=options)
        print(study_table(summary), end="")
        theta = f", theta_{task.name}.png" if (out / f"theta_{task.name}.png").exists() else ""
        print(f"wrote {out}/study.json, study.md, study_{task.name}.png{theta} (scores in percent)")
    return 0


def _study_run_options(task: Task, plan: StudyPlan, args: argparse.Namespace) -> RunOptions:
    """How every run of a study or landscape trains: the plan's tolerance, the task's defaults,
    the flags (``--quick``: one epoch) and the physics flags."""
    from dataclasses import replace

    from ..experiments.study import study_options

    epochs = args.epochs or (QUICK_STUDY_EPOCHS if args.quick else None)
    options = study_options(task, plan, epochs=epochs, **_training_flags(task, args))
    return _checked(replace(options, sensor=options.sensor | _physics_option(task, args)), args)


def _cmd_landscape(args: argparse.Namespace) -> int:
    from ..experiments.landscape import run_landscape
    from ..experiments.tasks import get_task
    from ..experiments.training import init_distributed

    task = get_task(args.task).with_net(getattr(args, "net", None))
    folder = _task_folder(task, args)
    size = args.size or task.study.learned_sizes[0]
    check_sensor_memory(size)
    out = out_dir(args.out or f"results/landscape-{task.name}-{args.family}")
    lo, hi = args.range
    if args.study and not any((Path(args.study) / d).is_dir() for d in ("runs", "layouts")):
        raise UsageError(f"argument --study: no study runs (or shipped layouts) in {args.study!r}")
    if args.study:
        not_within(out, "--out", args.study, "--study")
    from ..experiments.landscape import landscape_table

    with _rank_zero_prints(init_distributed()[0]):  # every rank writes, as a study's do
        options = _study_run_options(task, task.study, args)
        n = args.grid or (3 if args.quick else 7)
        with _data_errors():
            summary = run_landscape(
                task, folder, out, family=args.family, size=size, n=n, lo=lo, hi=hi, options=options,
                study=args.study, repeats=args.seeds or 3,
            )  # fmt: skip
        print(landscape_table(summary), end="")
        figure = f"landscape_{task.name}_{args.family}.png"
        print(f"wrote {out}/landscape.json, landscape.md and {figure} (percent)")
    return 0


def _cmd_evaluate(args: argparse.Namespace) -> int:
    from ..experiments.models import evaluate_model, load_model

    existing_folder(args.data, "--data")
    try:
        model, info = load_model(args.model, args.task, pick_device(args.device))
    except ValueError as exc:
        raise UsageError(f"argument --model: {exc}") from None
    try:
        scores = evaluate_model(args.task, model, args.data, args.split)
    except (FileNotFoundError, ValueError) as exc:  # a bad split is named as such, else the data
        flag = "--split" if args.split is not None and "split" in str(exc) else "--data"
        raise UsageError(f"argument {flag}: {exc}") from None
    layout = {k: v for k, v in info["layout"].items() if k in ("family", "theta", "center", "knots", "grid")}
    from ..experiments.tasks import get_task

    split = args.split or get_task(args.task).report_split
    if args.task == "faces":
        split = "all"  # a faces folder is scored whole
    out = {"task": args.task, "model": str(args.model), "data": str(args.data), "split": split}
    out |= {"layout": layout, "size_hw": info["size_hw"], "units": "percent", **scores}
    print(json.dumps(out, indent=2))
    return 0


def _extent_text(task: TaskSpec) -> str:
    h, w = task.image_size
    return f"{w}x{h} µm"


def _sizes_text(sizes) -> str:
    return " and ".join(f"{w}x{h}" for h, w in sizes)


def _add_training_args(
    p: argparse.ArgumentParser, task: TaskSpec, quick_help: str, quick_epochs: int | None = None
) -> None:
    """The options every training command of every task takes, and the task's own
    (``quick_epochs``: the epochs ``--quick`` trains, where not the task's quick default)."""
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
        "--epochs",
        type=positive_int,
        help=f"epochs (default: {d.epochs}; {quick_epochs or q.epochs} with --quick)",
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
    add_run_args(p)
    add_physics_args(p, extent=f"the task's images at 1 µm a source pixel ({_extent_text(task)})")


def _task_parser(
    sub: argparse._SubParsersAction,
    task: TaskSpec,
    description: str,
    quick_help: str,
    quick_epochs: int | None = None,
) -> argparse.ArgumentParser:
    """A task's parser under a command, with the training arguments every command shares."""
    p = sub.add_parser(task.name, help=task.description, description=description, formatter_class=Formatter)
    _add_training_args(p, task, quick_help, quick_epochs)
    return p


def _add_families_and_sizes(
    p: argparse.ArgumentParser, families: Sequence[str], family_help: str, size_help: str
) -> None:
    """The repeatable ``--family`` (one of ``families``) and ``--size`` of ``train`` and ``study``."""
    p.add_argument("--family", action="append", choices=families, help=family_help)
    p.add_argument("--size", type=parse_wxh, action="append", help=size_help)


def _add_train_parser(sub: argparse._SubParsersAction, task: TaskSpec, families: Sequence[str]) -> None:
    d = task.defaults
    t = _task_parser(
        sub,
        task,
        f"{task.description}: train layouts jointly with the network and compare them "
        "with the uniform baseline.",
        "smoke test on the bundled samples: 1 seed, the first size, few epochs",
    )
    _add_families_and_sizes(
        t,
        families,
        f"a family to train, repeatable (default: {', '.join(d.families)})",
        f"sensor WIDTHxHEIGHT, repeatable (default: {_sizes_text(d.sizes)}; the first with --quick)",
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
    st = _task_parser(
        sub,
        task,
        f"The {task.name} pixel-budget study: uniform layouts at "
        f"{_sizes_text(plan.uniform_sizes)}, every family at {_sizes_text(plan.learned_sizes)}; resumable.",
        f"bundled samples, 1 seed, {QUICK_STUDY_EPOCHS} epoch, 2 uniform sizes, 1 learned size, "
        "families rect and density (or --family)",
        quick_epochs=QUICK_STUDY_EPOCHS,
    )
    _add_families_and_sizes(
        st,
        [*families, "density"],
        f"families besides uniform, repeatable (default: {', '.join(plan.families)})",
        f"a sensor WIDTHxHEIGHT where every family is trained, repeatable; the uniform curve gains "
        f"it (default: {_sizes_text(plan.learned_sizes)}; the first with --quick)",
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
        help="with --ship: the precision of the shipped models' weights (default: float16; int8: conv and "
        "linear weights at 255 levels per output channel; none: no models, e.g. PSPNet's 49 M parameters)",
    )
    st.set_defaults(func=_cmd_study, task=task.name)


def _add_landscape_parser(sub: argparse._SubParsersAction, task: TaskSpec, two: Sequence[str]) -> None:
    lt = _task_parser(
        sub,
        task,
        f"A θ-landscape of {task.name}: θ frozen on an N x N grid (one seed a point, "
        "three at uniform and at the best point), the study's training; resumable.",
        f"bundled samples, {QUICK_STUDY_EPOCHS} epoch, a 3x3 grid",
        quick_epochs=QUICK_STUDY_EPOCHS,
    )
    lt.add_argument("--family", choices=two, required=True, help="a two-parameter family")
    for action in lt._actions:  # its seeds are those at θ = 0 and at the best point alone
        if "--seeds" in action.option_strings:
            action.help = "seeds at θ = 0 and at the best grid point, each other point one (default: 3)"
    lt.add_argument(
        "--grid", type=int_range(2, 25), help="N: the grid is N x N, 2 to 25 (default: 7; 3 with --quick)"
    )
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


def add_commands(
    sub: argparse._SubParsersAction, specs: dict[str, TaskSpec], families: Sequence[str], two: Sequence[str]
) -> None:
    """The ``train``, ``study``, ``landscape`` and ``evaluate`` commands' parsers, a subcommand a task."""
    per_task = (
        ("train", "Train a layout jointly with a network: the paper's experiments.",
         _add_train_parser, families),
        ("study", "The pixel-budget study: uniform layouts at several sizes, every family at some; "
         "resumable.", _add_study_parser, families),
        ("landscape", "Train the task's network with θ frozen at every point of a grid: does learning "
         "find the best θ?", _add_landscape_parser, two),
    )  # fmt: skip
    for name, text, add, names in per_task:
        tasks = add_command(sub, name, text).add_subparsers(
            dest="task", required=True, metavar="TASK", parser_class=Parser
        )
        for task in specs.values():
            add(tasks, task, names)

    ev = add_command(
        sub, "evaluate", "Score a saved model (a train run's model_*.pt) on a data folder; print JSON."
    )
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
    add_run_args(ev)
    ev.set_defaults(func=_cmd_evaluate)
