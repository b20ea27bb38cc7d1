"""Compiled kernels (numba; no compiler needed on the user's machine), one file per idea:

- [`exact`][layoutwarp.kernels.exact]: the exact integrator, prefix tables, forward and
  backward on the CPU, and the same per-segment functions as CUDA kernels;
- [`mesh`][layoutwarp.kernels.mesh]: the pixel meshes of the built-in curved families with
  every vertex's θ-derivative, on the CPU or built on a CUDA device;
- [`runs`][layoutwarp.kernels.runs]: a fixed layout's product with its area weights, held as runs
  of whole cells and cut cells; [`weights`][layoutwarp.kernels.weights] builds them from its mesh;
- [`noise`][layoutwarp.kernels.noise]: the sensor's measurement (noise, full well, ADC);
- [`device`][layoutwarp.kernels.device]: numba's CUDA target, and every CUDA launch;
- [`base`][layoutwarp.kernels.base]: what they share (numba, the decorators, the threads that run
  a kernel's shares).

Compiled code is cached on disk (``cache=True``): a second process loads it instead of
compiling again. numba invalidates a cache only when the function's own file changes, and the
kernels inline functions of other files of this package (the mesh kernels the exact
integrator's per-segment functions) and read ``layoutwarp.mesh``'s constants: on import, the
digest of all those sources is compared with the one kept in the cache folder, and where it
differs (an edited source, a ``git checkout``) the compiled kernels kept there are deleted, so that
numba compiles them again ([`renew_stale_caches`][layoutwarp.kernels.base.renew_stale_caches]).
[`available`][layoutwarp.kernels.base.available] says whether numba is installed;
without it the torch reference runs. This package's namespace holds the names the rest of
layoutwarp calls; [`mesh`][layoutwarp.kernels.mesh] (which imports torch) is imported on its own.
"""

from __future__ import annotations

from .base import CHUNK, available, retain_freed_memory, run_shares, threads
from .device import CUDA_THREADS, cuda_available, cuda_checked, cuda_launch, cuda_ptx
from .exact import (
    WHOLE_TABLE_BYTES,
    band_rows,
    exact_backward,
    exact_forward,
    exact_forward_banded,
)
from .exact import (
    segment_moments_from_python as segment_moments,
)
from .noise import sensor_measure, sensor_measure_plain
from .prefix import BLOCK, prefix_tables
from .runs import measured_runs_apply, runs_apply
from .weights import build_runs


def cache_folder() -> str | None:
    """Where numba keeps this installation's compiled kernels (``None`` without numba): this
    package's ``__pycache__`` (the mesh kernels' in ``mesh/__pycache__`` beneath it), or its place
    under ``NUMBA_CACHE_DIR`` (the mesh kernels' beside it)."""
    return getattr(getattr(segment_moments, "_cache", None), "_cache_path", None)


if available():  # before any kernel loads its cache (at its first call)
    from .base import renew_stale_caches

    renew_stale_caches(cache_folder())

__all__ = [
    "BLOCK",
    "CHUNK",
    "CUDA_THREADS",
    "WHOLE_TABLE_BYTES",
    "available",
    "band_rows",
    "build_runs",
    "cache_folder",
    "cuda_available",
    "cuda_checked",
    "cuda_launch",
    "cuda_ptx",
    "exact_backward",
    "exact_forward",
    "exact_forward_banded",
    "measured_runs_apply",
    "prefix_tables",
    "retain_freed_memory",
    "run_shares",
    "runs_apply",
    "segment_moments",
    "sensor_measure",
    "sensor_measure_plain",
    "threads",
]
