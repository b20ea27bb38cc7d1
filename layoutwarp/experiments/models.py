"""Model files: a trained network with its sensor, one file per training run, and scoring them.

A model file (``torch.save`` of a plain dict, read with ``weights_only=True``) holds
``format`` (``"layoutwarp.model/1"``), ``task``, ``version`` (the package version that wrote
it), ``layout`` (the family and [`to_config`][layoutwarp.layouts.base.Layout.to_config]),
``size_hw``, ``sensor`` (the [`SensorLayer`][layoutwarp.sensor.SensorLayer] options),
``training`` (seed, epochs and the like) and
``state_dict`` (the network's weights, the sensor's θ included). [`load_model`][] rebuilds
the network of the file's task ([`TASKS`][layoutwarp.experiments.tasks.TASKS]) with the layout
fixed, so scoring never changes it.

Format ``layoutwarp.model/2`` adds int8 weights for shipping (``quantized``: the float32
per-output-channel scale of every int8 tensor); files without them are still written as
``/1``, which older readers load.
"""

from __future__ import annotations

import io
from pathlib import Path
from typing import Any

import torch
from torch import nn

from ..checks import check_choice
from ..doctor import run_info
from ..files import atomic_write
from ..layoutfile import layout_from_spec, layout_spec
from .tasks import get_task

__all__ = ["FORMAT", "READS", "WEIGHTS", "evaluate_model", "load_model", "save_model"]

FORMAT = "layoutwarp.model/2"
#: Formats [`load_model`][] reads.
READS = ("layoutwarp.model/1", FORMAT)
#: Precisions [`save_model`][] stores the network's weights in.
WEIGHTS = ("float32", "float16", "int8")


def save_model(
    path: str | Path,
    task: str,
    model: nn.Module,
    *,
    sensor: dict,
    training: dict,
    weights: str = "float32",
    net: str = "",
) -> Path:
    """Write ``model`` (a task network with a ``sensor``) to a model file, atomically.

    Args:
        path: the file to write.
        task: a registered task's name.
        model: the trained network.
        net: which of the task's networks it is ([`nets`][layoutwarp.experiments.tasks.Task.nets];
            ``""``: its default).
        sensor: the sensor options it was trained with (``method``, ``tol``, ...).
        training: anything JSON-able that describes the run (seed, epochs, scores, ...).
        weights: ``"float32"``; ``"float16"`` (half the size); ``"int8"`` (a quarter: conv and
            linear weights rounded to 255 levels per output channel, the rest float16). Scores
            can shift slightly with either; the sensor's θ is always kept in full precision.
    """
    check_choice(weights, WEIGHTS, "weights")
    get_task(task).with_net(net or None)  # checks both
    layout = model.sensor.layout
    state, scales = {}, {}
    for k, v in model.state_dict().items():
        if k.startswith("sensor.") or not v.is_floating_point() or weights == "float32":
            state[k] = v
        elif weights == "int8" and v.ndim >= 2:
            scale = v.detach().abs().amax(dim=tuple(range(1, v.ndim))).float().clamp_min(1e-30) / 127
            state[k] = (v / scale.view(-1, *[1] * (v.ndim - 1))).round().clamp(-127, 127).to(torch.int8)
            scales[k] = scale
        else:
            state[k] = v.half()
    info = run_info()
    data = {
        "format": FORMAT if scales else READS[0],
        "task": task,
        "net": net,
        "version": info["layoutwarp"],
        "run": info,
        "layout": layout_spec(layout),
        "size_hw": list(model.sensor.size),
        "sensor": dict(sensor),
        "training": dict(training),
        "state_dict": state,
    } | ({"quantized": scales} if scales else {})
    buf = io.BytesIO()
    torch.save(data, buf)
    return atomic_write(path, buf.getvalue())


def load_model(
    path: str | Path, task: str | None = None, device: str | torch.device = "cpu"
) -> tuple[nn.Module, dict[str, Any]]:
    """Rebuild a network from a model file (in eval mode, its layout fixed).

    Args:
        path: a file written by [`save_model`][].
        task: the task the caller expects (``None``: any).
        device: where to put the network.

    Returns:
        ``(model, info)`` with ``info`` the file's other entries.

    Raises:
        ValueError: not a model file, another format version or task, or weights that do not
            fit the network, with the file's name and the problem on one line.
    """
    path = Path(path)
    try:
        data = torch.load(path, map_location="cpu", weights_only=True)
    except FileNotFoundError:
        raise ValueError(f"{path}: no such model file") from None
    except Exception:  # pickle, zip and torch errors alike (their names and text are torch's
        # internals): not a model file
        raise ValueError(
            f"{path}: not a readable layoutwarp model file (torch.load cannot read it)"
        ) from None
    fmt = data.get("format") if isinstance(data, dict) else None
    if fmt not in READS:
        what = f"format {fmt!r}" if isinstance(fmt, str) else "no model format"
        raise ValueError(f"{path}: {what}; this layoutwarp reads {' and '.join(map(repr, READS))}")
    if task is not None and data.get("task") != task:
        raise ValueError(f"{path}: a {data.get('task')!r} model, not a {task!r} model")
    try:
        network = get_task(data.get("task")).with_net(data.get("net") or None).network
        layout = layout_from_spec(data["layout"])
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from None
    net = network(layout, tuple(data["size_hw"]), learn=None, **data["sensor"])  # the layout: fixed
    scales = data.get("quantized", {})
    state = {}
    for k, v in data["state_dict"].items():
        if k in scales:
            v = v.float() * scales[k].view(-1, *[1] * (v.ndim - 1))
        state[k] = v.float() if v.dtype == torch.float16 else v
    try:
        net.load_state_dict(state)
    except RuntimeError as exc:
        first = str(exc).splitlines()[0]
        raise ValueError(f"{path}: the weights do not fit the {data['task']} network ({first})") from None
    net.to(device).eval()
    return net, {k: v for k, v in data.items() if k not in ("state_dict", "quantized")}


def evaluate_model(task: str, model: nn.Module, folder: str | Path, split: str | None = None) -> dict:
    """Score a model on a folder laid out like the task's data (see `Task.load_split`):

    * MNIST: IDX files; ``split`` ``"test"`` (default, ``t10k-*``) or ``"train"``;
    * CamVid: ``NAME/`` images and ``NAMEannot/`` label maps, ``split`` = NAME (default ``"val"``);
      mIoU, pixel accuracy and per-class IoU (percent) at full resolution;
    * faces: images and ``labels.csv`` (every face listed; ``split`` must not be given).

    Returns:
        ``{"n": items scored, **scores}`` (percent).
    """
    t = get_task(task)
    part = t.load_split(Path(folder), split)
    n = (
        len(part["images"])
        if isinstance(part, dict)
        else len(part[0])
        if isinstance(part, tuple)
        else len(part)
    )
    return {"n": n, **t.score(model, part)}
