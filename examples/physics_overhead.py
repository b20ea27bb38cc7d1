"""What sensor physics adds to a fixed layout's forward, and that forward against INTER_AREA.

Times three calls in interleaved rounds (each round calls every one once, so all three meet the
same machine state; the order rotates round by round, so each follows each other as often, a
call after OpenCV's spinning threads being slower): ``cv2.resize(INTER_AREA)``, ``simulate`` of a
fixed curv layout (its cached area weights) and the same with the bench's camera (shot and read
noise, full well, 12-bit ADC), on a random 2048x1024 RGB image to a 257x129 sensor, and prints
the medians, their ratio for ``simulate`` against INTER_AREA and, for the physics, the median of
each round's ratio (both calls of a round meet the same machine state, which drifts by 1.5x
within seconds on small virtual machines), as ``layoutwarp bench`` does.
Run: ``python examples/physics_overhead.py [--rounds 60] [--threads 2]``.
"""

from __future__ import annotations

import argparse
import statistics
import time

import cv2
import numpy as np
import torch

import layoutwarp as lw
from layoutwarp.experiments.bench import BENCH_PHYSICS


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
        "simulate + physics": lambda: lw.simulate(img, layout, (129, 257), physics=camera),
    }
    times: dict[str, list[float]] = {name: [] for name in calls}
    with torch.no_grad():
        for call in calls.values():  # warm-up: compiles, builds and caches the area weights
            call()
        names = list(calls)
        for k in range(args.rounds):  # each round in a rotated order: every call follows each other
            for name in names[k % 3 :] + names[: k % 3]:
                t0 = time.perf_counter()
                calls[name]()
                times[name].append(1e3 * (time.perf_counter() - t0))
    ms = {name: statistics.median(t) for name, t in times.items()}
    for name, value in ms.items():
        print(f"{name:20s} {value:7.2f} ms")
    print(f"simulate / INTER_AREA: {ms['simulate'] / ms['INTER_AREA']:.2f}x")
    ratios = [q / p for p, q in zip(times["simulate"], times["simulate + physics"], strict=True)]
    print(f"physics overhead: {100 * (statistics.median(ratios) - 1):+.1f} % (median of the rounds' ratios)")


if __name__ == "__main__":
    main()
