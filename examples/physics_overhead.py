"""What sensor physics adds to a fixed layout's forward, and that forward against INTER_AREA.

Times four calls in the bench's interleaved rounds (``interleaved_times``: each round calls
every one once, so all meet the same machine state, and the rounds take the calls' 24 orders
in turn, so each follows each other as often, a call after OpenCV's spinning threads being
slower): ``cv2.resize(INTER_AREA)``, ``simulate`` of a
fixed curv layout (its cached area weights), the same with ``allow_nonfinite=True`` (no check
for NaN/Inf) and the same with the bench's camera (shot and read noise, full well, 12-bit ADC),
on a random 2048x1024 RGB image to a 257x129 sensor, and prints the medians, their ratio for
``simulate`` against INTER_AREA and, for the finiteness check and the physics, the median of
each round's ratio against ``simulate`` (both calls of a round meet the same machine state,
which drifts by 1.5x within seconds on small virtual machines), as ``layoutwarp bench`` does.
Run: ``python examples/physics_overhead.py [--rounds 60] [--threads 2]``.
"""

from __future__ import annotations

import argparse
import statistics

import cv2
import numpy as np
import torch

import layoutwarp as lw
from layoutwarp.experiments.bench import BENCH_PHYSICS, interleaved_times


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=60, help="interleaved rounds (default 60)")
    parser.add_argument("--threads", type=int, default=2, help="torch and OpenCV threads (default 2)")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    cv2.setNumThreads(args.threads)
    img = torch.rand(1, 3, 1024, 2048, generator=torch.Generator().manual_seed(0))
    hwc = np.ascontiguousarray(img[0].permute(1, 2, 0).numpy())
    camera = lw.SensorPhysics(sensor_um=(2800.0, 5600.0), **BENCH_PHYSICS)
    layout = lw.make_layout("curv", (0.35, 0.25))
    calls = {
        "INTER_AREA": lambda: cv2.resize(hwc, (257, 129), interpolation=cv2.INTER_AREA),
        "simulate": lambda: lw.simulate(img, layout, (129, 257)),
        "no finiteness check": lambda: lw.simulate(img, layout, (129, 257), allow_nonfinite=True),
        "simulate + physics": lambda: lw.simulate(img, layout, (129, 257), physics=camera),
    }
    with torch.no_grad():  # the warm-up call compiles, builds and caches the area weights
        times = dict(zip(calls, interleaved_times(list(calls.values()), args.rounds), strict=True))
    ms = {name: statistics.median(t) for name, t in times.items()}
    for name, value in ms.items():
        print(f"{name:20s} {value:7.2f} ms")
    print(f"simulate / INTER_AREA: {ms['simulate'] / ms['INTER_AREA']:.2f}x")

    def over(slow: str, fast: str) -> float:  # % that `slow` takes over `fast`, the rounds' median
        return 100 * (statistics.median([q / p for p, q in zip(times[fast], times[slow], strict=True)]) - 1)

    print(f"finiteness check: {over('simulate', 'no finiteness check'):+.1f} % (the same median)")
    print(f"physics overhead: {over('simulate + physics', 'simulate'):+.1f} % (median of the rounds' ratios)")


if __name__ == "__main__":
    main()
