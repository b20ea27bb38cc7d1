"""How the benchmark times a call and measures its memory: medians after a warm-up, interleaved
rounds (every call once a round, so all meet the same machine state), a device's work waited
for, and a GPU's peak allocated memory."""

from __future__ import annotations

import itertools
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
from torch import Tensor

__all__ = [
    "cuda_peak_mb",
    "interleaved_times",
    "sync",
    "time_backward",
    "time_call",
    "time_overhead",
    "time_paired",
]


def sync() -> None:
    """Wait for queued GPU work, so that a timed call is really done (a no-op without CUDA)."""
    if torch.cuda.is_available():
        torch.cuda.synchronize()


def time_paired(fns: Sequence[Callable[[], object]], repeats: int) -> list[float]:
    """Median ms of each of ``fns`` over the rounds of [`interleaved_times`][]."""
    return [float(np.median(col)) for col in interleaved_times(fns, repeats)]


def time_overhead(
    base: Callable[[], object], other: Callable[[], object], rounds: int
) -> tuple[float, float, float]:
    """``other`` against ``base`` over [`interleaved_times`][]' rounds: the median ms of each,
    and how much longer ``other`` takes as the median of the rounds' ratios minus 1 (both calls
    of a round meet the same machine state)."""
    times = interleaved_times([base, other], rounds)
    t_base, t_other = (float(np.median(col)) for col in times)
    return t_base, t_other, float(np.median(np.divide(times[1], times[0]))) - 1


def interleaved_times(fns: Sequence[Callable[[], object]], rounds: int) -> list[list[float]]:
    """Time calls that are to be compared, in interleaved rounds: ``times[i][k]``, the ms of
    ``fns[i]`` in round ``k`` (``max(rounds, 1)`` rounds, after one warm-up call each).

    Every round calls each of ``fns`` once, so the calls of a round meet the same machine state
    (on a small virtual machine the speed drifts by 1.5x within seconds): compare two calls by
    the median of their rounds' ratios. Round ``k`` takes the ``k``-th of the calls' orders (all
    of them in turn), so each call follows each other as often: what a call leaves behind
    (caches, another pool's spinning threads) is shared alike, which a rotation of one order,
    keeping every call's predecessor, would not do."""
    for fn in fns:
        fn()
    orders = list(itertools.permutations(range(len(fns))))
    times: list[list[float]] = [[] for _ in fns]
    for k in range(max(rounds, 1)):
        for i in orders[k % len(orders)]:
            times[i].append(time_call(fns[i], 0))
    return times


def time_call(fn: Callable[[], object], repeats: int) -> float:
    """Median ms of ``repeats`` calls after a warm-up (``repeats = 0``: one call, no warm-up)."""
    if repeats == 0:
        sync()
        t0 = time.perf_counter()
        fn()
        sync()
        return (time.perf_counter() - t0) * 1e3
    fn()
    times = []
    for _ in range(repeats):
        sync()
        t0 = time.perf_counter()
        fn()
        sync()
        times.append(time.perf_counter() - t0)
    return float(np.median(times) * 1e3)


def time_backward(forward: Callable[[], Tensor], layout: Any, repeats: int) -> float:
    """Median time (ms) of ``forward().sum().backward()``'s backward pass alone, after a warm-up
    (``layout``'s ρ gradient reset between calls)."""
    times = []
    for k in range(repeats + 1):
        loss = forward().sum()
        sync()
        t0 = time.perf_counter()
        loss.backward()
        sync()
        if k:
            times.append(time.perf_counter() - t0)
        layout.rho.grad = None
    return float(np.median(times) * 1e3)


def cuda_peak_mb(fn: Callable[[], object]) -> float:
    """Growth of allocated GPU memory (MiB) over what was allocated before ``fn`` ran, at its peak."""
    sync()
    torch.cuda.reset_peak_memory_stats()
    base = torch.cuda.memory_allocated()
    fn()
    sync()
    return (torch.cuda.max_memory_allocated() - base) / 2**20


@dataclass
class Row:
    """One measured configuration (times in ms, errors in image units, memory in MiB)."""

    image: str
    layout: str
    method: str
    setting: str
    forward_ms: float
    backward_ms: float | None = None
    rmse: float | None = None
    max_err: float | None = None
    scene_rmse: float | None = None
    grad_rel_err: float | None = None
    peak_mb: float | None = None
    extra: dict = field(default_factory=dict)
