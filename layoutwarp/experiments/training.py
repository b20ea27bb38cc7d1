"""What every experiment shares: its defaults, the training loop, run records and summaries."""

from __future__ import annotations

import json
import os
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch
from torch import nn
from tqdm import tqdm

from ..files import atomic_write
from .models import save_run_model

__all__ = [
    "ExperimentDefaults",
    "TaskRun",
    "autocast",
    "default_device",
    "fit",
    "format_theta",
    "layout_name",
    "model_device",
    "optimizer",
    "run_grid",
    "save_runs",
    "summarise",
    "theta_text",
    "world",
]


@dataclass(frozen=True)
class ExperimentDefaults:
    """The one set of defaults of an experiment: its run function and the command line read it.

    Attributes:
        task: the experiment's name (``layoutwarp train TASK``).
        shared: its folder under the shared data folder (the full data set).
        sample: its folder under ``data_samples/`` (used by ``--quick``).
        families: the layout families it compares (``"uniform"`` is the fixed baseline).
        sizes: sensor sizes ``(H, W)``.
        seeds: number of seeds.
        epochs: training epochs.
        quick_epochs: epochs with ``--quick`` (which also uses 1 seed and the first size).
        tol: the exact integrator's curved-edge tolerance.
        freeze_epochs: epochs with θ frozen at the start (0 with ``--quick``).
    """

    task: str
    shared: str
    sample: str
    families: tuple[str, ...]
    sizes: tuple[tuple[int, int], ...]
    seeds: int
    epochs: int
    quick_epochs: int
    tol: float
    freeze_epochs: int = 0

    def sensor(self) -> dict:
        """The sensor options of the experiment unless the caller gives its own."""
        return {"method": "exact", "tol": self.tol}


def world() -> tuple[int, int]:
    """``(rank, world size)`` of this process: ``(0, 1)`` alone; under ``torchrun`` (``WORLD_SIZE``
    > 1) the process group is initialised once from its environment: gloo for CPU tensors, and
    NCCL for CUDA tensors where CUDA is available (so ``--device cpu`` works on a GPU machine)."""
    import torch.distributed as dist

    if int(os.environ.get("WORLD_SIZE", "1")) <= 1 or not dist.is_available():
        return 0, 1
    if not dist.is_initialized():
        dist.init_process_group("cpu:gloo,cuda:nccl" if torch.cuda.is_available() else "gloo")
    return dist.get_rank(), dist.get_world_size()


def _check_same_theta(theta: torch.Tensor) -> None:
    """Raise if the ranks of a distributed run hold different θ (they must stay identical)."""
    import torch.distributed as dist

    hi, lo = theta.detach().clone(), -theta.detach().clone()
    dist.all_reduce(hi, op=dist.ReduceOp.MAX)
    dist.all_reduce(lo, op=dist.ReduceOp.MAX)
    if not torch.equal(hi, -lo):
        raise RuntimeError(f"θ differs between ranks by up to {float((hi + lo).abs().max()):.3g}")


def fit(
    model: nn.Module,
    indices: torch.Tensor,
    batch_loss: Callable[[torch.Tensor, nn.Module], torch.Tensor],
    opt: torch.optim.Optimizer,
    gen: torch.Generator,
    *,
    epochs: int,
    batch_size: int,
    freeze_epochs: int = 0,
    sched: torch.optim.lr_scheduler.LRScheduler | None = None,
    desc: str = "train",
    progress: bool = True,
    amp: bool = False,
) -> list[list[float]]:
    """The training loop shared by every experiment; returns θ after each epoch (and at start).

    Each epoch shuffles ``indices`` with ``gen`` and steps ``opt`` on ``batch_loss(idx, net)``
    (``net``: the module to call, ``model`` or its DistributedDataParallel wrapper) for
    batches of ``batch_size`` indices (a last batch of one joins the one before, as batch
    normalisation needs two samples). ``model.sensor``'s parameters are frozen for the first
    ``freeze_epochs`` epochs; ``sched`` steps once per epoch. tqdm draws on terminals only
    (``disable=None``), so logs stay readable. ``amp`` runs the network under autocast
    (:func:`autocast`; the sensor itself always integrates in float32).

    Under ``torchrun`` (:func:`world`) every rank draws the same permutation and takes its
    share ``batch[rank::world_size]`` of each global batch; DistributedDataParallel averages
    the gradients (θ included, as an ordinary parameter), so a step equals the single-process
    step on the global batch. After every epoch the ranks' θ are compared (they must agree
    exactly); only rank 0 draws a progress bar. With CUDA, the batch-norm layers become
    ``SyncBatchNorm`` (statistics over the global batch; untested here for lack of GPUs).

    Nothing in the loop reads a device value back except the progress bar's loss and θ
    (every 20th step, only when the bar is drawn) and the θ check between epochs.
    """
    sensor = list(model.sensor.parameters())
    history = [model.sensor.theta.detach().tolist()]
    device = model_device(model)
    # float16 (CUDA autocast) needs loss scaling; bfloat16 (CPU autocast) and float32 do not
    scaler = torch.amp.GradScaler(device.type, enabled=amp and device.type == "cuda")
    n = len(indices)
    starts = list(range(0, n, batch_size))
    if len(starts) > 1 and n - starts[-1] == 1:  # no 1-sample batch: batch norm needs two
        starts.pop()
    bounds = list(zip(starts, [*starts[1:], n], strict=True))
    rank, size = world()
    if size > 1 and device.type == "cuda":  # batch statistics over the global batch (in place:
        nn.SyncBatchNorm.convert_sync_batchnorm(model)  # the parameters, and so `opt`, stay)
    bar = tqdm(
        total=epochs * len(bounds),
        desc=desc,
        disable=None if progress and rank == 0 else True,
        leave=False,
    )
    for epoch in range(epochs):
        for p in sensor:
            p.requires_grad_(epoch >= freeze_epochs)
        model.train()
        net = model
        if size > 1:  # rebuilt each epoch: which parameters train can change (freeze_epochs)
            from torch.nn.parallel import DistributedDataParallel

            net = DistributedDataParallel(model, device_ids=[device] if device.type == "cuda" else None)
        perm = indices[torch.randperm(len(indices), generator=gen)]
        for a, b in bounds:
            with autocast(model, amp):
                loss = batch_loss(perm[a:b][rank::size], net)
            opt.zero_grad()
            scaler.scale(loss).backward()
            scaler.step(opt)
            scaler.update()
            bar.update(1)
            if not bar.disable and bar.n % 20 == 1:  # reading the loss waits for the device
                th = model.sensor.theta.detach()
                bar.set_postfix(loss=f"{loss.item():.3f}", theta=format_theta(th.tolist()))
        if sched is not None:
            sched.step()
        if size > 1:
            _check_same_theta(model.sensor.theta)
        history.append(model.sensor.theta.detach().tolist())
    bar.close()
    return history


@dataclass
class TaskRun:
    """One training run of a task."""

    task: str
    layout: str
    size_hw: list[int]
    seed: int
    scores: dict
    theta: list[float]
    theta_history: list[list[float]] = field(default_factory=list)
    seconds: float = 0.0


def optimizer(model: nn.Module, lr: float, theta_lr: float) -> torch.optim.Optimizer:
    """Adam with the sensor's trainable parameters in a group of their own (``theta_lr``)."""
    sensor = [p for p in model.sensor.parameters() if p.requires_grad]
    rest = [p for n, p in model.named_parameters() if not n.startswith("sensor.")]
    groups = [{"params": rest, "lr": lr}] + ([{"params": sensor, "lr": theta_lr}] if sensor else [])
    return torch.optim.Adam(groups)


def summarise(runs: list[TaskRun], metrics: tuple[str, ...]) -> dict:
    summary: dict = {}
    for run in runs:
        key = f"{run.layout} {run.size_hw[1]}x{run.size_hw[0]}"
        summary.setdefault(key, {"layout": run.layout, "size_hw": run.size_hw, "runs": []})["runs"].append(
            run
        )
    for s in summary.values():
        rs = s.pop("runs")
        for m in metrics:
            v = np.array([r.scores[m] for r in rs])
            s[m] = {"mean": float(v.mean()), "std": float(v.std(ddof=1)) if len(v) > 1 else 0.0}
        s["theta_mean"] = np.mean([r.theta for r in rs], 0).tolist()
        s["n"] = len(rs)
    return summary


def save_runs(
    out: Path, task: str, data_dir, n_train: int, n_test: int, epochs: int, runs, metrics, sensor, **options
) -> None:
    result = {
        "task": task,
        "data": str(data_dir),
        "train_size": n_train,
        "test_size": n_test,
        "epochs": epochs,
        **options,
        "sensor": sensor or {"method": "exact"},
        "summary": summarise(runs, metrics),
        "runs": [asdict(r) for r in runs],
    }
    atomic_write(out / "results.json", json.dumps(result, indent=2))


def run_grid(
    task: str,
    out: Path,
    configs: Sequence[tuple[str, tuple[int, int], int]],
    train: Callable[[str, tuple[int, int], int], tuple[TaskRun, nn.Module]],
    *,
    sensor: dict,
    training: dict,
    describe: Callable[[TaskRun], str],
    save: Callable[[list[TaskRun]], None],
) -> dict[tuple[str, tuple[int, int]], nn.Module]:
    """Train every ``(family, size, seed)`` of ``configs`` with ``train``; after each run save its
    model in ``out`` (the ``training`` record plus its scores), print one line (``describe``)
    and call ``save`` with the runs so far. Returns the first seed's model of every family and
    size (for figures)."""
    runs: list[TaskRun] = []
    models: dict[tuple[str, tuple[int, int]], nn.Module] = {}
    for family, size, seed in configs:
        run, model = train(family, size, seed)
        runs.append(run)
        models.setdefault((family, tuple(size)), model)
        info = {"sensor": sensor, "training": {**training, "scores": run.scores}}
        save_run_model(out, task, family, size, seed, model, **info)
        print(
            f"  {task} {family:8s} {size[1]}x{size[0]} seed {seed}: {describe(run)}  "
            f"θ = {format_theta(run.theta)}  [{run.seconds:.0f} s]",
            flush=True,
        )
        save(runs)
    return models


def format_theta(values: Sequence[float], digits: int = 3) -> str:
    """θ as ``(+0.100, -0.200)``; more than four values (spline logits, grid control points) are
    summarised as ``(16 values, max |θ| 0.52)``."""
    values = list(values)
    if len(values) > 4:
        return f"({len(values)} values, max |θ| {max(abs(v) for v in values):.2f})"
    return "(" + ", ".join(f"{v:+.{digits}f}" for v in values) + ")"


def model_device(model: nn.Module) -> torch.device:
    """The device of a model's parameters (where its batches must go)."""
    return next(model.parameters()).device


def default_device() -> str:
    """``"cuda"`` when a CUDA GPU is available, else ``"cpu"`` (the command line's default)."""
    return "cuda" if torch.cuda.is_available() else "cpu"


def autocast(model: nn.Module, enabled: bool) -> torch.autocast:
    """Mixed precision for ``model``'s device: float16 on CUDA, bfloat16 on the CPU. The
    sensor layer turns it off for its own integration (:func:`~layoutwarp.simulate`)."""
    device = model_device(model).type
    dtype = torch.float16 if device == "cuda" else torch.bfloat16
    return torch.autocast(device_type=device, dtype=dtype, enabled=enabled)


def layout_name(layout: str | nn.Module) -> str:
    """A layout's name in run records and progress bars: the family name it was given, or the
    family of a layout instance."""
    return layout if isinstance(layout, str) else str(getattr(layout, "family", type(layout).__name__))


def theta_text(model: nn.Module) -> str:
    return "θ=" + format_theta(model.sensor.theta.detach().tolist(), 2)
