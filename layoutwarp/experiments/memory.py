"""The benchmark's memory figures: the growth of the resident set over one call, measured in a
spawned child (a forked one would deadlock in torch's thread pool)."""

from __future__ import annotations

import multiprocessing as mp
import os

import cv2
import numpy as np
import torch

from .. import resampler
from ..layoutfile import layout_from_spec
from ..maps import forward_maps
from ..sensor import simulate
from .scene import blurred_noise

__all__ = ["memory_child", "peak_memory_mb", "status_mb"]


def status_mb(key: str) -> float:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(key + ":"):
                return int(line.split()[1]) / 1024
    raise KeyError(key)


def memory_child(spec: dict, conn) -> None:  # pragma: no cover - runs in a spawned process
    torch.set_num_threads(spec["threads"])
    if "cache_size" in spec:  # how many fixed layouts' area weights simulate keeps
        resampler.RESAMPLERS.maxsize = spec["cache_size"]
    img = blurred_noise(*spec["src"])
    npimg = np.ascontiguousarray(img[0].permute(1, 2, 0).numpy())
    layout = layout_from_spec(spec["layout"])
    maps = forward_maps(layout, spec["size"], spec["src"]).numpy() if spec["method"] == "remap" else None
    if spec["method"] not in ("inter_area", "remap"):  # load the code (compiled kernels) once, on a
        with torch.no_grad():  # small image and sensor: the measured call builds its own mesh
            simulate(blurred_noise(48, 64), layout, (5, 7), spec["method"], **spec["opts"])
    with open("/proc/self/clear_refs", "w") as f:
        f.write("5")  # reset the peak resident set (VmHWM) to the current one
    before = status_mb("VmRSS")
    with torch.no_grad():
        if spec["method"] == "inter_area":
            cv2.resize(npimg, spec["size"][::-1], interpolation=cv2.INTER_AREA)
        elif maps is not None:
            cv2.remap(npimg, maps[0], maps[1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        else:
            simulate(img, layout, spec["size"], spec["method"], **spec["opts"])
    conn.send(status_mb("VmHWM") - before)
    conn.close()


def peak_memory_mb(spec: dict) -> float | None:
    """Growth of the resident set over one forward call, in MiB, in a fresh spawned process.

    The child first runs the method once on a small image and sensor, so that loading code
    (the compiled kernels) is not counted; the measured call builds its mesh and tables anew.

    ``spec`` names the run: ``layout`` (a [`layout_from_spec`][] dict), ``method`` (a
    [`simulate`][] method, ``"inter_area"`` or ``"remap"``), ``opts``, ``src``, ``size``,
    ``threads``, and optionally ``cache_size`` (the ``maxsize`` of
    [`RESAMPLERS`][layoutwarp.resampler.RESAMPLERS]). (A forked child would deadlock in torch's
    thread pool.)
    """
    if not os.path.exists("/proc/self/clear_refs"):
        return None
    ctx = mp.get_context("spawn")
    parent, child = ctx.Pipe()
    proc = ctx.Process(target=memory_child, args=(spec, child))
    proc.start()
    value = parent.recv() if parent.poll(900) else None
    proc.join()
    return value
