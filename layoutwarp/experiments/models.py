"""Model files: a trained network with its sensor, one file per training run, and scoring them.

A model file (``torch.save`` of a plain dict, read with ``weights_only=True``) holds
``format`` (``"layoutwarp.model/1"``), ``task``, ``version`` (the package version that wrote
it), ``layout`` (the family and :meth:`~layoutwarp.Layout.to_config`), ``size_hw``, ``sensor``
(the :class:`~layoutwarp.SensorLayer` options), ``training`` (seed, epochs and the like) and
``state_dict`` (the network's weights, the sensor's θ included). :func:`load_model` rebuilds
the network with the layout fixed, so scoring never changes it.

Format ``layoutwarp.model/2`` adds int8 weights for shipping (``quantized``: the float32
per-output-channel scale of every int8 tensor); files without them are still written as
``/1``, which older readers load.
"""

from __future__ import annotations

import io
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from ..files import atomic_write
from ..layouts import FAMILIES

__all__ = ["FORMAT", "TASKS", "evaluate_model", "load_model", "run_name", "save_model", "save_run_model"]

FORMAT = "layoutwarp.model/2"
#: Formats :func:`load_model` reads.
READS = ("layoutwarp.model/1", FORMAT)
#: Precisions :func:`save_model` stores the network's weights in.
WEIGHTS = ("float32", "float16", "int8")
#: The tasks whose models these files hold.
TASKS = ("mnist", "camvid", "faces")


def _network(task: str) -> type[nn.Module]:
    from .camvid import SegNet
    from .faces import FaceNet
    from .mnist import MnistNet

    return {"mnist": MnistNet, "camvid": SegNet, "faces": FaceNet}[task]


def save_model(
    path: str | Path, task: str, model: nn.Module, *, sensor: dict, training: dict, weights: str = "float32"
) -> Path:
    """Write ``model`` (a task network with a ``sensor``) to a model file, atomically.

    Args:
        path: the file to write.
        task: ``"mnist"``, ``"camvid"`` or ``"faces"``.
        model: the trained network.
        sensor: the sensor options it was trained with (``method``, ``tol``, ...).
        training: anything JSON-able that describes the run (seed, epochs, scores, ...).
        weights: ``"float32"``; ``"float16"`` (half the size); ``"int8"`` (a quarter: conv and
            linear weights rounded to 255 levels per output channel, the rest float16). Scores
            can shift slightly with either; the sensor's θ is always kept in full precision.
    """
    from ..checks import check_choice

    check_choice(weights, WEIGHTS, "weights")
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
    from .. import __version__

    data = {
        "format": FORMAT if scales else READS[0],
        "task": task,
        "version": __version__,
        "layout": {"family": layout.family, **layout.to_config()},
        "size_hw": list(model.sensor.size),
        "sensor": dict(sensor),
        "training": dict(training),
        "state_dict": state,
    } | ({"quantized": scales} if scales else {})
    buf = io.BytesIO()
    torch.save(data, buf)
    return atomic_write(path, buf.getvalue())


def run_name(family: str, size: Sequence[int], seed: int) -> str:
    """The name of one training run in file names: ``<family>_<W>x<H>_seed<s>``."""
    return f"{family}_{size[1]}x{size[0]}_seed{seed}"


def save_run_model(
    folder: str | Path, task: str, family: str, size: Sequence[int], seed: int, model: nn.Module, **info: Any
) -> Path:
    """Save a training run's model as ``folder/model_<run name>.pt`` (``info``: ``sensor`` and
    the training record, as :func:`save_model`)."""
    path = Path(folder) / f"model_{run_name(family, size, seed)}.pt"
    training = {"family": family, "seed": seed, **info.get("training", {})}
    return save_model(path, task, model, sensor=info["sensor"], training=training)


def load_model(
    path: str | Path, task: str | None = None, device: str | torch.device = "cpu"
) -> tuple[nn.Module, dict[str, Any]]:
    """Rebuild a network from a model file (in eval mode, its layout fixed).

    Args:
        path: a file written by :func:`save_model`.
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
    except Exception as exc:  # pickle, zip and torch errors alike: not a model file
        raise ValueError(f"{path}: not a readable layoutwarp model file ({type(exc).__name__})") from None
    fmt = data.get("format") if isinstance(data, dict) else None
    if fmt not in READS:
        what = f"format {fmt!r}" if isinstance(fmt, str) else "no model format"
        raise ValueError(f"{path}: {what}; this layoutwarp reads {' and '.join(map(repr, READS))}")
    if task is not None and data.get("task") != task:
        raise ValueError(f"{path}: a {data.get('task')!r} model, not a {task!r} model")
    spec = dict(data["layout"])
    family = spec.pop("family", None)
    if family not in FAMILIES:
        raise ValueError(f"{path}: unknown layout family {family!r}")
    layout = FAMILIES[family].from_config(spec)
    net = _network(data["task"])(layout, tuple(data["size_hw"]), learn=False, **data["sensor"])
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


def evaluate_model(task: str, model: nn.Module, data_dir: str | Path, split: str | None = None) -> dict:
    """Score a model on a folder laid out like the task's training data.

    * MNIST: IDX files; ``split`` ``"test"`` (default, ``t10k-*``) or ``"train"``;
    * CamVid: ``NAME/`` images and ``NAMEannot/`` label maps, ``split`` = NAME (default ``"val"``);
      mIoU, pixel accuracy and per-class IoU (percent) at full resolution;
    * faces: images and ``labels.csv`` (every face listed; ``split`` must not be given).
    """
    from .data import load_camvid, load_faces, load_mnist_split

    if task == "mnist":
        from .mnist import evaluate

        images, labels = load_mnist_split(data_dir, split or "test")
        return {"n": len(images), "accuracy": evaluate(model, images, labels)}
    if task == "camvid":
        from .camvid import evaluate_camvid

        val = load_camvid(data_dir, split or "val")
        return {"n": len(val[0]), **evaluate_camvid(model, val)}
    if split is not None:
        raise ValueError(
            f"--split: a faces folder has no splits (every face in labels.csv is scored), got {split!r}"
        )
    from .faces import FaceNet, evaluate_faces

    faces = load_faces(data_dir)
    x = torch.from_numpy(np.ascontiguousarray(faces["images"])).permute(0, 3, 1, 2)
    return {
        "n": len(x),
        **evaluate_faces(model, x, {k: torch.from_numpy(faces[k]).long() for k in FaceNet.HEADS}),
    }
