"""What runs here: the versions, which backend each path takes and why, and where compiled code
lives (``layoutwarp doctor``; [`backends`][] is the one line the bench and every results file
record, so a silent fallback to a slower path shows in the numbers it produced)."""

from __future__ import annotations

import importlib.metadata
import os
import platform
import sys
import warnings
from pathlib import Path
from typing import Any

from . import jit, kernels
from .version import __version__

__all__ = ["RANK_SEEDS", "backends", "cpu_backend", "cuda_backend", "report", "run_info", "world"]

#: The distributions whose versions the report lists (absent ones say so).
PACKAGES = ("torch", "numpy", "numba", "numba-cuda", "kornia", "opencv-contrib-python-headless", "scipy")


def _version(name: str) -> str | None:
    try:
        return importlib.metadata.version(name)
    except importlib.metadata.PackageNotFoundError:
        return None


def cpu_backend() -> str:
    """The CPU paths' backend: compiled kernels (and how many threads), or the torch path and why."""
    if not kernels.available():
        return "torch (numba is not installed)"
    if jit.mode() == "off":
        return f"torch ({jit.ENV}=off)"
    team = "torch's OpenMP" if kernels.base.team_name() == "openmp" else "Python"
    return f"compiled (numba, {kernels.threads()} threads, {team} ones; {jit.ENV}={jit.mode()})"


def cuda_backend(probe: bool = True) -> str:
    """The CUDA paths' backend: compiled CUDA kernels, the torch path and why, or no GPU.
    ``probe=False``: without compiling the CUDA kernels to find out (tens of seconds from an empty
    cache): what this process's CUDA calls found, if any made one."""
    import torch

    if not torch.cuda.is_available():
        return "no CUDA GPU"
    if not kernels.available():
        return "torch (numba is not installed)"
    if not probe and "float32" not in kernels.cuda_checked():
        return f"not used yet in this process ({torch.cuda.get_device_name()})"
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        ok = kernels.cuda_available("float32")
    if ok:
        line = f"compiled (numba-cuda {_version('numba-cuda')}) on {torch.cuda.get_device_name()}"
        failed = kernels.device.FAILED  # kernels that failed since: their calls take torch's path
        return line + "".join(f"; torch for {name} ({why})" for name, why in failed.items())
    reason = str(caught[-1].message).removeprefix("layoutwarp: ") if caught else "no numba CUDA target"
    return f"torch ({reason})"


def backends() -> str:
    """One line: the versions that matter and each path's backend (what results files record;
    the CUDA kernels are not compiled to find out)."""
    found = {n: _version(n) for n in ("torch", "numpy", "numba")}
    versions = ", ".join(f"{n} {v}" for n, v in found.items() if v)
    cuda = cuda_backend(probe=False)
    return f"python {platform.python_version()}, {versions}; cpu: {cpu_backend()}; cuda: {cuda}"


def report() -> str:
    """The full report of ``layoutwarp doctor``."""
    lines = [f"layoutwarp {__version__}, python {platform.python_version()} ({platform.machine()})"]
    lines += [f"  {name:<32} {_version(name) or 'not installed'}" for name in PACKAGES]
    lines += [f"CPU:  {cpu_backend()}", f"CUDA: {cuda_backend()}"]
    folder = jit.cache_folder()
    lines.append(f"compiled kernels: {folder or 'none (numba is not installed)'}")
    if folder:
        states = jit.status()
        lines += [f"  {unit:<16} {state}" for unit, state in states.items()]
        if "not compiled" in states.values():
            lines.append("  (compiled in the background at first use, or now: layoutwarp doctor --compile)")
    return "\n".join(lines)


#: How far apart the ranks of a process group start their seeds (rank ``r``: ``seed + r ·
#: RANK_SEEDS``): a [`SensorLayer`][layoutwarp.sensor.SensorLayer]'s seeded noise, and a training
#: run's generator once its network is built, so each rank draws noise of its own for its share of
#: the batch, as one process draws it anew for every image.
RANK_SEEDS = 1_000_000_007


def world() -> tuple[int, int]:
    """``(rank, world size)`` of this process in torch.distributed's default process group (one
    ``torchrun`` set up and the process joined, e.g. by
    [`init_distributed`][layoutwarp.experiments.training.init_distributed]), else ``(0, 1)``.
    Starts nothing."""
    import torch.distributed as dist

    if dist.is_available() and dist.is_initialized():
        return dist.get_rank(), dist.get_world_size()
    return 0, 1


def run_info(device: Any = None, seeds: Any = None) -> dict[str, Any]:
    """How a run ran, for every record that reports numbers (results, studies, benchmarks,
    preprocessing manifests), so a number can be traced and rerun.

    Returns:
        the layoutwarp, torch, numba, NumPy and Python versions, the machine, ``device``, torch's
        thread count, the world size and rank under ``torchrun`` (1 and 0 alone), the command
        line, ``seeds``, and which backend each path took ([`backends`][]).
    """
    import numpy as np
    import torch

    try:
        from importlib.metadata import version

        numba = version("numba")
    except Exception:  # not installed: the torch paths ran
        numba = None
    return {
        "layoutwarp": __version__,
        "torch": str(torch.__version__),
        "numba": numba,
        "numpy": np.__version__,
        "python": platform.python_version(),
        "machine": f"{platform.system()} {platform.machine()}",
        "device": None if device is None else str(device),
        "threads": torch.get_num_threads(),
        "world_size": int(os.environ.get("WORLD_SIZE", "1")),
        "rank": int(os.environ.get("RANK", "0")),
        "command": " ".join([Path(sys.argv[0]).name, *sys.argv[1:]]) if sys.argv else None,
        "backends": backends(),
        "seeds": seeds,
    }
