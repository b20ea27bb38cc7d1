"""What a busy machine costs: the README example and a learnable training step, quiet and beside
one and three busy processes, as ratios of their quiet times.

The script starts the busy processes itself (plain Python loops, one core's worth each) and
stops them after each measurement. The README example runs as a user runs it, a fresh process
(with the kernels already in the cache); the step is a learnable curv layout with mixed-sign θ,
2048x1024 RGB to 257x129, forward and backward, timed in this process (median of ``--steps``).
Each setting is measured ``--repeats`` times, interleaved (quiet, one busy, three busy, ...), and
the medians are printed. Sharing the cores fairly would cost about ``(n + k) / n`` where the work
runs on ``n`` of them beside ``k`` busy processes: 1.5x and 2.5x on 2 cores.

With ``--empty-cache`` it measures instead what a new installation meets: ``layoutwarp train
mnist --quick`` (the README's main job) from an empty kernel cache (a fresh ``NUMBA_CACHE_DIR``
each time, so its kernels compile in the background while it trains), quiet and beside three
busy processes.

Run: ``python examples/busy_machine.py [--repeats 3] [--steps 5] [--json FILE] [--empty-cache]``.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from contextlib import contextmanager
from pathlib import Path

import torch

import layoutwarp as lw
from layoutwarp.experiments.firstcalls import README_EXAMPLE

BUSY = "while True:\n    pass\n"


@contextmanager
def busy(count: int):
    """``count`` busy processes for the duration."""
    procs = [subprocess.Popen([sys.executable, "-c", BUSY]) for _ in range(count)]
    time.sleep(0.5 if count else 0)  # running before the measurement starts
    try:
        yield
    finally:
        for p in procs:
            p.kill()
        for p in procs:
            p.wait()


def readme_seconds() -> float:
    """The README example's total, import included, in a fresh process (seconds)."""
    res = subprocess.run([sys.executable, "-c", README_EXAMPLE], capture_output=True, text=True, check=True)
    return json.loads(res.stdout.strip().splitlines()[-1])["total"]


def train_from_empty_seconds() -> float:
    """``layoutwarp train mnist --quick`` from an empty kernel cache, in a fresh process (seconds)."""
    with tempfile.TemporaryDirectory() as tmp:
        env = {**os.environ, "NUMBA_CACHE_DIR": os.path.join(tmp, "cache"), lw.jit.ENV: "background"}
        out = os.path.join(tmp, "run")
        cmd = [sys.executable, "-m", "layoutwarp", "train", "mnist", "--quick", "--out", out]
        t = time.perf_counter()
        subprocess.run(cmd, env=env, capture_output=True, text=True, check=True)
        return time.perf_counter() - t


def empty_cache(repeats: int, json_file: str | None) -> None:
    """The ``--empty-cache`` measurement (see the module docstring)."""
    times: dict[int, list[float]] = {0: [], 3: []}
    for r in range(repeats):
        for k in times:
            with busy(k):
                times[k].append(train_from_empty_seconds())
            print(f"round {r + 1}/{repeats}, {k} busy: {times[k][-1]:.1f} s", file=sys.stderr, flush=True)
    quiet = statistics.median(times[0])
    print(f"{os.cpu_count()} cores; train mnist --quick from an empty cache, medians of {repeats}")
    for k, ts in times.items():
        print(f"{k:>3} busy: {statistics.median(ts):6.1f} s  {statistics.median(ts) / quiet:5.2f}x")
    if json_file:
        Path(json_file).write_text(json.dumps({"cores": os.cpu_count(), "train_s": times}, indent=2))


def step_ms(img: torch.Tensor, layout: lw.Layout, steps: int) -> float:
    """A learnable step's median over ``steps`` calls (ms), after one untimed call."""
    times = []
    for k in range(steps + 1):
        t = time.perf_counter()
        lw.simulate(img, layout, (129, 257)).sum().backward()
        layout.rho.grad = None
        if k:
            times.append((time.perf_counter() - t) * 1e3)
    return statistics.median(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3, help="measurements of each setting (default 3)")
    parser.add_argument("--steps", type=int, default=5, help="timed steps a measurement (default 5)")
    parser.add_argument("--json", metavar="FILE", help="also write the numbers to this JSON file")
    parser.add_argument(
        "--empty-cache", action="store_true", help="train mnist --quick from an empty kernel cache instead"
    )
    args = parser.parse_args()
    if args.empty_cache:
        empty_cache(args.repeats, args.json)
        return
    lw.jit.set_mode("wait")  # the compiled kernels, loaded from the cache (compiled first if need be)
    img = torch.rand(1, 3, 1024, 2048, generator=torch.Generator().manual_seed(0))
    layout = lw.CurvLayout((0.3, -0.24), learn=True)
    readme_seconds()  # the cache filled and the files read once before anything is timed
    step_ms(img, layout, 1)
    settings = (0, 1, 3)
    readme: dict[int, list[float]] = {k: [] for k in settings}
    step: dict[int, list[float]] = {k: [] for k in settings}
    for r in range(args.repeats):
        for k in settings:
            with busy(k):
                readme[k].append(readme_seconds())
                step[k].append(step_ms(img, layout, args.steps))
            print(
                f"round {r + 1}/{args.repeats}, {k} busy: README example {readme[k][-1]:.2f} s, "
                f"step {step[k][-1]:.0f} ms",
                file=sys.stderr,
                flush=True,
            )
    cores = os.cpu_count() or 1
    out = {"cores": cores, "threads": torch.get_num_threads(), "settings": {}}
    print(f"{cores} cores, torch threads {torch.get_num_threads()}; medians of {args.repeats}")
    print(f"{'busy processes':>15} {'README example':>16} {'ratio':>6} {'learnable step':>15} {'ratio':>6}")
    for k in settings:
        rm, sm = statistics.median(readme[k]), statistics.median(step[k])
        r0, s0 = statistics.median(readme[0]), statistics.median(step[0])
        out["settings"][k] = {"readme_s": rm, "readme_ratio": rm / r0, "step_ms": sm, "step_ratio": sm / s0}
        print(f"{k:>15} {rm:>14.2f} s {rm / r0:>5.2f}x {sm:>12.0f} ms {sm / s0:>5.2f}x")
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
