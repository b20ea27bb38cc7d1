"""What runs here: the versions, which backend each path takes and why, and where compiled code
lives (``layoutwarp doctor``; [`backends`][] is the one line the bench and every results file
record, so a silent fallback to a slower path shows in the numbers it produced)."""

from __future__ import annotations

import importlib.metadata
import platform
import warnings

from . import jit, kernels

__all__ = ["backends", "cpu_backend", "cuda_backend", "report"]

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
    return f"compiled (numba, {kernels.threads()} threads; {jit.ENV}={jit.mode()})"


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
    from .version import __version__

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
