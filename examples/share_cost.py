"""What a second thread gains a fixed layout's product, by image size: the basis of
``kernels.base.SMALL_WORK``, the work from which a kernel hands a share to a second thread.

For each source size (RGB float32 → a fixed curv layout's sensor, a pixel spanning 8x8 or 4x4
source cells), the median µs of the compiled product (``kernels.runs_apply`` on the kept runs) on
one thread and on two, each call right after a small torch op (as in a pipeline, where torch's
OpenMP threads are awake), and what ``kernels.threads`` chooses for it. With ``--learnable``, a
learnable curv layout's training step (forward, a convolution, backward) at mid sizes instead,
with ``SMALL_WORK`` at 2^18 and at 2^20 in interleaved rounds.

    python examples/share_cost.py [--rounds 7] [--learnable]
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable

import numpy as np
import torch

import layoutwarp as lw
from layoutwarp import kernels
from layoutwarp.resampler import AreaResampler

CASES = [((128, 128), (16, 16)), ((200, 200), (25, 25)), ((256, 256), (32, 32)), ((256, 512), (65, 129)),
         ((360, 480), (72, 96)), ((512, 512), (64, 64)), ((1024, 1024), (128, 128))]  # fmt: skip


def median_us(call, rounds: int, n: int = 100) -> float:
    """Median over ``rounds`` of the mean µs of ``n`` calls (after ten warm-up calls)."""
    for _ in range(10):
        call()
    times = []
    for _ in range(rounds):
        t0 = time.perf_counter()
        for _ in range(n):
            call()
        times.append((time.perf_counter() - t0) / n)
    return float(np.median(times)) * 1e6


def _product(
    arrays: tuple, x: np.ndarray, out: np.ndarray, threads: int, awake: torch.Tensor
) -> Callable[[], None]:
    """A call of the product on ``threads`` threads, right after a small torch op."""

    def call() -> None:
        awake.mul_(1.0)
        kernels.runs_apply(arrays, x, out, threads)

    return call


LEARNABLE = [((360, 480), (72, 96), 1), ((360, 480), (45, 60), 2), ((256, 512), (65, 129), 1),
             ((128, 128), (16, 16), 4)]  # fmt: skip


def _training_step(x: torch.Tensor, layout: lw.Layout, size: tuple[int, int]) -> Callable[[], None]:
    """A training step of ``layout`` on ``x``: the sensor, a convolution, a loss, the backward."""
    conv = torch.nn.Conv2d(3, 4, 3, padding=1)

    def step() -> None:
        conv(lw.simulate(x, layout, size)).square().mean().backward()

    return step


def learnable_steps(rounds: int) -> None:
    """Median ms of a learnable step with ``SMALL_WORK`` at 2^18 and at 2^20, rounds alternating."""
    for src, size, batch in LEARNABLE:
        x = torch.rand(batch, 3, *src, generator=torch.Generator().manual_seed(0))
        step = _training_step(x, lw.CurvLayout((0.3, -0.24), learn=True), size)
        for _ in range(3):
            step()
        times: dict[int, list[float]] = {1 << 18: [], 1 << 20: []}
        for r in range(2 * rounds):
            for small in (1 << 18, 1 << 20) if r % 2 else (1 << 20, 1 << 18):
                kernels.base.SMALL_WORK = small
                t0 = time.perf_counter()
                step()
                step()
                times[small].append((time.perf_counter() - t0) / 2 * 1e3)
        now, before = (float(np.median(times[s])) for s in (1 << 18, 1 << 20))
        print(f"learnable {src[1]}x{src[0]} -> {size[1]}x{size[0]}, batch {batch}: 2^18 {now:.2f} ms, "
              f"2^20 {before:.2f} ms ({now / before:.2f}x)")  # fmt: skip
    kernels.base.SMALL_WORK = 1 << 18


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rounds", type=int, default=7, help="rounds of 100 calls (default: 7)")
    parser.add_argument("--learnable", action="store_true", help="a learnable step at mid sizes instead")
    args = parser.parse_args()
    torch.set_num_threads(2)
    if args.learnable:
        learnable_steps(args.rounds)
        return
    awake = torch.rand(200_000)
    print(f"team: {kernels.base.team_name()}; SMALL_WORK = {kernels.base.SMALL_WORK} elements")
    for src, size in CASES:
        res = AreaResampler(lw.CurvLayout((0.5, 0.3)), size, src)
        x = np.random.default_rng(0).random((3, src[0] * src[1]), dtype=np.float32)
        out = np.empty((3, size[0] * size[1]), np.float32)
        t = {nt: median_us(_product(res.runs.arrays(), x, out, nt, awake), args.rounds) for nt in (1, 2)}
        chosen = kernels.threads(x.size)
        print(f"{src[1]}x{src[0]} -> {size[1]}x{size[0]} ({x.size} elements): one thread {t[1]:.0f} µs, "
              f"two {t[2]:.0f} µs ({t[1] / t[2]:.2f}x); chosen: {chosen}")  # fmt: skip


if __name__ == "__main__":
    main()
