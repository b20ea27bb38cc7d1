"""Training runs: one run of a task, its record, and the experiment loop over many.

Every task trains through [`train_run`][] (the study and the landscape too), records a run
as a [`RunRecord`][] and writes one results format ([`RESULTS_FORMAT`][]), so a number
printed by ``train``, ``study`` or ``landscape`` means the same thing everywhere.
"""

from __future__ import annotations

import contextlib
import json
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from ..checks import ArgumentError
from ..doctor import RANK_SEEDS, run_info, world
from ..files import atomic_write
from ..layoutfile import save_layout
from ..layouts import Layout
from ..mesh import pixel_mesh
from .models import save_model
from .protocols import TaskDefaults
from .tasks import Task, TaskData
from .training import fit, format_theta, optimizer, schedule

__all__ = [
    "AREA_RATIO_TOL",
    "RESULTS_FORMAT",
    "RESUMABLE",
    "RunOptions",
    "RunRecord",
    "check_resumed",
    "format_summary",
    "keep_settings",
    "read_runs",
    "run_experiment",
    "run_name",
    "study_run_records",
    "summarise",
    "train_run",
]

RESULTS_FORMAT = "layoutwarp.results/1"


@dataclass(frozen=True)
class RunOptions:
    """How a run trains: the task's defaults, with what the command line changed.

    Attributes:
        epochs, batch_size, lr, theta_lr, freeze_epochs, schedule, optimizer, weight_decay: as
            [`TaskDefaults`][] (frozen epochs are capped at ``epochs − 1``, so θ always trains).
        sensor: [`SensorLayer`][layoutwarp.sensor.SensorLayer] options (``method``, ``tol``, ...).
        device: where the network and sensor run.
        backbone_weights: a torchvision-format ResNet state dict the network's backbone starts
            from (networks with a ResNet backbone; ``None``: random initialisation).
        amp: mixed precision for the network (the sensor stays float32).
        progress: draw progress bars (on terminals).
        task_options: the task's own options (its protocol's `options`, see
            [`TaskSpec`][layoutwarp.experiments.protocols.TaskSpec]).
    """

    epochs: int
    batch_size: int
    lr: float
    theta_lr: float
    freeze_epochs: int
    schedule: str
    optimizer: str
    weight_decay: float
    sensor: dict[str, Any]
    device: str = "cpu"
    backbone_weights: str | None = None
    amp: bool = False
    progress: bool = True
    task_options: dict[str, Any] = field(default_factory=dict)

    @classmethod
    def of(cls, defaults: TaskDefaults, **changes: Any) -> RunOptions:
        """The options of ``defaults`` with ``changes`` (``None`` values keep the default)."""
        base = {
            "epochs": defaults.epochs,
            "batch_size": defaults.batch_size,
            "lr": defaults.lr,
            "theta_lr": defaults.theta_lr,
            "freeze_epochs": defaults.freeze_epochs,
            "schedule": defaults.schedule,
            "optimizer": defaults.optimizer,
            "weight_decay": defaults.weight_decay,
            "sensor": defaults.sensor(),
        }
        return cls(**(base | {k: v for k, v in changes.items() if v is not None}))

    def record(self) -> dict[str, Any]:
        """The options as results files and model files record them."""
        return {k: v for k, v in asdict(self).items() if k not in ("progress", "sensor")}


@dataclass
class RunRecord:
    """One training run: what trained, its scores (percent) and θ after every epoch.

    ``family`` is the layout family (``"density"`` for the unlearned baseline); ``theta_history``
    starts with θ before training; ``area_ratio_history`` is the ratio of the largest to the
    smallest pixel area at the same points (what a grid or spline layout's θ means).
    """

    task: str
    family: str
    size_hw: list[int]
    seed: int
    scores: dict[str, Any]
    theta: list[float]
    theta_history: list[list[float]] = field(default_factory=list)
    area_ratio_history: list[float] = field(default_factory=list)
    epochs: int = 0
    seconds: float = 0.0

    @property
    def name(self) -> str:
        return run_name(self.family, self.size_hw, self.seed)


def _net_name(task: Task) -> str:
    return f"{task.name} {task.net}".strip()


def run_name(family: str, size: Sequence[int], seed: int) -> str:
    """The name of one training run in file names: ``<family>_<W>x<H>_seed<s>``."""
    return f"{family}_{size[1]}x{size[0]}_seed{seed}"


def _files(folder: Path, pattern: str) -> list[Path]:
    """The files of ``folder`` that match ``pattern``, sorted, but a writer's temporary ones
    ([`atomic_write`][layoutwarp.files.atomic_write]'s ``.NAME.<random><suffix>``: another
    process's write under way, or one a killed process left)."""
    return sorted(p for p in folder.glob(pattern) if not p.name.startswith("."))


def read_runs(folder: Path, name_of: Callable[[dict], str], what: str) -> list[dict]:
    """The run records a ``folder`` of ``what`` (a study, a landscape) holds in ``runs/*.json``, by
    file name; each must be named as ``name_of`` names its record: a file of another kind (a
    landscape's runs written into a study's folder, a summary copied there) is refused in one
    line, not read as one of these runs."""
    records = []
    for path in _files(folder / "runs", "*.json"):
        try:
            record = json.loads(path.read_text())
            ours = isinstance(record, dict) and name_of(record) == path.stem
        except (ValueError, KeyError, TypeError, IndexError):
            ours = False
        if not ours:
            raise ValueError(f"{path} is no run of {what} (the folder's runs/ holds its own); move it away")
        records.append(record)
    return records


def study_run_records(folder: Path) -> list[dict]:
    """The records of a study folder's finished runs, by file name ([`read_runs`][]: each named
    by [`run_name`][])."""
    return read_runs(folder, lambda r: run_name(r["family"], r["size_hw"], r["seed"]), "a study")


#: What the runs of one study or landscape folder may differ in: where they trained.
RESUMABLE = ("device",)


def _settings(options: RunOptions) -> dict[str, Any]:
    """What ``settings.json`` holds of ``options``: as JSON reads it back."""
    return json.loads(json.dumps({"training": options.record(), "sensor": options.sensor}))


def _made(out: Path) -> bool:
    """Whether a study or landscape folder holds a run that finished or stopped with a checkpoint."""
    return bool(_files(out / "runs", "*.json") or _files(out / "checkpoints", "*.pt"))


def check_resumed(out: Path, options: RunOptions, what: str) -> None:
    """Refuse, in one line naming ``out``, to resume a ``what`` (a study, a landscape) whose
    finished or stopped runs trained with other settings than ``options`` (but for
    [`RESUMABLE`][]): its curves would mix two trainings, and a stopped run would go on under
    settings it did not start with. The settings are ``out/settings.json``'s
    ([`keep_settings`][]; in a folder of an earlier version, its first finished run's, where it
    has one); a folder with no run finished or stopped holds none. A training setting the folder's
    record lacks (an earlier version's) is not compared; a sensor option it lacks is one its runs
    did not have."""
    if not _made(out):
        return
    path, runs = out / "settings.json", _files(out / "runs", "*.json")
    record, then = path if path.exists() else next(iter(runs), None), None
    if record is not None:
        with contextlib.suppress(OSError, ValueError):
            then = json.loads(record.read_text())
    if not isinstance(then, dict):
        return  # a stopped run of an earlier version, or a record unread: nothing to hold it to
    now = _settings(options)
    for part in ("training", "sensor"):
        old, new = then.get(part), now[part]
        if not isinstance(old, dict):
            continue
        # a sensor option the record lacks is one the runs did not have (physics, say); a
        # training setting it lacks, one an earlier version did not record
        for key in sorted(old.keys() | new.keys()) if part == "sensor" else sorted(old):
            if key not in RESUMABLE and old.get(key) != new.get(key):
                raise ArgumentError(
                    "out", f"{out} holds a {what} whose runs trained with {key} {old.get(key)!r}, not "
                    f"{new.get(key)!r}: use an empty folder, or those settings to resume it",
                )  # fmt: skip


def keep_settings(out: Path, options: RunOptions) -> None:
    """Write ``options``' settings to ``out/settings.json`` (for [`check_resumed`][]) as a study or
    landscape begins a run: where the folder holds none, or no run finished or stopped yet (a
    first run that failed before its first checkpoint leaves no settings that bind)."""
    if not (out / "settings.json").exists() or not _made(out):
        atomic_write(out / "settings.json", json.dumps(_settings(options), indent=2))


#: The tolerance of the pixel areas behind a run's area ratios: each area within 1e-4 of itself, so
#: the ratio within 2e-4 (a curv 257x513 sensor's in 0.2 s; 1e-6 took 0.9 s at each epoch).
AREA_RATIO_TOL = 1e-4


def _area_ratios(layout: Layout, size: tuple[int, int], thetas: Sequence[Sequence[float]]) -> list[float]:
    """Largest over smallest pixel area of ``layout`` at each of ``thetas`` (a θ repeated, as a
    frozen one is, computed once): of its pixel polygons, curved edges within
    [`AREA_RATIO_TOL`][] ([`pixel_mesh`][layoutwarp.mesh.pixel_mesh]; the corners' quads alone
    missed a curv pixel's bulge: 5.30 for 8.61 at θ = (−0.8, −0.8), 4x4)."""
    ratio: dict[tuple[float, ...], float] = {}
    for theta in map(tuple, thetas):
        if theta not in ratio:
            with torch.no_grad():
                th = torch.tensor(theta, dtype=torch.float64)
                mesh = pixel_mesh(
                    layout, size, tol=AREA_RATIO_TOL, dtype=torch.float64, theta=th, cache=False
                )
                area = mesh.areas().abs()
            ratio[theta] = float(area.max() / area.min())
    return [ratio[tuple(t)] for t in thetas]


def train_run(
    task: Task,
    data: TaskData,
    family: str,
    size: tuple[int, int],
    seed: int,
    options: RunOptions,
    *,
    layout: Layout | None = None,
    checkpoint: Path | None = None,
) -> tuple[RunRecord, nn.Module]:
    """Train one configuration of ``task`` and score it on the report split.

    Args:
        task: the task.
        data: its data ([`Task.load`][]).
        family: a registered layout family (learned from θ = 0; ``"uniform"`` fixed), or
            ``"density"`` (the task's unlearned [`Task.density_layout`][]).
        size: sensor size ``(H, W)``.
        seed: seeds the network's initialisation, the batch order and the augmentation.
        options: how to train.
        layout: train with this layout instead (used as it is: fixed or learnable), recorded
            under ``family``.
        checkpoint: written after every epoch and resumed from (see [`fit`][]);
            the caller removes it once the run's results are kept.

    Returns:
        the run's record and the trained network.
    """
    torch.manual_seed(seed)
    gen = torch.Generator().manual_seed(seed)
    if layout is None:
        layout = task.density_layout(data, size) if family == "density" else None
    if layout is None:  # a family by name: learned, but for uniform; a layout object brings its own
        model = task.network(family, size, learn=family != "uniform", **options.sensor)
    else:
        model = task.network(layout, size, learn=None, **options.sensor)
    model = model.to(options.device)
    if options.backbone_weights:
        if not hasattr(model, "load_backbone"):
            raise ValueError(f"backbone_weights: the {_net_name(task)} network has no ResNet backbone")
        model.load_backbone(options.backbone_weights)
    rank, _ = world()
    if rank:  # the network starts as rank 0's (DistributedDataParallel copies it); the draws of
        # torch's generator from here (sensor noise, dropout) are each rank's own, as one process
        # draws them anew for every image of the global batch
        torch.manual_seed(seed + rank * RANK_SEEDS)
    opt = optimizer(model, options.lr, options.theta_lr, options.optimizer, options.weight_decay)
    indices, batch_loss = task.batches(model, data.train, gen, options.task_options)
    sched = schedule(opt, options.schedule, options.epochs)
    history, seconds = fit(
        model,
        indices,
        batch_loss,
        opt,
        gen,
        epochs=options.epochs,
        batch_size=options.batch_size,
        freeze_epochs=min(options.freeze_epochs, max(options.epochs - 1, 0)),
        sched=sched,
        desc=f"{task.name} {family} {size[1]}x{size[0]} seed {seed}",
        progress=options.progress,
        amp=options.amp,
        checkpoint=checkpoint,
    )
    scores = task.score(model, data.report)
    fixed = model.sensor.layout
    record = RunRecord(
        task.name,
        family,
        list(size),
        seed,
        scores,
        fixed.theta.detach().tolist(),
        history,
        _area_ratios(fixed, size, history),
        options.epochs,
        seconds,
    )
    return record, model


def summarise(task: Task, records: Sequence[RunRecord | dict]) -> list[dict[str, Any]]:
    """Mean ± standard deviation (over seeds) of every metric, per family and sensor size, in
    the order the configurations first appear."""
    groups: dict[tuple[str, tuple[int, ...]], list[dict]] = {}
    for r in records:
        r = asdict(r) if isinstance(r, RunRecord) else r
        groups.setdefault((r["family"], tuple(r["size_hw"])), []).append(r)
    rows = []
    for (family, size), rs in groups.items():
        scores = {}
        for m in task.metrics:
            v = np.array([float(r["scores"][m]) for r in rs])
            scores[m] = {"mean": float(v.mean()), "std": float(v.std(ddof=1)) if len(v) > 1 else 0.0}
        theta = np.mean([r["theta"] for r in rs], 0).tolist() if rs[0]["theta"] else []
        rows.append(
            {"family": family, "size_hw": list(size), "n": len(rs), "scores": scores, "theta_mean": theta}
        )
    return rows


def format_summary(task: Task, rows: Sequence[dict]) -> str:
    """The summary rows as a plain-text table (scores in percent)."""
    head = f"{'family':9s} {'sensor':7s} " + " ".join(f"{m + ' (%)':>17s}" for m in task.metrics)
    lines = [head + "  θ (mean)"]
    for r in rows:
        h, w = r["size_hw"]
        cells = " ".join(
            f"{r['scores'][m]['mean']:8.2f} ± {r['scores'][m]['std']:5.2f} " for m in task.metrics
        )
        lines.append(
            f"{r['family']:9s} {f'{w}x{h}':7s} {cells} {format_theta(r['theta_mean'], 2)}  n={r['n']}"
        )
    return "\n".join(lines)


def run_experiment(
    task: Task,
    folder: str | Path,
    out: str | Path,
    *,
    families: Sequence[str],
    sizes: Sequence[tuple[int, int]],
    seeds: Sequence[int],
    options: RunOptions,
    limit: int | None = None,
    say: Callable[[str], None] = print,
) -> dict[str, Any]:
    """Train every family × sensor size × seed of ``task``; write ``results.json`` (after every
    run, so a stopped experiment keeps what finished), a model file per run, the learned layout
    files and figures to ``out``.

    Returns:
        the results written to ``results.json``.
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    data = task.load(Path(folder), limit)
    records: list[RunRecord] = []
    models: dict[tuple[str, tuple[int, int]], nn.Module] = {}
    result: dict[str, Any] = {}
    for size in sizes:
        size = tuple(size)
        for family in families:
            for seed in seeds:
                record, model = train_run(task, data, family, size, seed, options)
                records.append(record)
                models.setdefault((family, size), model)
                training = options.record() | {"family": family, "seed": seed, "scores": record.scores}
                save_model(
                    out / f"model_{record.name}.pt",
                    task.name,
                    model,
                    sensor=options.sensor,
                    training=training,
                    net=task.net,
                )
                scores = "  ".join(f"{m} {record.scores[m]:6.2f}%" for m in task.metrics)
                say(
                    f"  {task.name} {family:8s} {size[1]}x{size[0]} seed {seed}: {scores}  "
                    f"θ = {format_theta(record.theta)}  [{record.seconds:.0f} s]"
                )
                result = _results(task, data, options, records, seeds)
                atomic_write(out / "results.json", json.dumps(result, indent=2))
    _layout_files(task, out, models, result["summary"])
    from .plots import training_figures

    cpu = {key: model.cpu() for key, model in models.items()}  # figures are drawn on the CPU
    training_figures(task, data, cpu, records, out)
    return result


def _results(
    task: Task, data: TaskData, options: RunOptions, records: list[RunRecord], seeds: Sequence[int]
) -> dict[str, Any]:
    return {
        "format": RESULTS_FORMAT,
        "task": task.name,
        "net": task.net,
        "data": str(data.source),
        "train_size": data.sizes.get("train"),
        "report_split": task.report_split,
        "report_size": data.sizes.get("report"),
        "units": "percent",
        "metrics": list(task.metrics),
        "sensor": options.sensor,
        "training": options.record(),
        "summary": summarise(task, records),
        "runs": [asdict(r) for r in records],
        "run": run_info(options.device, list(seeds)),
    }


def _layout_files(
    task: Task, out: Path, models: dict[tuple[str, tuple[int, int]], nn.Module], summary: list[dict]
) -> None:
    """``layout_<family>_<W>x<H>.json`` of each configuration's first seed, and ``layout.json``:
    the learned layout with the best headline metric (at the first size)."""
    for (family, size), model in models.items():
        save_layout(
            model.sensor.layout, out / f"layout_{family}_{size[1]}x{size[0]}.json", size, task=task.name
        )
    learned = [r for r in summary if r["family"] not in ("uniform", "density")]
    if learned:
        best = max(learned, key=lambda r: r["scores"][task.metric]["mean"])
        size = tuple(best["size_hw"])
        score = best["scores"][task.metric]["mean"]
        extra = {"task": task.name, task.metric: score}
        save_layout(models[best["family"], size].sensor.layout, out / "layout.json", size, **extra)
