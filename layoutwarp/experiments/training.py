"""The training loop every task shares, its optimiser, devices and processes."""

from __future__ import annotations

import io
import os
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import torch
from torch import nn
from tqdm import tqdm

from ..checks import check_choice
from ..doctor import world
from ..files import atomic_write

__all__ = [
    "SCHEDULES",
    "BatchLoss",
    "autocast",
    "default_device",
    "fit",
    "format_theta",
    "init_distributed",
    "model_device",
    "optimizer",
    "schedule",
    "world",
]

#: A task's loss on a batch: ``(indices, net) -> loss``, ``net`` the module to call.
BatchLoss = Callable[[torch.Tensor, nn.Module], torch.Tensor]


def init_distributed() -> tuple[int, int]:
    """Join the process group ``torchrun`` set up for this process (``WORLD_SIZE`` > 1), once:
    gloo for CPU tensors and NCCL for CUDA tensors where CUDA is available (so ``--device cpu``
    works on a GPU machine). Returns [`world`][layoutwarp.doctor.world]; alone, it does nothing."""
    import torch.distributed as dist

    if int(os.environ.get("WORLD_SIZE", "1")) > 1 and dist.is_available() and not dist.is_initialized():
        dist.init_process_group("cpu:gloo,cuda:nccl" if torch.cuda.is_available() else "gloo")
    return world()


def _check_same_start(first: int, run: str = "") -> None:
    """Refuse, in one line on every rank, a distributed run whose ranks would begin another run
    (``run``: its name) or at different epochs: a record or checkpoint one rank found and another
    did not (``--out`` not a folder every rank sees). They would pair their collectives across
    runs or epochs, and fail later, if at all."""
    import zlib

    import torch.distributed as dist

    name = zlib.crc32(run.encode())
    bounds = torch.tensor([first, -first, name, -name], dtype=torch.int64)
    dist.all_reduce(bounds, op=dist.ReduceOp.MAX)
    if int(bounds[2]) != -int(bounds[3]):
        raise ValueError(
            f"the ranks would train different runs ({run} on this one): every rank must see the "
            "runs already done (--out a folder every rank sees, e.g. on a shared file system)"
        )
    if int(bounds[0]) != -int(bounds[1]):
        raise ValueError(
            f"the ranks would resume at epochs {-int(bounds[1])} to {int(bounds[0])}: every rank "
            "must see the run's checkpoint (--out a folder every rank sees, e.g. on a shared file system)"
        )


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
    batch_loss: BatchLoss,
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
    checkpoint: Path | None = None,
) -> tuple[list[list[float]], float]:
    """The training loop shared by every experiment; returns θ after each epoch (and at start)
    and the seconds spent training, over every stretch of a resumed run.

    Each epoch shuffles ``indices`` with ``gen`` and steps ``opt`` on ``batch_loss(idx, net)``
    (``net``: the module to call, ``model`` or its DistributedDataParallel wrapper) for
    batches of ``batch_size`` indices (a last batch of one joins the one before, as batch
    normalisation needs two samples). ``model.sensor``'s parameters are frozen for the first
    ``freeze_epochs`` epochs; ``sched`` steps once per epoch. tqdm draws on terminals only
    (``disable=None``), so logs stay readable. ``amp`` runs the network under autocast
    ([`autocast`][]; the sensor itself always integrates in float32).

    Under ``torchrun`` ([`init_distributed`][]) every rank draws the same permutation and takes its
    share ``batch[rank::world_size]`` of each global batch; DistributedDataParallel averages
    the gradients (θ included, as an ordinary parameter), so a step equals the single-process
    step on the global batch. After every epoch the ranks' θ are compared (they must agree
    exactly); only rank 0 draws a progress bar. With CUDA, the batch-norm layers become
    ``SyncBatchNorm`` (statistics over the global batch; untested here for lack of GPUs).

    Nothing in the loop reads a device value back except the progress bar's loss and θ
    (every 20th step, only when the bar is drawn) and the θ check between epochs.

    ``checkpoint``: a file the loop writes after every epoch (the model, the optimiser, the
    schedule, ``gen``'s and torch's random states, the history and the seconds so far; rank 0,
    atomically) and
    resumes from when it exists, so that a stopped run loses at most an epoch and, resumed,
    trains as it would have without the stop (the same values on the CPU).
    """
    sensor = list(model.sensor.parameters())
    history = [model.sensor.theta.detach().tolist()]
    device = model_device(model)
    # float16 (CUDA autocast) needs loss scaling; bfloat16 (CPU autocast) and float32 do not
    scaler = torch.amp.GradScaler(device.type, enabled=amp and device.type == "cuda")
    first, earlier, t0 = 0, 0.0, time.perf_counter()
    if checkpoint is not None and checkpoint.exists():
        first, history, earlier = _resume(checkpoint, model, opt, sched, scaler, gen)
    n = len(indices)
    starts = list(range(0, n, batch_size))
    if len(starts) > 1 and n - starts[-1] == 1:  # no 1-sample batch: batch norm needs two
        starts.pop()
    bounds = list(zip(starts, [*starts[1:], n], strict=True))
    rank, size = world()
    if size > 1:
        _check_same_start(first, desc)
    if size > 1 and device.type == "cuda":  # batch statistics over the global batch (in place:
        nn.SyncBatchNorm.convert_sync_batchnorm(model)  # the parameters, and so `opt`, stay)
    bar = tqdm(
        total=epochs * len(bounds),
        initial=first * len(bounds),
        desc=desc,
        disable=None if progress and rank == 0 else True,
        leave=False,
    )
    for epoch in range(first, epochs):
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
        if checkpoint is not None and rank == 0:
            seconds = earlier + time.perf_counter() - t0
            _save_checkpoint(checkpoint, epoch + 1, model, opt, sched, scaler, gen, history, seconds)
    bar.close()
    return history, earlier + time.perf_counter() - t0


def _save_checkpoint(
    path: Path,
    epochs_done: int,
    model: nn.Module,
    opt: torch.optim.Optimizer,
    sched: torch.optim.lr_scheduler.LRScheduler | None,
    scaler: torch.amp.GradScaler,
    gen: torch.Generator,
    history: list[list[float]],
    seconds: float,
) -> None:
    state = {
        "epochs_done": epochs_done,
        "model": model.state_dict(),
        "opt": opt.state_dict(),
        "sched": None if sched is None else sched.state_dict(),
        "scaler": scaler.state_dict(),
        "gen": gen.get_state(),
        "rng": torch.get_rng_state(),
        "cuda_rng": torch.cuda.get_rng_state_all() if torch.cuda.is_available() else None,
        "history": history,
        "seconds": seconds,
        # the sensor's place in its seeded noise sequence (a buffer its state dict leaves out)
        "noise_calls": getattr(model.sensor, "noise_calls", None),
    }
    buf = io.BytesIO()
    torch.save(state, buf)
    atomic_write(path, buf.getvalue())


def _resume(
    path: Path,
    model: nn.Module,
    opt: torch.optim.Optimizer,
    sched: torch.optim.lr_scheduler.LRScheduler | None,
    scaler: torch.amp.GradScaler,
    gen: torch.Generator,
) -> tuple[int, list[list[float]], float]:
    """Load a checkpoint of [`fit`][]'s into the run's objects: the epochs done, the history and
    the seconds spent so far (0 in checkpoints written before they were kept). Read with
    ``weights_only=True``: tensors and plain containers only, so a checkpoint cannot run code."""
    state = torch.load(path, map_location=model_device(model), weights_only=True)
    model.load_state_dict(state["model"])
    opt.load_state_dict(state["opt"])
    if sched is not None and state["sched"] is not None:
        sched.load_state_dict(state["sched"])
    scaler.load_state_dict(state["scaler"])
    gen.set_state(state["gen"])
    if state.get("noise_calls") is not None and hasattr(model.sensor, "noise_calls"):
        model.sensor.noise_calls.copy_(state["noise_calls"])
    torch.set_rng_state(state["rng"])
    if state["cuda_rng"] is not None and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda_rng"])
    rank, _ = world()
    if rank:  # the checkpoint holds rank 0's generator: each other rank's draws go on as its own
        torch.manual_seed(int(torch.randint(0, 2**62, ())) + rank)
    return int(state["epochs_done"]), state["history"], float(state.get("seconds", 0.0))


def optimizer(
    model: nn.Module, lr: float, theta_lr: float, kind: str = "adam", weight_decay: float = 0.0
) -> torch.optim.Optimizer:
    """Adam, or SGD with momentum 0.9 (``kind="sgd"``, PSPNet's), with the sensor's trainable
    parameters in a group of their own (``theta_lr``, no weight decay; Adam is elementwise, so
    ``theta_lr = lr`` is plain Adam over every parameter); ``weight_decay`` on the network."""
    check_choice(kind, ("adam", "sgd"), "optimizer")
    sensor = [p for p in model.sensor.parameters() if p.requires_grad]
    rest = [p for n, p in model.named_parameters() if not n.startswith("sensor.")]
    groups = [{"params": rest, "lr": lr, "weight_decay": weight_decay}]
    groups += [{"params": sensor, "lr": theta_lr, "weight_decay": 0.0}] if sensor else []
    return torch.optim.SGD(groups, momentum=0.9) if kind == "sgd" else torch.optim.Adam(groups)


def schedule(
    opt: torch.optim.Optimizer, kind: str, epochs: int
) -> torch.optim.lr_scheduler.LRScheduler | None:
    """The learning rates over ``epochs`` (stepped once an epoch): ``"constant"`` (``None``),
    ``"cosine"`` (annealed to 0) or ``"poly"`` (PSPNet's ``(1 − epoch/epochs)^0.9``)."""
    check_choice(kind, SCHEDULES, "schedule")
    epochs = max(epochs, 1)
    if kind == "cosine":
        return torch.optim.lr_scheduler.CosineAnnealingLR(opt, epochs)
    if kind == "poly":
        return torch.optim.lr_scheduler.LambdaLR(opt, lambda e: max(1.0 - e / epochs, 0.0) ** 0.9)
    return None


#: The learning-rate schedules of [`schedule`][].
SCHEDULES = ("constant", "cosine", "poly")


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
    sensor layer turns it off for its own integration ([`simulate`][layoutwarp.sensor.simulate])."""
    device = model_device(model).type
    dtype = torch.float16 if device == "cuda" else torch.bfloat16
    return torch.autocast(device_type=device, dtype=dtype, enabled=enabled)
